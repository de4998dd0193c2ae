"""Part model files: round trip, version check, corrupt files, ROI checks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cellctl.pick import model as pm
from tests.support import pick_scenes as scenes

SIZE = (480, 360)


@pytest.fixture(scope="module")
def taught() -> tuple[pm.PartModel, np.ndarray, np.ndarray]:
    part = scenes.part_tee()
    style = scenes.SceneStyle(size=SIZE, noise_sigma=1.0)
    img, roi = scenes.teach_scene(part, np.random.default_rng(0), centre=(240.0, 180.0), style=style)
    scene, _ = scenes.render([scenes.Instance(part, 200.3, 170.6, -73.0)], style, np.random.default_rng(1))
    return pm.teach(img, roi, name="tee", teach_image="teach.png"), img, scene


def test_round_trip_gives_the_same_matches(taught: tuple[pm.PartModel, np.ndarray, np.ndarray],
                                           tmp_path: Path) -> None:
    m, _, scene = taught
    path = tmp_path / "tee.json"
    m.save(path)
    d = json.loads(path.read_text())
    assert d["format_version"] == pm.FORMAT_VERSION and d["mode"] == "shape" and d["name"] == "tee"
    assert d["teach"]["reference_px"] == [240.0, 180.0]
    assert d["teach"]["params"]["min_contrast"] == 12.0
    back = pm.PartModel.load(path)
    a, b = m.find(scene).matches, back.find(scene).matches
    assert len(a) == len(b) >= 1
    for x, y in zip(a, b, strict=True):
        assert y.u_px == pytest.approx(x.u_px, abs=2e-3)  # points are stored to 1e-4 px
        assert y.angle_deg == pytest.approx(x.angle_deg, abs=2e-3)
    assert a[0].u_px == pytest.approx(200.3, abs=0.1) and a[0].score > 0.9


def test_blob_round_trip(taught: tuple[pm.PartModel, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    _, img, scene = taught
    roi = taught[0].roi
    m = pm.teach(img, roi, mode="blob", name="tee-blob")
    m.save(tmp_path / "b.json")
    back = pm.PartModel.load(tmp_path / "b.json")
    assert back.mode == "blob"
    assert back.find(scene).matches[0].u_px == pytest.approx(m.find(scene).matches[0].u_px)


def test_newer_version_is_refused(taught: tuple[pm.PartModel, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    d = taught[0].to_dict()
    d["format_version"] = pm.FORMAT_VERSION + 1
    path = tmp_path / "new.json"
    path.write_text(json.dumps(d))
    with pytest.raises(pm.ModelFileError, match="newer than this cellctl reads"):
        pm.PartModel.load(path)


@pytest.mark.parametrize("text, message", [
    ("{not json", "not valid JSON"),
    ('{"format_version": 1, "mode": "shape"}', "incomplete or corrupt"),
    ('{"format_version": 1, "mode": "magic", "teach": {}}', "unknown mode"),
    ('[1, 2]', "not a cellctl part model"),
    ('{"mode": "shape"}', "no integer format_version"),
])
def test_corrupt_files_are_refused(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(pm.ModelFileError, match=message):
        pm.PartModel.load(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(pm.ModelFileError, match="cannot read model file"):
        pm.PartModel.load(tmp_path / "nope.json")


def test_damaged_point_indices_are_refused(taught: tuple[pm.PartModel, np.ndarray, np.ndarray]) -> None:
    d = taught[0].to_dict()
    d["shape"]["levels"][1]["features"] = [10 ** 6]
    with pytest.raises(pm.ModelFileError, match="corrupt"):
        pm.PartModel.from_dict(d)


@pytest.mark.parametrize("roi, message", [
    ((-1.0, 10.0, 50.0, 50.0), "outside"),
    ((450.0, 10.0, 50.0, 50.0), "outside"),
    ((10.0, 340.0, 50.0, 50.0), "outside"),
    ((10.0, 10.0, 0.0, 50.0), "empty"),
    ((10.0, 10.0, 50.0, -3.0), "empty"),
])
def test_bad_roi(taught: tuple[pm.PartModel, np.ndarray, np.ndarray], roi: tuple[float, float, float, float],
                 message: str) -> None:
    with pytest.raises(ValueError, match=message):
        pm.teach(taught[1], roi)


def test_full_image_roi_is_allowed(taught: tuple[pm.PartModel, np.ndarray, np.ndarray]) -> None:
    m = pm.teach(taught[1], (0.0, 0.0, float(SIZE[0]), float(SIZE[1])))
    assert m.reference_px == (SIZE[0] / 2, SIZE[1] / 2)


def test_view_sigma_round_trip_and_schema(taught: tuple[pm.PartModel, np.ndarray, np.ndarray]) -> None:
    """A model taught from several views keeps ``shape.view_sigma`` (vision.shape.multi.spread): the file
    schema takes it, the reader gives it back, and a match's 1-sigma grows by it; a one-view model writes
    none."""
    import dataclasses
    import math

    from cellctl.pick.model_schema import PartModelDoc

    m, _, scene = taught
    assert "view_sigma" not in m.to_dict()["shape"]
    assert m.shape is not None
    wide = dataclasses.replace(m, shape=dataclasses.replace(m.shape, view_tau=(0.5, math.radians(2.0))))
    d = wide.to_dict()
    assert d["shape"]["view_sigma"] == {"px": 0.5, "deg": 2.0}
    PartModelDoc.model_validate(d)
    back = pm.PartModel.from_dict(json.loads(json.dumps(d)))
    assert back.shape is not None and back.shape.view_tau == pytest.approx((0.5, math.radians(2.0)))
    a, b = m.find(scene).matches[0], back.find(scene).matches[0]
    assert b.u_px == pytest.approx(a.u_px, abs=2e-3)  # the pose stays: only the 1-sigma carries it
    assert b.sigma_px > max(a.sigma_px, 0.3) and b.sigma_angle_deg > max(a.sigma_angle_deg, 1.0)
