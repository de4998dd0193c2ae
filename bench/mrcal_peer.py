"""mrcal's side of bench/intrinsics_real.py: run by the *system* Python (``/usr/bin/python3``), where
Debian's mrcal lives (``apt-get install -y mrcal python3-mrcal``); it imports nothing of cellctl.

Reads one JSON request on stdin, writes one JSON answer on stdout:

- ``{"op": "diff", "pairs": [[A, B], ...], "points_px": [[u, v], ...]}``: for each pair of
  ``.cameramodel`` files, the projection difference the way ``calibration.intrinsics
  .projection_difference(A, B, points)`` computes it: B's rays through the points are projected
  by A after the camera-frame rotation that minimises the squared differences (rotation
  compensated); points whose ray does not project back onto them through B (within 0.1 px) are
  left out. Answer ``{"rms_px": [...], "max_px": [...], "left_out": [...]}``.
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


def main() -> None:
    req = json.load(sys.stdin)
    if req["op"] == "diff":
        pts = np.asarray(req["points_px"], dtype=float)
        res = [_diff(a, b, pts) for a, b in req["pairs"]]
        out = {"rms_px": [r[0] for r in res], "max_px": [r[1] for r in res], "left_out": [r[2] for r in res]}
    else:
        raise SystemExit(f"unknown op {req['op']!r}")
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
