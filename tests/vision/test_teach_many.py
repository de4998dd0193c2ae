"""A model taught from several images keeps what they share (``vision.shape.multi.teach_many``)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tests.support import pick_scenes
from vision import shape
from vision.errors import TeachError
from vision.shape.multi import teach_many

SIZE = (640, 480)


def _teach_images() -> tuple[list[np.ndarray], list[tuple[float, float, float, float]]]:
    part = pick_scenes.part_bracket()
    imgs, rois = [], []
    for k, centre in enumerate([(320.3, 240.6), (300.7, 250.2), (330.1, 230.9)]):
        img, roi = pick_scenes.teach_scene(part, np.random.default_rng(40 + k), centre=centre,
                                           style=pick_scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=0))
        imgs.append(img)
        rois.append(roi)
    # the first image has a scratch on the table inside its ROI, beside the part
    u, v, w, h = rois[0]
    cv2.line(imgs[0], (int(u + 8), int(v + h - 6)), (int(u + w - 8), int(v + h - 3)), 250, 2)
    return imgs, rois


def _near_scratch(model: shape.ShapeModel, roi: tuple[float, float, float, float]) -> int:
    u, v, w, h = roi
    ref_y = v + h / 2
    y = model.levels[0].points[:, 1] + ref_y
    return int(np.count_nonzero(y > v + h - 9))


def test_what_only_one_image_shows_is_dropped() -> None:
    imgs, rois = _teach_images()
    one = shape.teach(imgs[0], rois[0])
    many = teach_many(imgs, rois)
    assert _near_scratch(one, rois[0]) >= 10  # the single image's model holds the scratch
    assert _near_scratch(many, rois[0]) == 0
    assert len(many.levels[0].points) >= 0.6 * len(one.levels[0].points)
    # and it finds the part as well as before
    part = pick_scenes.part_bracket()
    scene, truth = pick_scenes.render([pick_scenes.Instance(part, 200.4, 300.8, 33.3)],
                                      pick_scenes.SceneStyle(size=SIZE, noise_sigma=2.0, clutter=10),
                                      np.random.default_rng(3))
    m = shape.find(many, scene).matches
    assert len(m) == 1
    assert math.hypot(m[0].u_px - truth[0].u_px, m[0].v_px - truth[0].v_px) < 0.1
    assert abs(m[0].angle_deg - truth[0].angle_deg) < 0.1


def test_images_of_another_part_are_refused() -> None:
    imgs, rois = _teach_images()
    blank = np.full_like(imgs[1], 80)
    with pytest.raises(TeachError, match="not found in teach image 2"):
        teach_many([imgs[0], blank], rois[:2])
    with pytest.raises(TeachError, match="1 to 5 teach images"):
        teach_many(imgs, rois[:2])
