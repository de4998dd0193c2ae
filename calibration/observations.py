"""Detected target points of one image: the contract between detection and the solvers.

Pixels are ``(u, v)``, (0, 0) the centre of the top-left pixel. For circle marks ``uv`` is the
image of each mark's *centre* (perspective bias corrected as well as the detector could without
a calibrated camera) and ``uv_ellipse`` the raw fitted-ellipse centre, which solvers that know
the camera use with ``calibration.conic.circle_centre_bias_px`` inside their loop.

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
"""Part of the typical point's error that no local fit sees (lens model, bias residue), as a
fraction of the median point uncertainty: it caps any point's weight at ~2.2x the typical one."""
POINT_OUTLIER_FACTOR: Final = 3.0
"""A point whose own uncertainty exceeds its view's median by this factor is weighted down on its own."""


def point_weights(sigmas: Sequence[NDArray[np.float64] | None], counts: Sequence[int]) -> list[NDArray[np.float64]]:
    """Relative residual weights ``1 / s_i`` of the points of several detections (views).

    The weight follows the *view's* precision: ``r_v`` = the view's median point uncertainty over
    the median of all points; a point only departs from its view when its own uncertainty is
    more than ``POINT_OUTLIER_FACTOR`` times the view's (a window without structure). Per-point
    estimates scatter too much to weight by one by one: on rendered circle plates that made the
    calibration 2.8x worse than unweighted, while a blurred or noisy view as a whole is what must
    stop dominating. Then ``s = sqrt(r² + f²) / sqrt(1 + f²)`` with ``f`` = ``SYSTEMATIC_FLOOR``, so
    the typical point weighs about 1 and the solvers' residual scale stays in pixels. Views
    without uncertainties (``None``) weigh 1.
    """
    finite = [s[np.isfinite(s) & (s > 0)] for s in sigmas if s is not None]
    allv = np.concatenate(finite) if finite else np.zeros(0)
    if allv.size == 0:
        return [np.ones(n) for n in counts]
    med = float(np.median(allv))
    f2 = SYSTEMATIC_FLOOR**2
    out = []
    for s, n in zip(sigmas, counts, strict=True):
        if s is None:
            out.append(np.ones(n))
            continue
        sv = np.asarray(s, dtype=np.float64)
        ok = np.isfinite(sv) & (sv > 0)
        view = float(np.median(sv[ok])) if ok.any() else med
        own = np.where(ok, sv, 1e3 * view) / (POINT_OUTLIER_FACTOR * view)
        r = view / med * np.maximum(1.0, own)
        out.append(np.sqrt(1.0 + f2) / np.sqrt(r * r + f2))
    return out
