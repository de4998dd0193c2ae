"""mrcal's side of bench/intrinsics_real.py: run by the *system* Python (``/usr/bin/python3``), where
Debian's mrcal lives (``apt-get install -y mrcal python3-mrcal``); it imports nothing of cellctl.

Reads one JSON request on stdin, writes one JSON answer on stdout:

- ``{"op": "diff", "pairs": [[A, B], ...], "points_px": [[u, v], ...]}``: for each pair of
  ``.cameramodel`` files, the projection difference the way ``calibration.intrinsics
  .projection_difference(A, B, points)`` computes it: B's rays through the points are projected
  by A after the camera-frame rotation that minimises the squared differences (rotation
  compensated); points whose ray does not project back onto them through B (within 0.1 px) are
  left out. Answer ``{"rms_px": [...], "max_px": [...], "left_out": [...]}``.
- ``{"op": "residuals", "model": M}``: the board residuals of a ``.cameramodel`` that carries its
  ``optimization_inputs`` (mrcal's published solves), at its stored solution, counted four ways over
  the inliers (weight > 0): weighted (mrcal's ``weight`` = 2^-level times the pixel error) per
  coordinate (what mrcal 2.2 prints as ``rms_reproj_error__pixels``) and per corner (the 2020 tour's
  "RMS error"), and unweighted per coordinate and per corner. Answer ``{"weighted_per_coordinate",
  "weighted_per_corner", "unweighted_per_coordinate", "unweighted_per_corner", "inliers", "lensmodel"}``.
"""

from __future__ import annotations

import json
import sys

import mrcal
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

ROUND_TRIP_PX = 0.1


def _diff(model_a: str, model_b: str, pts: np.ndarray) -> tuple[float, float, int]:
    a, b = mrcal.cameramodel(model_a), mrcal.cameramodel(model_b)
    la, ia = a.intrinsics()
    lb, ib = b.intrinsics()
    rays = mrcal.unproject(pts, lb, ib)
    ok = np.all(np.isfinite(rays), axis=1)
    back = np.full(len(pts), np.inf)
    back[ok] = np.linalg.norm(mrcal.project(rays[ok], lb, ib) - pts[ok], axis=1)
    ok &= back < ROUND_TRIP_PX
    rays, p = rays[ok], pts[ok]

    def f(w: np.ndarray) -> np.ndarray:
        q = mrcal.project(rays @ Rotation.from_rotvec(w).as_matrix().T, la, ia)
        return np.nan_to_num(q - p, nan=1e6).reshape(-1)

    w = least_squares(f, np.zeros(3), method="lm", x_scale=1e-3).x
    mag = np.linalg.norm(f(w).reshape(-1, 2), axis=1)
    return float(np.sqrt(np.mean(mag**2))), float(mag.max()), int(np.sum(~ok))


def _residuals(path: str) -> dict[str, object]:
    m = mrcal.cameramodel(path)
    oi = m.optimization_inputs()
    x = mrcal.optimizer_callback(**oi, no_jacobian=True)[1]
    obs = oi["observations_board"]
    w = obs[..., 2].reshape(-1)
    xb = x[: 2 * w.size].reshape(-1, 2)          # weight * (projected - observed), board corners first
    inl = w > 0
    r = xb[inl] / w[inl, None]
    return {"lensmodel": oi["lensmodel"], "inliers": int(inl.sum()),
            "weighted_per_coordinate": float(np.sqrt(np.mean(xb[inl] ** 2))),
            "weighted_per_corner": float(np.sqrt(np.mean(np.sum(xb[inl] ** 2, axis=1)))),
            "unweighted_per_coordinate": float(np.sqrt(np.mean(r**2))),
            "unweighted_per_corner": float(np.sqrt(np.mean(np.sum(r**2, axis=1))))}


def main() -> None:
    req = json.load(sys.stdin)
    if req["op"] == "diff":
        pts = np.asarray(req["points_px"], dtype=float)
        res = [_diff(a, b, pts) for a, b in req["pairs"]]
        out = {"rms_px": [r[0] for r in res], "max_px": [r[1] for r in res], "left_out": [r[2] for r in res]}
    elif req["op"] == "residuals":
        out = _residuals(req["model"])
    else:
        raise SystemExit(f"unknown op {req['op']!r}")
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
