"""calibration.jsonable: numpy to JSON with one policy: a non-finite number is an error naming its key."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.jsonable import NonFiniteError, dumps, to_jsonable


def test_numpy_arrays_scalars_tuples_and_keys_become_plain_json() -> None:
    value = {"K": np.eye(3), "n": np.int64(7), "ok": np.bool_(True), "rms_px": np.float32(0.25),
             "pair": (1, 2.5), 3: "three", "none": None}
    out = to_jsonable(value)
    assert out == {"K": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "n": 7, "ok": True,
                   "rms_px": 0.25, "pair": [1, 2.5], "3": "three", "none": None}
    assert type(out["n"]) is int and type(out["ok"]) is bool and type(out["rms_px"]) is float
    assert json.loads(dumps(value, indent=2)) == out


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -np.inf, np.float64("nan")])
def test_non_finite_numbers_are_refused_with_their_path(bad: float) -> None:
    with pytest.raises(NonFiniteError) as err:
        dumps({"views": [{"rms_px": 0.1}, {"rms_px": 0.2}, {"rms_px": bad}]})
    assert "$.views[2].rms_px" in str(err.value)


def test_non_finite_inside_an_array_is_refused() -> None:
    with pytest.raises(NonFiniteError, match=r"\$\.H\[1\]\[2\]"):
        to_jsonable({"H": np.array([[1.0, 0.0, 0.0], [0.0, 1.0, np.nan]])})


def test_what_json_cannot_hold_is_a_type_error() -> None:
    with pytest.raises(TypeError, match=r"\$\.when: object"):
        to_jsonable({"when": object()})
    assert issubclass(NonFiniteError, ValueError)
