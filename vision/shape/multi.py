"""A shape model taught from several images of the same part: what is stable across them stays.

One teach image's edges are partly not the part: a scratch on the table inside the ROI, a shadow or
a highlight of the light on that day, the glint on a 3-D part. For a 3-D part under the cell's fixed,
one-sided light (a screw head), the shading stays put in the image while the part turns: only what
turns with the part is the part. ``teach_many``:

1. teaches from the first image and ROI, and finds the part in each further image inside its ROI
   (``vision.shape.multi_align``: the shape search, or a rotation sweep of the taught patch where the
   single image's edges are too much of its light to be found elsewhere);
2. keeps, on every pyramid level, the first image's candidate edges that an edge of the same
   orientation meets within 1 px (level pixels) in most teach images (all of 2-3, all but one of 4-5);
   the point budget is then filled from those only (an edge of one image's shading, grain or glint
   drops out; the first model's budget is not wasted on them);
3. where the sweep aligned an image, moves its pose to where the most of the first model's edges
   recur, and again (within 2 px) for the edges most images share, before step 2 (an alignment
   dragged by one image's shading would otherwise drop edges that are the part's);
4. keeps as the taught patch the average of the aligned teach patches (each image's light matched to
   the first's by gain and offset): the interior without one image's shading;
5. measures how far the part's changing look moves a fit (``spread``): in each view the final model's
   edge fit against its patch fit; their disagreement beyond their own 1-sigma is kept with the model
   (``ShapeModel.view_tau``, a model file's ``view_sigma``) and added to every match's 1-sigma.

An edge counts as seen in a view only with the first view's contrast polarity (dark to bright the same
way): on a 3-D part under one-sided light the rim and the socket's walls are lit on one side and
shaded on the other, and where the views disagree the edge is the light's, not the part's (the screw
heads: 7 of 9 found at the defaults with this rule, 5 of 9 without; ``bench/results/pick_real.md``).
Units: pixels of the teach images; ROIs ``(U, V, W, H)`` as ``teach``.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.errors import TeachError
from vision.image import F64, U8, gradients, pyramid
from vision.shape import kernels
from vision.shape.colour import channel, taught_mix
from vision.shape.frame import part_centre, recentred
from vision.shape.model import GRAD_PER_CONTRAST, LevelModel, ShapeModel, TeachParams
from vision.shape.multi_align import Pose4, align, overlap
from vision.shape.patch import MIN_PATCH_NCC, TeachPatch, fit, make_patch
from vision.shape.refine import Pose, refine_lsq
from vision.shape.teaching import teach
from vision.shape.uncertainty import view_tau

MAX_TEACH_IMAGES = 5
MIN_KEPT_FRACTION = 0.2
"""A model keeping less than this share of its first image's points is refused (the images do not
show the same part, or not alike)."""


def needed(n_images: int) -> int:
    """In how many of ``n_images`` teach images an edge must be seen to stay: all of 1-3, all but one of
    4-5 (one image's glint or a speck of dust on one part does not drop an edge the others show)."""
    return n_images - (n_images - 1) // 3


def teach_many(images: list[NDArray[Any]], rois: list[tuple[float, float, float, float]],
               params: TeachParams | None = None,
               centres: list[tuple[float, float]] | None = None) -> ShapeModel:
    """Teach from 1-5 images of one part (``rois[i]`` frames it in ``images[i]``; two ROIs may frame two
    parts alike in the same image); see the module. ``centres`` (optional, image pixels, one per view):
    the part's centre measured in each view; the model reports their mean in the part's frame
    (``ShapeModel.origin``, ``vision.shape.frame``) instead of its ROI centre, and their scatter there
    (per axis, over the views) joins ``view_tau``'s position term."""
    if centres is not None and len(centres) != len(images):
        raise TeachError(f"give one centre per teach image ({len(images)} images, {len(centres)} centres)")
    if not 1 <= len(images) <= MAX_TEACH_IMAGES or len(images) != len(rois):
        raise TeachError(f"give 1 to {MAX_TEACH_IMAGES} teach images, each with its ROI "
                         f"(got {len(images)} images and {len(rois)} ROIs)")
    p = params or TeachParams()
    mix = taught_mix(images, rois, p.colour, p.edge_sigma_px, p.min_contrast * GRAD_PER_CONTRAST)
    grays = [channel(i, mix) for i in images]
    pg = replace(p, colour="grey")  # (the channel is already made: teach on it as on a grey image)
    model = replace(teach(grays[0], rois[0], pg), params=p, colour=mix)
    if len(images) == 1:
        if centres is None:
            return model
        u, v, w, h = rois[0]
        return recentred(model, *part_centre([(u + w / 2.0, v + h / 2.0, 0.0, 1.0)], centres))
    poses = aligned_poses(model, grays, rois, p)
    need = needed(len(images))
    pyrs = [pyramid(g, len(model.levels) - 1) for g in grays]

    def keep(level: int, pts: F64, nrm: F64) -> NDArray[np.bool_]:
        if level >= len(pyrs[0]):
            return np.zeros(len(pts), bool)
        return _seen_count(pts, nrm, level, [pyr[level] for pyr in pyrs], poses, p) >= need

    out = replace(teach(grays[0], rois[0], pg, keep=keep), params=p)
    patch = mean_patch(make_patch(grays[0], rois[0], out.levels[0].points), grays, poses)
    model = ShapeModel(out.levels, out.params, out.roi, out.image_size, patch, colour=mix)
    tau = spread(model, grays, poses)
    if centres is None:
        return ShapeModel(out.levels, out.params, out.roi, out.image_size, patch, tau, colour=mix)
    # the views' own centres in the part's frame scatter by how well the model's frame holds the measured
    # centre from view to view (a 3-D part's edges move with the light): that scatter is in every match's
    # reported centre too
    pcs = np.array([part_centre([pose], [c]) for pose, c in zip(poses, centres, strict=True)])
    scatter = math.sqrt(float(((pcs - pcs.mean(axis=0)) ** 2).sum()) / (2 * (len(pcs) - 1)))
    model = ShapeModel(out.levels, out.params, out.roi, out.image_size, patch, (math.hypot(tau[0], scatter), tau[1]),
                       colour=mix)
    return recentred(model, *part_centre(poses, centres))


def spread(model: ShapeModel, grays: list[U8], poses: list[Pose4]) -> tuple[float, float]:
    """The error (px, rad) a fit of ``model`` has beyond its own covariance by how the part's look changes
    between its teach views (5 of the module): in each view, at its aligned pose, the final model's edge
    fit and its patch fit (the views' average) are made as a search makes them, and their differences
    over the views give ``uncertainty.view_tau``'s moment estimate (one-sided light on a 3-D part moves the
    shading, and so one fit against the other, from view to view)."""
    thr = model.params.min_contrast * GRAD_PER_CONTRAST
    d: list[F64] = []
    S: list[F64] = []
    for img, (x, y, th, sc) in zip(grays, poses, strict=True):
        pyr = pyramid(img, model.top_level + 1)
        r = refine_lsq(pyr[0], model.levels[0], Pose(x, y, th, 1.0, sc), model.params.edge_sigma_px, thr, 2.0, 5,
                       fine=pyr[0], min_contrast=model.params.min_contrast, perspective=True)
        if model.patch is None or r.cov is None or not np.all(np.isfinite(r.cov)):
            continue
        lv = min(model.patch.fit_level(), len(pyr) - 1)
        f = 2.0 ** lv
        pf = fit(model.patch.at_level(lv), pyr[lv], r.pose.x / f, r.pose.y / f, r.pose.theta, r.pose.scale)
        if pf is None or pf.ncc < MIN_PATCH_NCC or not np.all(np.isfinite(pf.cov)):
            continue
        F = np.diag([f, f, 1.0])
        turn = math.remainder(pf.theta - r.pose.theta, 2 * math.pi)
        d.append(np.array([pf.x * f - r.pose.x, pf.y * f - r.pose.y, turn]))
        S.append(r.cov + F @ pf.cov @ F)
    if len(d) < 2:
        return 0.0, 0.0
    return view_tau(np.array(d), np.array(S))


def aligned_poses(model: ShapeModel, grays: list[U8], rois: list[tuple[float, float, float, float]],
                  p: TeachParams) -> list[Pose4]:
    """Where the first image's part (``model``) lies in each teach image (the first: its ROI centre,
    unturned); steps 1 and 3 of the module."""
    u0, v0, w0, h0 = rois[0]
    poses: list[Pose4] = [(u0 + w0 / 2.0, v0 + h0 / 2.0, 0.0, 1.0)]
    lv0 = model.levels[0]
    swept = [False]
    for k, (img, roi) in enumerate(zip(grays[1:], rois[1:], strict=True), start=2):
        pose, by_search = align(model, img, roi, k)
        poses.append(pose if by_search else overlap(lv0, img, pose, p))
        swept.append(not by_search)
    need = needed(len(grays))
    stable = _seen_count(lv0.points, lv0.normals, 0, grays, poses, p) >= need
    if stable.sum() < max(8, MIN_KEPT_FRACTION * len(stable)):
        raise TeachError(f"only {int(stable.sum())} of {len(stable)} model points are seen in {need} of the "
                         f"{len(grays)} teach images: the images do not show the part alike (another part, "
                         "another side, another light)")
    for k in (k for k in range(1, len(grays)) if swept[k]):
        poses[k] = overlap(LevelModel(0, lv0.points[stable], lv0.normals[stable],
                                      np.arange(int(stable.sum()), dtype=np.int64)), grays[k], poses[k], p, 2.0)
    return poses


def _seen_count(pts: F64, nrm: F64, level: int, images: list[U8], poses: list[Pose4],
                p: TeachParams) -> NDArray[np.int64]:
    """In how many of ``images`` (level ``level`` of each teach image; the first is where the points
    come from) an edge of the same orientation and contrast polarity lies within 1 level pixel of each
    point (``pts``: level pixels relative to the reference point) at the image's pose (level-0 pixels,
    rad)."""
    count = np.ones(len(pts), np.int64)
    f = 2.0 ** level
    thr = 0.5 * p.min_contrast * GRAD_PER_CONTRAST
    for img, (x, y, th, sc) in zip(images[1:], poses[1:], strict=True):
        c, s = math.cos(th), math.sin(th)
        R = np.array([[c, s], [-s, c]])  # CCW on screen, as ShapeModel.contour
        q = np.ascontiguousarray(sc * pts @ R.T + np.array([x, y]) / f)
        n = np.ascontiguousarray(nrm @ R.T)
        gx, gy = gradients(img, p.edge_sigma_px if level == 0 else 0.0)
        G = np.ascontiguousarray(np.stack([gx, gy], axis=2))
        d, found, cosd, sign = kernels.associate(G, q, n, 2, float(thr))
        count += np.asarray(found & (np.abs(d) <= 1.0) & (cosd >= math.cos(math.radians(30.0))) & (sign > 0),
                            np.int64)
    return count


def mean_patch(first: TeachPatch, images: list[U8], poses: list[Pose4]) -> TeachPatch:
    """The first image's patch averaged with the other images' pixels at their poses (level-0 px,
    rad), each image's grey values matched to the first's by gain and offset over the mask."""
    H, W = first.image.shape
    jj, ii = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    px, py = jj + first.origin[0], ii + first.origin[1]
    ref = first.image.astype(np.float64)
    acc = ref.copy()
    m = first.mask
    for img, (x, y, th, sc) in zip(images[1:], poses[1:], strict=True):
        c, s = math.cos(th), math.sin(th)
        qx = (sc * (c * px + s * py) + x).astype(np.float32)
        qy = (sc * (-s * px + c * py) + y).astype(np.float32)
        got = cv2.remap(img.astype(np.float32), qx, qy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        g = got.astype(np.float64)
        A = np.stack([g[m], np.ones(int(m.sum()))], axis=1)
        a, b = np.linalg.lstsq(A, ref[m], rcond=None)[0]
        acc += a * g + b
    mean = np.clip(np.round(acc / len(images)), 0, 255).astype(np.uint8)
    return TeachPatch(mean, first.origin, first.mask.copy())
