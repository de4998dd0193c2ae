"""A shape model taught from several images of the same part: what is stable across them stays.

One teach image's edges are partly not the part: a scratch on the table inside the ROI, a shadow or
a highlight of the light on that day, the glint on a 3-D part. ``teach_many`` teaches from the first
image and ROI, finds the part in each further image inside its ROI (any turn), and keeps the level-0
model points that an edge of the same direction meets within 1 px in every image; the coarse levels
keep the points near a kept level-0 point. The taught patch is the first image's, masked to the kept
points' hull. Units: pixels of the teach images; ROIs ``(U, V, W, H)`` as ``teach``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from vision.errors import TeachError
from vision.image import as_gray, gradients
from vision.shape import kernels
from vision.shape.model import GRAD_PER_CONTRAST, LevelModel, ShapeModel, TeachParams, teach
from vision.shape.patch import make_patch
from vision.types import SearchParams

MAX_TEACH_IMAGES = 5
MIN_KEPT_FRACTION = 0.2
"""A model keeping less than this share of its first image's points is refused (the images do not
show the same part, or not alike)."""


def teach_many(images: list[NDArray[Any]], rois: list[tuple[float, float, float, float]],
               params: TeachParams | None = None) -> ShapeModel:
    """Teach from 1-5 images of one part (``rois[i]`` frames it in ``images[i]``); see the module."""
    if not 1 <= len(images) <= MAX_TEACH_IMAGES or len(images) != len(rois):
        raise TeachError(f"give 1 to {MAX_TEACH_IMAGES} teach images, each with its ROI "
                         f"(got {len(images)} images and {len(rois)} ROIs)")
    from vision.shape.search import find

    first = as_gray(images[0])
    model = teach(first, rois[0], params)
    if len(images) == 1:
        return model
    lv0 = model.levels[0]
    keep = np.ones(len(lv0.points), bool)
    for k, (img_any, roi) in enumerate(zip(images[1:], rois[1:], strict=True), start=2):
        img = as_gray(img_any)
        u, v, w, h = roi
        res = find(model, img, SearchParams(roi=(u + w / 4, v + h / 4, w / 2, h / 2), max_count=1))
        if not res.matches:
            raise TeachError(f"the part taught from the first image is not found in teach image {k} inside its "
                             f"ROI ({res.reason()}): give images of the same part, framed alike")
        m = res.matches[0]
        keep &= _seen(model, img, m.u_px, m.v_px, m.angle_deg, m.scale)
    if keep.sum() < max(8, MIN_KEPT_FRACTION * len(keep)):
        raise TeachError(f"only {int(keep.sum())} of {len(keep)} model points are seen in every teach image: "
                         "the images do not show the part alike (another part, another side, another light)")
    levels = [LevelModel(0, lv0.points[keep], lv0.normals[keep], np.arange(int(keep.sum()), dtype=np.int64))]
    kept0 = lv0.points[keep]
    for lv in model.levels[1:]:
        s = 2.0 ** lv.level
        d = np.min(np.hypot(*(lv.points[:, None, :] * s - kept0[None, :, :]).transpose(2, 0, 1)), axis=1)
        near = d <= 2.0 * s
        if near.sum() < 16:
            break
        remap = -np.ones(len(lv.points), np.int64)
        remap[near] = np.arange(int(near.sum()))
        feats = remap[lv.features]
        feats = feats[feats >= 0]
        if len(feats) == 0:
            break
        levels.append(LevelModel(lv.level, lv.points[near], lv.normals[near], feats))
    patch = make_patch(first, rois[0], kept0)
    return ShapeModel(levels, model.params, model.roi, model.image_size, patch)


def _seen(model: ShapeModel, img: NDArray[np.uint8], u: float, v: float, angle_deg: float,
          scale: float) -> NDArray[np.bool_]:
    """Which level-0 model points an image edge of the same orientation meets within 1 px at the pose."""
    q, tangents = model.contour(u, v, angle_deg, scale)
    n = np.stack([tangents[:, 1], -tangents[:, 0]], axis=1)
    gx, gy = gradients(img, model.params.edge_sigma_px)
    G = np.ascontiguousarray(np.stack([gx, gy], axis=2))
    thr = 0.5 * model.params.min_contrast * GRAD_PER_CONTRAST
    d, found, cosd, _ = kernels.associate(G, np.ascontiguousarray(q), np.ascontiguousarray(n), 2, float(thr))
    return np.asarray(found & (np.abs(d) <= 1.0) & (cosd >= math.cos(math.radians(30.0))))
