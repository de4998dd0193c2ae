"""What cannot be right is refused when it is stored, not when it is used (issue 34, item 4): the
red-team's calibration files (distortion 1e300, skew 1e12, K's last row 0 0 0, a negative
covariance) and recipes (a 1 MB name, a grid pitch of [0, 0], min_score 0.05, 2 m/s) answer 422
with the reason and store nothing; a bad calibration that is stored anyway (before these checks)
makes a pick answer 409 with the reason, never 500.

The cell is the virtual cell with its true calibrations active and recipe 1 stored
(``tests.plc.conftest.prepare_cell``), the real app in this process (``tests.support.app``).
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from cellctl.calibration_checks import MAX_SKEW_RATIO, check_covariance, check_intrinsics
from cellctl.pick.pose import UnusableCalibration, fold_yaw
from tests.plc.conftest import RECIPE, prepare_cell
from tests.support.app import AppCell, in_process_cell


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AppCell, dict[str, Any], dict[str, Any]]]:
    tmp = tmp_path_factory.mktemp("stored")
    path, facts = prepare_cell(tmp, {})
    with in_process_cell(tmp, config=path) as app, app.http() as http:
        recipe = http.get(f"/recipes/{RECIPE}").json()["data"]
        camera = http.get(f"/calibrations/{facts['camera_calibration_id']}").json()["result"]
        yield app, recipe, camera


def _camera_cases() -> list[tuple[str, Any, str]]:
    return [
        ("distortion 1e300", lambda d: d.update(dist=[1e300, 0.0, 0.0, 0.0, 0.0][:len(d["dist"])]), "distortion"),
        ("distortion folding over", lambda d: d.update(dist=[-3.0, 0.0, 0.0, 0.0, 0.0][:len(d["dist"])]),
         "cannot project its own image"),
        ("skew 1e12", lambda d: d["K"][0].__setitem__(1, 1e12), "skew"),
        ("K last row 0 0 0", lambda d: d["K"].__setitem__(2, [0.0, 0.0, 0.0]), "last row 0 0 1"),
        ("K lower part", lambda d: d["K"][1].__setitem__(0, 3.0), "upper triangular"),
        ("negative covariance", lambda d: d.update(parameters={"names": ["fx", "fy"],
                                                               "covariance": [[-1.0, 0.0], [0.0, 1.0]]}),
         "positive semi-definite"),
        ("asymmetric covariance", lambda d: d.update(parameters={"covariance": [[1.0, 0.5], [0.0, 1.0]]}),
         "symmetric"),
    ]


@pytest.mark.parametrize(("what", "mutate", "words"), _camera_cases(), ids=[c[0] for c in _camera_cases()])
def test_a_camera_that_cannot_project_its_image_is_refused(cell: tuple[AppCell, dict[str, Any], dict[str, Any]],
                                                          what: str, mutate: Any, words: str) -> None:
    app, _, camera = cell
    bad = copy.deepcopy(camera)
    mutate(bad)
    with app.http() as http:
        before = len(http.get("/calibrations").json())
        r = http.post("/calibrations", json=bad)
        assert r.status_code == 422, (what, r.text)
        err = r.json()["error"]
        assert err["code"] == "invalid_calibration" and words in err["message"], err
        assert len(http.get("/calibrations").json()) == before


def test_a_handeye_with_a_negative_covariance_is_refused(cell: tuple[AppCell, dict[str, Any], dict[str, Any]]) -> None:
    app, _, _ = cell
    he: dict[str, Any] = {"setup": "eye-in-hand", "T_tool_cam": np.eye(4).tolist(), "T_base_target": np.eye(4).tolist(),
          "uncertainty": {"covariance": (-np.eye(6) * 1e-6).tolist()}}
    with app.http() as http:
        r = http.post("/calibrations", json=he)
        assert r.status_code == 422 and "uncertainty.covariance" in r.json()["error"]["message"], r.text
        he["uncertainty"]["covariance"] = (np.eye(6) * 1e-6).tolist()
        assert http.post("/calibrations", json=he).status_code == 201  # the same file with a covariance stores


def test_the_checks_hold_good_cameras_and_state_their_bounds() -> None:
    K = [[1000.0, 0.0, 640.0], [0.0, 1000.0, 512.0], [0.0, 0.0, 1.0]]
    assert check_intrinsics(K, [-0.3, 0.1, 0.001, 0.001, 0.0], "opencv5", 1280, 1024) == []
    assert check_intrinsics(K, [-0.3], "division", 1280, 1024) == []
    # A polynomial that folds over only at the corners (fitted on central views) is stored, with a note.
    notes = check_intrinsics(K, [-0.6, 0.2, 0.0, 0.0, -0.05], "opencv5", 1280, 1024)
    assert len(notes) == 1 and "corners" in notes[0]
    K_skew = [[1000.0, MAX_SKEW_RATIO * 1000.0 * 0.9, 640.0], [0.0, 1000.0, 512.0], [0.0, 0.0, 1.0]]
    assert check_intrinsics(K_skew, [0.0] * 5, "opencv5", 1280, 1024) == []
    check_covariance(np.diag([1.0, 0.0, 2.0]), "psd")  # semi-definite is fine
    check_covariance([], "empty")


RECIPE_CASES: list[tuple[str, Any, str, str]] = [
    ("1 MB name", lambda r: r.update(name="n" * 1_000_000), "body.recipe.name", "invalid_request"),
    ("empty name", lambda r: r.update(name=""), "body.recipe.name", "invalid_request"),
    ("min_score 0.05", lambda r: r["search"].update(min_score=0.05), "body.recipe.search.min_score",
     "invalid_request"),
    ("speed 2 m/s", lambda r: r.update(speed_m_s=2.0), "max_linear_speed_m_s", "recipe_outside_cell"),
    ("grid pitch [0, 0]", lambda r: r.update(place={"kind": "grid", "origin_ur": [0.4, -0.2, 0.01, 0, 0, 0],
                                                     "rows": 1000, "cols": 1000, "layers": 1000,
                                                     "pitch_mm": [0.0, 0.0]}), "slots", "recipe_outside_cell"),
    ("grid pitch [0, 0] 3x3", lambda r: r.update(place={"kind": "grid", "origin_ur": [0.4, -0.2, 0.01, 0, 0, 0],
                                                         "rows": 3, "cols": 3, "pitch_mm": [0.0, 0.0]}),
     "pitch_mm[0]", "recipe_outside_cell"),
    ("grid beyond the envelope", lambda r: r.update(place={"kind": "grid", "origin_ur": [0.4, -0.2, 0.01, 0, 0, 0],
                                                            "rows": 2, "cols": 50, "pitch_mm": [100.0, 50.0]}),
     "outside the workspace envelope", "recipe_outside_cell"),
    ("fixed place below the table", lambda r: r.update(place={"kind": "fixed",
                                                              "pose_ur": [0.4, -0.2, -5.0, 0, 0, 0]}),
     "place pose", "recipe_outside_cell"),
]


@pytest.mark.parametrize(("what", "mutate", "words", "code"), RECIPE_CASES, ids=[c[0] for c in RECIPE_CASES])
def test_a_recipe_the_cell_cannot_run_is_refused_at_save(cell: tuple[AppCell, dict[str, Any], dict[str, Any]],
                                                        what: str, mutate: Any, words: str, code: str) -> None:
    app, recipe, _ = cell
    r = copy.deepcopy(recipe)
    r.setdefault("search", {})
    mutate(r)
    with app.http() as http:
        answer = http.post("/recipes", json={"recipe_id": 77, "recipe": r})
        assert answer.status_code == 422, (what, answer.text[:300])
        err = answer.json()["error"]
        assert err["code"] == code and words in err["message"], (what, err["message"][:300])
        assert len(answer.content) < 10_000  # a 1 MB name is not echoed back
        assert http.get("/recipes/77").status_code == 404


def test_a_sane_grid_recipe_saves(cell: tuple[AppCell, dict[str, Any], dict[str, Any]]) -> None:
    app, recipe, _ = cell
    r = {**copy.deepcopy(recipe), "place": {"kind": "grid", "origin_ur": [0.4, -0.2, 0.01, 0, 0, 0],
                                            "rows": 2, "cols": 3, "pitch_mm": [40.0, 40.0]}}
    with app.http() as http:
        assert http.post("/recipes", json={"recipe_id": 78, "recipe": r}).status_code == 201


def test_fold_yaw_of_a_non_finite_yaw_is_a_typed_error() -> None:
    with pytest.raises(UnusableCalibration, match="not a finite number"):
        fold_yaw(float("nan"), np.pi, 0.0)
    assert fold_yaw(0.1, np.pi, 0.0) == pytest.approx(0.1)


def test_a_pick_through_a_bad_stored_calibration_answers_409_not_500(
        cell: tuple[AppCell, dict[str, Any], dict[str, Any]]) -> None:
    app, _, camera = cell
    services = app.client.app.state.services  # type: ignore[attr-defined]
    store = services.store
    before = store.active("camera", "cam0", None)
    # Stored as an older cellctl did (no checks), then activated: the red-team's distortion of 1e300.
    bad = {**json.loads(json.dumps(camera)), "dist": [1e300] + [0.0] * (len(camera["dist"]) - 1)}
    record = store.save_calibration("camera", "cam0", None, bad, {}, creator="test", note="stored unchecked")
    store.activate(record.id, "test")
    try:
        with app.http() as http:
            r = http.post("/pick", json={"recipe_id": RECIPE})
            assert r.status_code == 409, r.text[:300]
            err = r.json()["error"]
            assert err["code"] == "calibration_unusable" and "activate another calibration" in err["message"], err
    finally:
        store.activate(before.id, "test")
