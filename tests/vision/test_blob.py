"""Blob route: threshold, select by area/shape, centre and orientation from moments."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.support import pick_scenes as scenes
from vision import blob
from vision.types import SearchParams

SIZE = (640, 480)


def _style(**kw: object) -> scenes.SceneStyle:
    base: dict[str, object] = {"size": SIZE, "noise_sigma": 1.5}
    base.update(kw)
    return scenes.SceneStyle(**base)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def taught() -> tuple[scenes.PartShape, blob.BlobModel]:
    part = scenes.part_bracket()
    img, roi = scenes.teach_scene(part, np.random.default_rng(0), centre=(320.0, 240.0), style=_style())
    return part, blob.teach(img, roi)


def test_teach_features(taught: tuple[scenes.PartShape, blob.BlobModel]) -> None:
    _, m = taught
    assert m.polarity == "bright"
    assert m.directed
    # outline minus holes: 180x120 minus notches minus holes, about 18000 px^2
    assert 16000 < m.area_px < 20000
    assert m.elongation > 1.1


@pytest.mark.parametrize("angle", [0.0, 45.0, -90.0, 135.5, 180.0, -179.0])
def test_find_at_rotations(taught: tuple[scenes.PartShape, blob.BlobModel], angle: float) -> None:
    part, m = taught
    img, truth = scenes.render([scenes.Instance(part, 300.6, 230.3, angle)], _style(), np.random.default_rng(3))
    ms = blob.find(m, img).matches
    assert len(ms) == 1
    t = truth[0]
    assert math.hypot(ms[0].u_px - t.u_px, ms[0].v_px - t.v_px) < 0.25
    assert abs(scenes.wrap_deg(ms[0].angle_deg - t.angle_deg)) < 0.3


def test_selects_by_area_and_shape(taught: tuple[scenes.PartShape, blob.BlobModel]) -> None:
    part, m = taught
    insts = [scenes.Instance(part, 170.0, 150.0, 30.0), scenes.Instance(scenes.part_flange(), 470.0, 320.0, 0.0),
             scenes.Instance(scenes.part_bracket(0.7), 450.0, 120.0, 0.0)]
    img, _ = scenes.render(insts, _style(), np.random.default_rng(4))
    ms = blob.find(m, img).matches
    assert len(ms) == 1 and abs(ms[0].u_px - 170.0) < 0.5


def test_dark_parts_and_fixed_threshold() -> None:
    part = scenes.part_tee()
    st = _style(background=200.0, part_value=50.0)
    img, roi = scenes.teach_scene(part, np.random.default_rng(5), centre=(320.0, 240.0), style=st)
    m = blob.teach(img, roi, blob.BlobParams(threshold=125.0))
    assert m.polarity == "dark" and m.threshold == 125.0
    insts = [scenes.Instance(part, 250.2, 260.7, -120.0), scenes.Instance(part, 470.0, 150.0, 60.0)]
    scene, truth = scenes.render(insts, st, np.random.default_rng(6))
    ms = blob.find(m, scene, SearchParams(max_count=1)).matches
    assert len(ms) == 1
    assert min(math.hypot(ms[0].u_px - t.u_px, ms[0].v_px - t.v_px) for t in truth) < 0.3


def test_empty_roi_is_refused() -> None:
    img = np.full((100, 100), 90, np.uint8)
    with pytest.raises(ValueError, match="no region"):
        blob.teach(img, (10, 10, 60, 60))
