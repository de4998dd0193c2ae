"""Detected target points of one image: the contract between detection and the solvers.

Pixels are ``(u, v)``, (0, 0) the centre of the top-left pixel. For circle marks ``uv`` is the
image of each mark's *centre* (perspective bias corrected as well as the detector could without
a calibrated camera) and ``uv_ellipse`` the raw fitted-ellipse centre, which solvers that know
the camera use with ``calibration.detect.conic.circle_centre_bias_px`` inside their loop.

``uv_sigma_px`` is each point's own 1-sigma position uncertainty (px, per axis) from its local
fit (``calibration.detect.precision``); solvers weight by it through ``point_weights``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray


@dataclass
class Detection:
    """The points of one target found in one image (or why none were)."""

    image: str
    found: bool
    ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    uv: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    uv_ellipse: NDArray[np.float64] | None = None
    reason: str = ""
    image_size: tuple[int, int] = (0, 0)
    """(width, height) of the image in pixels."""
    quality: dict[str, float] = field(default_factory=dict)
    uv_sigma_px: NDArray[np.float64] | None = None
    """(N,) 1-sigma position uncertainty of each point (px, per axis) from its local fit, or None."""

    def to_json(self) -> dict[str, Any]:
        """The ``cellctl detect`` JSON of one image (docs/cli.md)."""
        points = []
        for k, i in enumerate(self.ids):
            p: dict[str, Any] = {"id": int(i), "u_px": float(self.uv[k, 0]), "v_px": float(self.uv[k, 1])}
            if self.uv_ellipse is not None:
                p["u_ellipse_px"] = float(self.uv_ellipse[k, 0])
                p["v_ellipse_px"] = float(self.uv_ellipse[k, 1])
            if self.uv_sigma_px is not None:
                sk = float(self.uv_sigma_px[k])
                p["sigma_px"] = round(sk, 5) if np.isfinite(sk) else None
            points.append(p)
        out: dict[str, Any] = {"image": self.image, "found": self.found, "points": points}
        if self.reason:
            out["reason"] = self.reason
        if self.image_size != (0, 0):
            out["width"], out["height"] = self.image_size
        if self.quality:
            out["quality"] = self.quality
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Detection:
        pts = d.get("points", [])
        ids = np.array([p["id"] for p in pts], dtype=np.int64)
        uv = np.array([[p["u_px"], p["v_px"]] for p in pts], dtype=np.float64).reshape(-1, 2)
        ell = None
        if pts and "u_ellipse_px" in pts[0]:
            ell = np.array([[p["u_ellipse_px"], p["v_ellipse_px"]] for p in pts], dtype=np.float64)
        sig = None
        if pts and "sigma_px" in pts[0]:
            sig = np.array([np.inf if p.get("sigma_px") is None else p["sigma_px"] for p in pts], dtype=np.float64)
        return cls(image=d["image"], found=bool(d["found"]), ids=ids, uv=uv, uv_ellipse=ell, uv_sigma_px=sig,
                   reason=d.get("reason", ""), image_size=(int(d.get("width", 0)), int(d.get("height", 0))),
                   quality=dict(d.get("quality", {})))


SYSTEMATIC_FLOOR: Final = 0.5
"""Least part of the typical point's error that no local fit sees (lens model, bias residue), as
a fraction of the median point uncertainty: it caps any point's weight at ~2.2x the typical one.
A solver that sees larger unexplained residuals raises the floor (``systematic_floor_px``)."""
POINT_OUTLIER_FACTOR: Final = 3.0
"""A point whose own uncertainty exceeds its view's median by this factor is weighted down on its own."""


def effective_sigmas(sigmas: Sequence[NDArray[np.float64] | None], counts: Sequence[int]
                     ) -> tuple[list[NDArray[np.float64] | None], float]:
    """Each point's uncertainty as the weights use it (px): its *view's* median uncertainty, or
    its own when that exceeds the view's by more than ``POINT_OUTLIER_FACTOR`` (a window without
    structure); ``None`` for views without uncertainties. Also the median over all points."""
    finite = [s[np.isfinite(s) & (s > 0)] for s in sigmas if s is not None]
    allv = np.concatenate(finite) if finite else np.zeros(0)
    if allv.size == 0:
        return [None for _ in counts], float("nan")
    med = float(np.median(allv))
    out: list[NDArray[np.float64] | None] = []
    for s in sigmas:
        if s is None:
            out.append(None)
            continue
        sv = np.asarray(s, dtype=np.float64)
        ok = np.isfinite(sv) & (sv > 0)
        view = float(np.median(sv[ok])) if ok.any() else med
        own = np.where(ok, sv, 1e3 * view) / (POINT_OUTLIER_FACTOR * view)
        out.append(view * np.maximum(1.0, own))
    return out, med


def point_weights(sigmas: Sequence[NDArray[np.float64] | None], counts: Sequence[int], *,
                  floor_px: float | None = None) -> list[NDArray[np.float64]]:
    """Relative residual weights ``1 / s_i`` of the points of several detections (views).

    The weight follows the *view's* precision (``effective_sigmas``): per-point estimates scatter
    too much to weight by one by one (on rendered circle plates that made the calibration 2.8x
    worse than unweighted), while a blurred or noisy view as a whole is what must stop
    dominating. Each point's error is taken as ``sqrt(s_i² + floor²)``: ``floor_px`` is the error
    no local fit sees (default ``SYSTEMATIC_FLOOR`` x the median uncertainty; a solver passes a
    larger one estimated from its residuals, ``systematic_floor_px``). Weights are normalised so
    that the median point weighs 1 (the solvers' residual scale stays in pixels). Views without
    uncertainties (``None``) weigh 1.
    """
    eff, med = effective_sigmas(sigmas, counts)
    if not np.isfinite(med):
        return [np.ones(n) for n in counts]
    floor = SYSTEMATIC_FLOOR * med if floor_px is None else max(float(floor_px), SYSTEMATIC_FLOOR * med)
    norm = np.sqrt(med * med + floor * floor)
    return [np.ones(n) if e is None else norm / np.sqrt(e * e + floor * floor)
            for e, n in zip(eff, counts, strict=True)]


def systematic_floor_px(residuals_px: NDArray[np.float64], sigmas_px: NDArray[np.float64], n_params: int) -> float:
    """The per-axis error ``tau`` (px) that the points' own uncertainties do not explain.

    Method of moments (as for the between-study variance of a meta-analysis): the smallest
    ``tau >= 0`` with ``sum |r_i|² / (s_i² + tau²) = 2M - n_params`` over the M points' residual
    vectors ``r_i`` and stated per-axis uncertainties ``s_i``. 0 when the stated uncertainties
    already explain the residuals. On real photographs of a board that no lens model fits to
    the detectors' precision (udacity 9x6: residuals 0.86 px against stated 0.003 px) it is
    what the points' error really is, and the weights become nearly uniform.
    """
    r2 = np.sum(np.asarray(residuals_px, dtype=np.float64).reshape(-1, 2) ** 2, axis=1)
    s2 = np.asarray(sigmas_px, dtype=np.float64).reshape(-1) ** 2
    ok = np.isfinite(r2) & np.isfinite(s2)
    r2, s2 = r2[ok], s2[ok]
    target = 2 * len(r2) - n_params
    if target <= 0 or np.sum(r2 / np.maximum(s2, 1e-300)) <= target:
        return 0.0
    lo, hi = 0.0, float(np.max(r2)) + 1e-300
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if np.sum(r2 / (s2 + mid)) > target:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-9 * hi:
            break
    return float(np.sqrt(0.5 * (lo + hi)))
