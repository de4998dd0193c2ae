"""The REST service: app factory (``create_app``), shared dependencies, one router per resource
(``routes/``), the error mapping (``errors``: the packages' error roots to HTTP). Public names are
imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cellctl.api.app import create_app
    from cellctl.api.errors import OWN_ERRORS, ApiError, install_error_handlers

_LAZY: dict[str, str] = {
    "create_app": "cellctl.api.app",
    "ApiError": "cellctl.api.errors",
    "OWN_ERRORS": "cellctl.api.errors",
    "install_error_handlers": "cellctl.api.errors",
}
"""Public names imported on first use (PEP 562): importing the package stays cheap and free of cycles."""

__all__ = [
    "ApiError",
    "OWN_ERRORS",
    "create_app",
    "install_error_handlers",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
