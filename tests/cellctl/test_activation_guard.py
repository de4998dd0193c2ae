"""Guarded activation (INTERFACES §5): a calibration whose verdict is not ok needs ``{"force": true}``.

The store is filled before the service starts (a real SQLite store, the real app in-process):
one camera calibration whose verdict is not ok, one whose verdict is ok, and an n-point map (no
verdict for that kind).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from cellctl.config import default_config_text
from cellctl.store import Store, sqlite_url
from tests.support.app import AppCell, in_process_cell

CAMERA = {"model": "opencv5", "width": 1280, "height": 960,
          "K": [[1900.0, 0.0, 640.0], [0.0, 1900.0, 480.0], [0.0, 0.0, 1.0]], "dist": [0.0] * 5, "rms_px": 0.05}
PROBLEMS = [{"code": "too_few_views", "message": "3 views; calibrate with at least 10"},
            {"code": "tilt_too_small", "message": "largest tilt 4 deg; add views tilted 30-45 deg"}]


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AppCell, dict[str, int]]]:
    tmp = tmp_path_factory.mktemp("activation")
    db = tmp / "store.db"
    cfg = tmp / "cell.yaml"
    cfg.write_text(default_config_text().replace("path: null ", f"path: {db} "))
    with Store(sqlite_url(db), "virtual-cell") as store:
        ids = {
            "bad": store.save_calibration("camera", "cam0", None, {**CAMERA, "verdict": {
                "ok": False, "problems": PROBLEMS}}, {}, "test").id,
            "good": store.save_calibration("camera", "cam0", None, {**CAMERA, "verdict": {
                "ok": True, "problems": []}}, {}, "test").id,
            "npoint": store.save_calibration("npoint", "cam0", "robot0", {
                "model": "homography", "H": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "rms_mm": 0.1}, {}, "test").id,
        }
    with in_process_cell(tmp, config=cfg) as cell:
        yield cell, ids


def _active_camera(http: object, cal_id: int) -> bool:
    r = http.get(f"/calibrations/{cal_id}")  # type: ignore[attr-defined]
    assert r.status_code == 200
    return bool(r.json()["active"])


def test_not_ok_verdict_is_refused_with_its_problems(served: tuple[AppCell, dict[str, int]]) -> None:
    s, ids = served
    with s.http() as http:
        for body in (None, {}, {"force": False}):
            r = http.post(f"/calibrations/{ids['bad']}/activate", json=body)
            assert r.status_code == 409, r.text
            err = r.json()["error"]
            assert err["code"] == "verdict_not_ok"
            assert "too_few_views" in err["message"] and "tilt_too_small" in err["message"]
            assert '"force": true' in err["message"]
        assert not _active_camera(http, ids["bad"])


def test_ok_verdict_and_no_verdict_activate_without_force(served: tuple[AppCell, dict[str, int]]) -> None:
    s, ids = served
    with s.http() as http:
        for key in ("good", "npoint"):
            r = http.post(f"/calibrations/{ids[key]}/activate")
            assert r.status_code == 200, r.text
            assert r.json()["active"] is True


def test_force_activates_and_is_audited(served: tuple[AppCell, dict[str, int]],
                                       caplog: pytest.LogCaptureFixture) -> None:
    s, ids = served
    with s.http() as http:
        r = http.post(f"/calibrations/{ids['bad']}/activate", json={"force": True})
        assert r.status_code == 200, r.text
        assert r.json()["active"] is True
        assert not _active_camera(http, ids["good"])  # the forced one replaced it
        audit = http.get("/audit").json()
        forced = [e for e in audit if e["action"] == "calibration.force_activate"]
        assert len(forced) == 1
        assert forced[0]["target"] == f"calibration:{ids['bad']}"
        assert [p["code"] for p in forced[0]["detail"]["problems"]] == ["too_few_views", "tilt_too_small"]
        assert "although its verdict is not ok" in caplog.text


def test_unknown_keys_in_the_body_are_refused(served: tuple[AppCell, dict[str, int]]) -> None:
    s, ids = served
    with s.http() as http:
        r = http.post(f"/calibrations/{ids['bad']}/activate", json={"forced": True})
        assert r.status_code == 422
        assert "forced" in r.json()["error"]["message"]
