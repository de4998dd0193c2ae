"""Public names of a package imported on first use (PEP 562), for the packages' curated ``__init__``.

A package's ``__init__`` lists its public names in ``__all__``, imports them for the type checker
under ``if TYPE_CHECKING:``, and hands the table of where each lives to :func:`lazy_getattr`::

    __getattr__ = lazy_getattr(__name__, {"SimRobot": "drivers.robot.sim", ...})

Importing the package then runs none of its modules (cheap, no import cycles, optional libraries
such as Aravis load only when asked for); the first ``package.Name`` imports the module and keeps
the value in the package. It lives in ``drivers`` so that both ``drivers`` and ``cellctl`` use the
one helper (``drivers`` imports no ``cellctl``); ``calibration`` and ``vision`` import their
modules eagerly and need none.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_getattr(package: str, table: Mapping[str, str]) -> Callable[[str], Any]:
    """The module ``__getattr__`` of ``package``: ``name`` from the module ``table[name]``, imported on
    first use and then kept in the package (later lookups do not come here); any other name raises
    ``AttributeError`` as a module does."""
    where = dict(table)

    def __getattr__(name: str) -> Any:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    return __getattr__
