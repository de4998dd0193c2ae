"""The REST service: app factory (``create_app``), shared dependencies, one router per resource
(``routes/``), the error mapping (``errors``: the packages' error roots to HTTP). Public names are
imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.lazy import lazy_getattr

if TYPE_CHECKING:
    from cellctl.api.app import create_app
    from cellctl.api.errors import OWN_ERRORS, ApiError, install_error_handlers

__all__ = [
    "ApiError",
    "OWN_ERRORS",
    "create_app",
    "install_error_handlers",
]

__getattr__ = lazy_getattr(__name__, {
    "create_app": "cellctl.api.app",
    "ApiError": "cellctl.api.errors",
    "OWN_ERRORS": "cellctl.api.errors",
    "install_error_handlers": "cellctl.api.errors",
})
"""Public names imported on first use (PEP 562): importing the package stays cheap and free of cycles."""
