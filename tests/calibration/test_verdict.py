"""Verdict rules: each problem fires on the data that should trigger it, and names what to do."""

from __future__ import annotations

import numpy as np

from calibration.verdict import assess, tilts_deg, uncovered_corners


def _ok_inputs() -> dict:
    cov = np.ones((12, 16), dtype=np.int64)
    normals = np.array([[np.sin(0.5), 0, np.cos(0.5)], [0, np.sin(0.5), np.cos(0.5)], [0, 0, 1.0]])
    return dict(n_views=12, size=(1280, 960), coverage=cov, normals=normals,
                sigmas={"fx": 1.0, "fy": 1.0, "cx": 0.5, "cy": 0.5},
                values={"fx": 1000.0, "fy": 1000.0, "cx": 640.0, "cy": 480.0},
                uncertainty={"projection_rms_px": 0.05})


def test_good_data_is_ok() -> None:
    v = assess(**_ok_inputs())
    assert v["ok"] and v["problems"] == []


def test_each_problem() -> None:
    a = _ok_inputs()
    a["n_views"] = 4
    assert [p["code"] for p in assess(**a)["problems"]] == ["too_few_views"]
    a = _ok_inputs()
    a["normals"] = np.array([[0, np.sin(0.5), np.cos(0.5)], [0, 0, 1.0]])
    probs = assess(**a)["problems"]
    assert [p["code"] for p in probs] == ["not_enough_tilt"]
    assert "vertical axis" in probs[0]["message"] and "horizontal axis" not in probs[0]["message"]
    a = _ok_inputs()
    a["coverage"][:3, -4:] = 0
    a["coverage"][-3:, :4] = 0
    probs = assess(**a)["problems"]
    assert probs[0]["code"] == "corners_not_covered"
    assert "top-right" in probs[0]["message"] and "bottom-left" in probs[0]["message"]
    assert "top-left" not in probs[0]["message"]
    a = _ok_inputs()
    a["sigmas"]["fx"] = 50.0
    probs = assess(**a)["problems"]
    assert probs[0]["code"] == "focal_poorly_determined" and "5.0%" in probs[0]["message"]
    a = _ok_inputs()
    a["sigmas"]["cy"] = 30.0
    assert assess(**a)["problems"][0]["code"] == "principal_point_poorly_determined"
    a = _ok_inputs()
    a["uncertainty"] = {"projection_rms_px": 2.0}
    assert assess(**a)["problems"][0]["code"] == "projection_uncertain"
    a = _ok_inputs()
    v = assess(**a, n_outlier_views=2)
    assert v["ok"] and v["advice"][0]["code"] == "outlier_views"


def test_tilt_and_corner_helpers() -> None:
    t = tilts_deg(np.array([[0, -np.sin(0.3), np.cos(0.3)], [np.sin(0.2), 0, np.cos(0.2)]]))
    assert np.allclose(t, np.degrees([[0.3, 0.0], [0.0, 0.2]]))
    cov = np.ones((9, 16), dtype=np.int64)
    assert uncovered_corners(cov) == []
    cov[:2, :3] = 0
    assert uncovered_corners(cov) == ["top-left"]
