"""Results to JSON: numpy arrays and scalars become lists and numbers; a non-finite number is an error.

One policy for every JSON that cellctl writes (result files, command output, stored results):
NaN and infinity are **refused**, not written as ``null`` and not as the non-standard ``NaN``. A
non-finite number in a result is a bug (or an unguarded degenerate case) upstream; a silent
``null`` hides it and a bare ``NaN`` breaks every strict JSON reader. The error names the key
path so the producer can be found. Where "no value" is a legitimate answer, the producer must
say so itself with ``None``.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from calibration import CalibrationError


class NonFiniteError(CalibrationError):
    """A result holds NaN or infinity where JSON needs a finite number."""


def to_jsonable(obj: Any, where: str = "$") -> Any:
    """``obj`` with numpy arrays/scalars and tuples turned into plain lists and numbers, keys into strings.

    Raises ``NonFiniteError`` naming the path (``$.views[3].rms_px``) of the first NaN or infinity,
    and ``TypeError`` for a value JSON cannot hold.
    """
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v, f"{where}.{k}") for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist(), where)
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item(), where)
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise NonFiniteError(f"{where} is {obj}: a result must hold finite numbers (a cellctl bug; report it)")
        return obj
    if obj is None or isinstance(obj, str | int | bool):
        return obj
    raise TypeError(f"{where}: {type(obj).__name__} is not JSON-serialisable")


def dumps(obj: Any, **kwargs: Any) -> str:
    """``json.dumps`` of ``to_jsonable(obj)`` (strict: no NaN/infinity); ``kwargs`` go to ``json.dumps``."""
    return json.dumps(to_jsonable(obj), allow_nan=False, **kwargs)
