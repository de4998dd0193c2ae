"""Least-squares refinement of a shape match to sub-pixel position, angle and scale.

Each model edge point is moved along its (rotated) normal to the nearest image edge of matching
orientation (peak of the gradient component along the normal, sub-pixel by a Gaussian fit), and
Gauss-Newton on (u, v, angle, scale) minimises the squared normal distances with Tukey weights
(occlusion and clutter get weight 0). On level 0 the edge positions are then taken as the
centroid of the intensity profile's differences along the normal — exact for a step edge
whatever its sub-pixel phase, where a peak fit aliases by a few hundredths of a pixel — and the
fit ends with a plane homography (a slightly tilted camera's perspective), whose local linear map
at the reference point gives the angle and scale. The refined pose is then scored by
``score.direction_score`` (edge-direction agreement over the visible model points).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from vision.image import CENTROID_HALF_WIDTH, F32, F64, U8, gradients, rot
from vision.shape import fit_kernels, kernels
from vision.shape.cov_kernels import edge_cov
from vision.shape.model import LevelModel
from vision.shape.score import PointDetail, direction_detail, find_threshold, grad_noise
from vision.shape.small_kernels import median
from vision.shape.uncertainty import sigma_of


@dataclass
class Pose:
    x: float
    y: float
    theta: float  # rad
    score: float
    scale: float = 1.0


def _associate(G: F32, q: F64, n: F64, reach: float, thr: float
               ) -> tuple[F64, NDArray[np.bool_], F64, F64]:
    """Nearest image edge of matching orientation along each normal within ``reach`` px.

    Returns the signed distances (sub-pixel, Gaussian fit of the gradient component along the
    normal), whether an edge was found, ``|cos|`` of the orientation difference there, and the
    sign of the image gradient along the model's normal (+1: the teach image's polarity).
    """
    return kernels.associate(G, np.ascontiguousarray(q), np.ascontiguousarray(n), int(math.ceil(reach)),
                             float(thr))


def _profile(img_f: F32, q: F64, n: F64) -> tuple[F64, F64, NDArray[np.bool_]]:
    return kernels.profile_centroids(img_f, np.ascontiguousarray(q), np.ascontiguousarray(n),
                                     CENTROID_HALF_WIDTH)


class LevelZeroExtras:
    """What a level-0 fit gives besides its pose and score: its covariance (``Refined.cov``: read for an
    answered match only) and the image's gradient noise around the part (``Refined.grad_noise``: read by the
    verification only), for a fit scoring below ``refine_lsq``'s ``extras_from`` computed when first read
    (pick speed: most level-0 hypotheses on a busy image end below ``min_score`` and never read either). The
    same values either way, to the bit (the same calls on the same arrays, none changed after the fit)."""

    def __init__(self, crop: U8, sigma: float, img_f: F32, m: F64, q: F64, n: F64, th: float, sc: float,
                 min_contrast: float, perspective: bool, visible: NDArray[np.bool_]) -> None:
        self._args = (crop, sigma, img_f, m, q, n, th, sc, min_contrast, perspective, visible)
        self._cov: F64 | None = None
        self._noise: float | None = None

    def cov(self) -> F64:
        """(3, 3) covariance of (x, y, theta) by the block jackknife of the centroid residuals (px, rad)."""
        if self._cov is None:
            _, _, img_f, m, q, n, th, sc, min_contrast, persp, vis = self._args
            off, S, clean = _profile(img_f, q, n)
            used = clean & (np.abs(off) < 1.0) & (np.abs(S) >= 0.5 * min_contrast) & vis
            # neighbouring points see overlapping profiles: points per independent one
            qu = q[used]
            spacing = float(median(np.hypot(qu[1:, 0] - qu[:-1, 0], qu[1:, 1] - qu[:-1, 1]))) if len(qu) > 2 else 1.0
            self._cov = edge_cov(off, used, m, q, n, th, sc,
                                 max((2 * CENTROID_HALF_WIDTH + 1) / max(spacing, 1e-9), 1.0), persp)
        return self._cov

    def noise(self) -> float:
        """``score.grad_noise`` of the fit's crop (grey levels / px)."""
        if self._noise is None:
            self._noise = grad_noise(self._args[0], self._args[1])
        return self._noise


