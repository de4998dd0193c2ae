"""Several part types in one call: which part is where, with the margin to the runner-up."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellctl.pick import model as pm
from tests.support import pick_scenes as scenes
from vision.recognize import recognize
from vision.types import SearchParams

SIZE = (800, 600)


@pytest.fixture(scope="module")
def models() -> list[pm.PartModel]:
    out = []
    for i, part in enumerate((scenes.part_bracket(), scenes.part_flange(), scenes.part_tee())):
        st = scenes.SceneStyle(size=SIZE, noise_sigma=1.0)
        img, roi = scenes.teach_scene(part, np.random.default_rng(i), centre=(400.0, 300.0), style=st)
        out.append(pm.teach(img, roi, name=part.name))
    return out


def test_each_part_is_named_with_a_margin(models: list[pm.PartModel]) -> None:
    insts = [scenes.Instance(scenes.part_bracket(), 180.4, 160.2, 25.0),
             scenes.Instance(scenes.part_flange(), 560.7, 170.1, -140.0),
             scenes.Instance(scenes.part_tee(), 380.2, 430.9, 95.0, 0.15)]
    img, truth = scenes.render(insts, scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=10),
                              np.random.default_rng(7))
    res = recognize(models, img)
    assert len(res.matches) == 3
    for t in truth:
        m = min(res.matches, key=lambda m: math.hypot(m.u_px - t.u_px, m.v_px - t.v_px))
        assert m.part == t.part
        assert math.hypot(m.u_px - t.u_px, m.v_px - t.v_px) < 0.2
        assert abs(scenes.wrap_deg(m.angle_deg - t.angle_deg)) < 0.1
        assert m.margin > 0.1
        assert m.margin == pytest.approx(m.score - m.runner_up_score)


def test_max_count_and_no_parts(models: list[pm.PartModel]) -> None:
    empty, _ = scenes.render([], scenes.SceneStyle(size=SIZE, clutter=20), np.random.default_rng(8))
    assert recognize(models, empty).matches == []
    tee = scenes.part_tee()
    insts = [scenes.Instance(tee, 200.0, 200.0, 0.0), scenes.Instance(tee, 600.0, 400.0, 90.0)]
    img, _ = scenes.render(insts, scenes.SceneStyle(size=SIZE), np.random.default_rng(9))
    res = recognize(models, img, SearchParams(max_count=1))
    assert len(res.matches) == 1 and res.matches[0].part == "tee"


def test_names_must_differ(models: list[pm.PartModel]) -> None:
    with pytest.raises(ValueError, match="names must differ"):
        recognize([models[0], models[0]], np.zeros((10, 10), np.uint8))
