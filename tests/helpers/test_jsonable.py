"""calibration.io.jsonable: numpy to JSON with one policy: a non-finite number is an error naming its key."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.io import NonFiniteError, dumps, to_jsonable


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


def test_the_cli_refuses_to_print_a_non_finite_result(capsys: pytest.CaptureFixture[str]) -> None:
    from cellctl.cli.output import emit

    emit({"rms_px": np.float64(0.5)})
    assert json.loads(capsys.readouterr().out) == {"rms_px": 0.5}
    with pytest.raises(NonFiniteError, match=r"\$\.uncertainty\.rot_deg"):
        emit({"uncertainty": {"rot_deg": float("nan")}})
    assert capsys.readouterr().out == ""  # nothing half-printed


def test_the_store_refuses_a_non_finite_result(tmp_path: Path) -> None:
    from cellctl.store.errors import InvalidInput
    from cellctl.store.store import Store

    with Store(f"sqlite:///{tmp_path}/cell.db", "cell-a") as store:
        rec = store.save_calibration("camera", "cam0", None, {"rms_px": np.float32(0.25), "K": np.eye(3)}, {},
                                     "tester")
        assert store.get_calibration(rec.id).result == {"rms_px": 0.25, "K": np.eye(3).tolist()}
        with pytest.raises(InvalidInput, match=r"cannot be stored as JSON: \$\.views\[0\]\.rms_px is nan"):
            store.save_calibration("camera", "cam0", None, {"views": [{"rms_px": np.nan}]}, {}, "tester")
        assert len(store.list_calibrations()) == 1