@dataclass
class Refined:
    """A refined pose with its score over the visible model points."""

    pose: Pose
    score: float
    rms_px: float
    n_points: int = 0
    """Model points that agree (an edge within 1 px, direction and polarity as asked)."""
    n_visible: int = 0
    detail: PointDetail | None = None
    """Per model point at the final pose (level 0 only): what the verification reads."""
    q: F64 | None = None
    """(N, 2) the model points at the final pose, image pixels (level 0 only)."""
    n: F64 | None = None
    """(N, 2) their unit normals there."""
    extras: LevelZeroExtras | None = None
    """Level 0 only: ``cov`` and ``grad_noise``, computed when read."""

    @property
    def grad_noise(self) -> float:
        """The gradient magnitude (grey levels / px) that the image's noise reaches around the part (level 0
        only; 0 otherwise)."""
        return 0.0 if self.extras is None else self.extras.noise()

    @property
    def cov(self) -> F64 | None:
        """(3, 3) covariance of (x, y, theta) of the level-0 fit by the block jackknife (px, rad); None on a
        coarser level."""
        return None if self.extras is None else self.extras.cov()

    @property
    def sigma_deg(self) -> float:
        """1-sigma of the angle of the final fit (level 0 only): ``cov``'s; NaN without a finite one.
        Computed when read (a search answers the patch-merged 1-sigma and never needs this one)."""
        return self._sigmas()[0]

    @property
    def sigma_px(self) -> float:
        """1-sigma of the reference point's position (the larger axis), from the same."""
        return self._sigmas()[1]

    def _sigmas(self) -> tuple[float, float]:
        cov = self.cov
        if cov is None or not np.all(np.isfinite(cov)):
            return float("nan"), float("nan")
        return sigma_of(cov)


