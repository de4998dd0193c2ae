"""Where the part taught from the first teach image lies in a further teach image (``multi``).

A pose here is ``(x, y, theta, scale)``: the reference point in level-0 pixels of the further image,
the turn in rad (CCW on screen, as ``ShapeModel.contour``) and the scale; a model point ``p``
(relative to the reference point) lies at ``scale * R(theta) p + (x, y)``.

``align`` asks the shape search first (a flat part: its edges are the same in every image). Where it
finds nothing inside the ROI, the single image's edges are too much of its own light (a 3-D part
under one-sided light: a bright crescent and a shadow that stay put while the part turns), and the
taught patch is swept over the whole turn instead (normalised correlation, masked to the part, at
half resolution, in 2-degree steps) and fitted from the best turn by grey values
(``patch.fit``). ``overlap`` then moves the pose to where the most of the model's edges recur (a
correlation of all the part's pixels is dragged by the light; the shared edges are what ``multi``
keeps).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from vision.errors import TeachError
from vision.image import U8, gradients
from vision.shape import kernels
from vision.shape.model import GRAD_PER_CONTRAST, LevelModel, ShapeModel, TeachParams
from vision.shape.patch import TeachPatch, fit
from vision.types import SearchParams

Pose4 = tuple[float, float, float, float]
SWEEP_STEP_DEG = 2.0
MIN_ALIGN_NCC = 0.5
"""The swept patch must correlate at least this well with the further image (a part, not the table)."""


def align(model: ShapeModel, img: U8, roi: tuple[float, float, float, float], k: int) -> tuple[Pose4, bool]:
    """The pose of ``model``'s part in teach image ``k`` (1-based, for the message) inside ``roi``, and
    whether the shape search found it (``False``: the patch sweep did; ``overlap`` should follow)."""
    from vision.shape.search import find

    u, v, w, h = roi
    res = find(model, img, SearchParams(roi=(u + w / 4, v + h / 4, w / 2, h / 2), max_count=1))
    if res.matches:
        m = res.matches[0]
        return (m.u_px, m.v_px, math.radians(m.angle_deg), m.scale), True
    got = None if model.patch is None else sweep(model.patch, img, roi)
    if got is None or got[4] < MIN_ALIGN_NCC:
        why = res.reason() or "nothing there"
        if got is not None:
            why += f"; its taught patch correlates {got[4]:.2f} at best (< {MIN_ALIGN_NCC:g})"
        raise TeachError(f"the part taught from the first image is not found in teach image {k} inside its ROI "
                         f"({why}): give images of the same part, framed alike")
    return got[:4], False


def sweep(patch: TeachPatch, img: U8, roi: tuple[float, float, float, float]
          ) -> tuple[float, float, float, float, float] | None:
    """The patch's best pose over the whole turn with its reference point in the ROI's middle half,
    then fitted by grey values: ``(x, y, theta, scale, ncc)``; ``None`` when nothing correlates."""
    u, v, w, h = roi
    f = 2
    tim = patch.image.astype(np.float32)
    mask = patch.mask.astype(np.uint8)
    H, W = tim.shape
    rx, ry = -patch.origin[0], -patch.origin[1]  # the reference point in the crop
    pad = int(max(W, H))
    big = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REFLECT)
    small = cv2.resize(big, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA).astype(np.float32)
    tw, th_ = int(math.ceil(W / f)), int(math.ceil(H / f))
    # the window: reference points over the ROI's middle half, the template's extent around them
    cx, cy = (u + w / 2 + pad) / f, (v + h / 2 + pad) / f
    x0, y0 = int(cx - w / (4 * f) - tw / 2) - 1, int(cy - h / (4 * f) - th_ / 2) - 1
    win = small[max(y0, 0):y0 + int(h / (2 * f)) + th_ + 3, max(x0, 0):x0 + int(w / (2 * f)) + tw + 3]
    if win.shape[0] < th_ or win.shape[1] < tw or float(win.std()) < 1e-3:
        return None
    best = (-2.0, 0.0, 0.0, 0.0)
    for a in np.arange(0.0, 360.0, SWEEP_STEP_DEG):
        R = cv2.getRotationMatrix2D((rx, ry), float(a), 1.0 / f)  # CCW on screen by a
        R[:, 2] += np.array([tw / 2.0 - rx, th_ / 2.0 - ry])
        t = cv2.warpAffine(tim, R, (tw, th_))
        mk = cv2.warpAffine(mask, R, (tw, th_), flags=cv2.INTER_NEAREST)
        if mk.sum() < 30 or float(t[mk > 0].std()) < 1e-3:
            continue
        r = cv2.matchTemplate(win, t, cv2.TM_CCOEFF_NORMED, mask=mk)
        r[~np.isfinite(r)] = -2.0
        _, mx, _, loc = cv2.minMaxLoc(r)
        if mx > best[0]:
            best = (float(mx), float(a), (max(x0, 0) + loc[0] + tw / 2.0) * f - pad,
                    (max(y0, 0) + loc[1] + th_ / 2.0) * f - pad)
    if best[0] <= -1.0:
        return None
    pf = fit(patch, img, best[2], best[3], math.radians(best[1]), 1.0)
    if pf is None or not pf.converged and pf.ncc < best[0]:
        return (best[2], best[3], math.radians(best[1]), 1.0, best[0])
    return (pf.x, pf.y, pf.theta, pf.scale, pf.ncc)


def overlap(lm: LevelModel, img: U8, pose: Pose4, p: TeachParams, reach_px: float = 6.0) -> Pose4:
    """``pose`` moved (rigidly, within +-``reach_px`` and a turn that moves the part's outermost
    point as far) to where the most of ``lm``'s edges (level-0 points) recur in ``img``: each point
    counts ``1 - (d / 1.5 px)^2`` for an edge of the same orientation (within 30 deg) at normal distance
    ``d``. A first alignment dragged by one image's shading (a correlation of all the part's pixels)
    lands where the shared edges are."""
    x, y, th, sc = pose
    gx, gy = gradients(img, p.edge_sigma_px)
    G = np.ascontiguousarray(np.stack([gx, gy], axis=2))
    thr = 0.5 * p.min_contrast * GRAD_PER_CONTRAST
    cos30 = math.cos(math.radians(30.0))
    r = max(lm.radius, 4.0)

    def value(dx: float, dy: float, dth: float) -> float:
        t = th + dth
        c, s = math.cos(t), math.sin(t)
        R = np.array([[c, s], [-s, c]])
        q = np.ascontiguousarray(sc * lm.points @ R.T + np.array([x + dx, y + dy]))
        n = np.ascontiguousarray(lm.normals @ R.T)
        d, found, cosd, _ = kernels.associate(G, q, n, 2, float(thr))
        ok = found & (cosd >= cos30) & (np.abs(d) < 1.5)
        return float(np.sum(1.0 - (d[ok] / 1.5) ** 2))

    best = (value(0.0, 0.0, 0.0), 0.0, 0.0, 0.0)
    steps = [st for st in (2.0, 1.0, 0.5, 0.25) if st <= reach_px / 2]
    for i, step in enumerate(steps):
        reach = reach_px if i == 0 else 2 * step
        grid = np.arange(-reach, reach + 1e-9, step)
        cx, cy, ct = best[1], best[2], best[3]
        for dx in grid:
            for dy in grid:
                for dt in grid / r:
                    v = value(cx + dx, cy + dy, ct + dt)
                    if v > best[0]:
                        best = (v, cx + dx, cy + dy, ct + dt)
    return (x + best[1], y + best[2], th + best[3], sc)