def refine_lsq(img_level: U8, lm: LevelModel, pose: Pose, sigma: float, thr: float,
                search_px: float, iterations: int, fine: U8 | None = None,
                min_contrast: float = 0.0, subset: NDArray[np.int64] | None = None,
                reject_below: float = 0.0, fit_scale: bool = False,
                max_scale_dev: float = 0.1, perspective: bool = False,
                polarity: str = "ignore_local_polarity", min_visible: float = 0.5,
                extras_from: float = 0.0) -> Refined:
    """Gauss-Newton fit of the model edge points to the image edges, scored at the final pose.

    With ``fit_scale`` the fit is a similarity (a slightly tilted view makes the part look a few
    per cent larger or smaller; a rigid fit would turn that into a position error). Model points
    outside the image (a part at the border) take no part in the fit or the score.

    With ``fine`` (level 0), a fit scoring at least ``extras_from`` has its covariance and the crop's noise
    computed at once, a lower one when they are read (``LevelZeroExtras``; the search's ``min_score``).
    """
    m, nrm_m = _fit_points(lm, subset)
    reach = lm.radius * (1 + max_scale_dev) + search_px + 5 + 3 * sigma
    h, w = img_level.shape
    x0, y0 = max(int(pose.x - reach), 0), max(int(pose.y - reach), 0)
    x1, y1 = min(int(pose.x + reach) + 1, w - 1), min(int(pose.y + reach) + 1, h - 1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return Refined(pose, 0.0, float("nan"))
    s0 = pose.scale
    vis_margin = 2.0 + 3 * sigma

    def visible(q: F64) -> NDArray[np.bool_]:
        return np.asarray((q[:, 0] >= vis_margin) & (q[:, 1] >= vis_margin) & (q[:, 0] <= x1 - x0 - vis_margin)
                          & (q[:, 1] <= y1 - y0 - vis_margin))

    crop = img_level[y0:y1 + 1, x0:x1 + 1]
    gx, gy = gradients(crop, sigma)
    G = cv2.merge([gx, gy])
    x, y, th, sc = pose.x - x0, pose.y - y0, pose.theta, pose.scale
    q0 = sc * (m @ rot(th).T) + np.array([x, y])
    vis0 = visible(q0)
    thr = find_threshold(crop, sigma, thr,
                         kernels.percentile75(kernels.magnitudes(G, q0[vis0])) if vis0.any() else thr)
    p4, failed, q, d, found, cosd, sign = fit_kernels.fit_stage_a(
        G, m, nrm_m, np.array([x, y, th, sc]), s0, max_scale_dev,
        float(search_px), int(iterations), float(thr), float(reject_below), bool(fit_scale), lm.radius,
        vis_margin, float(x1 - x0), float(y1 - y0))
    x, y, th, sc = (float(t) for t in p4)
    if failed:
        return Refined(Pose(x + x0, y + y0, th, 0.0, sc), 0.0, float("nan"))

    if fine is not None:
        # stage B: centroid edge positions on the raw image (phase-exact), a few Gauss-Newton steps
        img_f = fine[y0:y1 + 1, x0:x1 + 1].astype(np.float32)
        sel = found & (np.abs(d) < 1.0)
        persp = perspective
        ms, ns = m[sel], nrm_m[sel]
        x, y, th, sc = fit_kernels.fit_stage_b(  # the centroid Gauss-Newton loop, compiled (pick-speed)
            img_f, ms, ns, x, y, th, sc, s0, max_scale_dev, float(min_contrast), bool(fit_scale),
            1 if persp else 3, lm.radius, vis_margin, float(x1 - x0), float(y1 - y0), CENTROID_HALF_WIDTH)
        if persp:
            x, y, th, sc = fit_kernels.perspective_fit(img_f, ms, ns, x, y, th, sc, float(min_contrast),
                                                       CENTROID_HALF_WIDTH)  # _perspective_fit compiled
        # the score is taken at the final pose
        R = rot(th)
        q = sc * (m @ R.T) + np.array([x, y])
        n = nrm_m @ R.T
        d, found, cosd, sign = _associate(G, q, n, 2.0, thr)
        vis = visible(q)
        # the fit's covariance (its jackknife over the centroid residuals) and the crop's noise: when read
        extras = LevelZeroExtras(crop, sigma, img_f, m, q, n, th, sc, min_contrast, persp, vis)
    else:
        R = rot(th)
        q = sc * (m @ R.T) + np.array([x, y])
        n = nrm_m @ R.T
        vis = visible(q)
    score, n_agree, n_vis, detail = direction_detail(G, q, n, vis, thr, polarity, min_visible)
    if fine is not None and score >= extras_from:
        extras.cov()  # a hypothesis that may be answered: computed now, while its arrays are fresh in cache
        extras.noise()
    if fine is None:
        # a coarse level's hypothesis goes on by its pose and score: its rms is never read (NaN)
        return Refined(Pose(x + x0, y + y0, th, score, sc), score, float("nan"), n_agree, n_vis)
    inl = found & vis & (np.abs(d) < 1.0)
    di = d[inl]
    # np.mean's sum over its count, without its overhead (the same bits)
    rms = math.sqrt(float(np.add.reduce(di * di)) / len(di)) if len(di) else float("nan")
    return Refined(Pose(x + x0, y + y0, th, score, sc), score, rms, n_agree, n_vis, detail=detail,
                   q=q + np.array([x0, y0]), n=n, extras=extras)


def _fit_points(lm: LevelModel, subset: NDArray[np.int64] | None) -> tuple[F64, F64]:
    """The model points and normals a fit uses (all, or ``subset``: the level's features), C-contiguous
    float64, kept with the level model for its next fit (a search refines several candidates per level)."""
    if subset is None:
        return np.ascontiguousarray(lm.points, dtype=np.float64), np.ascontiguousarray(lm.normals, dtype=np.float64)
    got = lm.__dict__.get("_fit_subset")
    if got is None or got[0] is not subset or got[1] is not lm.points or got[2] is not lm.normals:
        got = (subset, lm.points, lm.normals, np.ascontiguousarray(lm.points[subset], dtype=np.float64),
               np.ascontiguousarray(lm.normals[subset], dtype=np.float64))
        lm.__dict__["_fit_subset"] = got
    return got[3], got[4]


def _perspective_fit(img_f: F32, m: F64, nrm: F64, x: float, y: float, th: float, sc: float,
                     min_contrast: float) -> tuple[float, float, float, float]:
    """Refine a similarity to a plane homography of the model (a tilted camera's view).

    ``q = (A m + c) / (1 + p.m)``; the reference point is ``c`` and the reported angle and scale
    are those of the local linear map ``A - c p^T`` at the reference point (the direction the
    part's x axis takes there). Gauss-Newton on the centroid normal distances.
    """
    R = rot(th)
    A = sc * R
    c = np.array([x, y])
    pv = np.zeros(2)
    for _ in range(2):
        w = 1.0 + m @ pv
        q = (m @ A.T + c) / w[:, None]
        J_lin = A - np.outer(c, pv)
        n = nrm @ J_lin.T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        off, S, clean = _profile(img_f, q, n)
        ok = clean & (np.abs(off) < 1.0) & (np.abs(S) >= 0.5 * min_contrast)
        wgt = np.where(ok, (1 - off ** 2) ** 2, 0.0)
        if np.count_nonzero(wgt) < 20:
            break
        mx, my = m[:, 0] / w, m[:, 1] / w
        inv = 1.0 / w
        nx, ny = n[:, 0], n[:, 1]
        qn = nx * q[:, 0] + ny * q[:, 1]
        J = np.stack([nx * mx, nx * my, nx * inv, ny * mx, ny * my, ny * inv, -qn * mx, -qn * my], axis=1)
        Hm = J.T @ (J * wgt[:, None]) + np.eye(8) * 1e-9 * (1 + np.abs(J).max())
        delta = np.linalg.solve(Hm, J.T @ (wgt * off))
        A = A + np.array([[delta[0], delta[1]], [delta[3], delta[4]]])
        c = c + np.array([delta[2], delta[5]])
        pv = pv + delta[6:8]
        if np.abs(delta[[2, 5]]).sum() < 1e-4:
            break
    J_lin = A - np.outer(c, pv)
    theta = math.atan2(-J_lin[1, 0], J_lin[0, 0])
    scale = math.sqrt(abs(np.linalg.det(J_lin)))
    return float(c[0]), float(c[1]), theta, scale

