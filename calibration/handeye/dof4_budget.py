"""What a 4-DOF hand-eye's own error adds to pixels mapped onto the target plane, and how many
stations bring it down to a given share.

A pixel mapped onto a plane ``z = const`` (base frame) carries two errors: the one any calibration
has (pixel noise through the working distance, and eye-in-hand the robot's pose noise at capture:
what the TRUE calibration maps with), and the estimate's own (its covariance propagated to the
plane). Their ratio sqrt(p² + c²) / p is what a held-out set measures against the true calibration
(``bench/handeye_special.py``). The estimate's part comes from the robot's pose noise through the
stations and shrinks as 1/sqrt(stations); the maximum-likelihood solve is already at what the
stations hold, so only more stations lower it. Units: metres inside, mm in the output.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.handeye.frames import perturb
from calibration.handeye.model import RobotNoise

Mat4 = NDArray[np.float64]
F64 = NDArray[np.float64]
RATIO_TARGET: Final = 1.2
"""The estimate's error is worth a warning when it makes mapped points worse than this x the truth's."""
WORST_K: Final = 1.96
"""The calibration part's 95th percentile over repeated captures, in its 1σ (measured: 1.79 over 40 seeds
of the 14-station eye-to-hand bench set, whose RMS was 1.06σ; a one-dimensional Gaussian's 1.96)."""


def _map(T_base_cam: Mat4, rays_cam: F64, z_m: F64) -> F64:
    """Base-frame x/y (m) where the camera rays meet the planes ``z = z_m``."""
    d = rays_cam @ T_base_cam[:3, :3].T
    o = T_base_cam[:3, 3]
    s = (z_m - o[2]) / d[:, 2]
    return o[:2] + s[:, None] * d[:, :2]


def mapping_budget(setup: str, G: Sequence[Mat4], C: Sequence[Mat4], obj: Sequence[F64], X: Mat4, Z: Mat4,
                   cov_X_stations: F64, camera: CameraModel, sigma_px: float, noise: RobotNoise,
                   ratio_target: float = RATIO_TARGET) -> dict[str, Any]:
    """The two parts of the map error (mm RMS, base x/y) over the stations' own target points, the
    predicted ratio to the true calibration, and the stations needed for ``ratio_target`` (RMS) and for
    1.5x in 19 of 20 captures.

    ``cov_X_stations``: the covariance of ``X`` from the stations alone (rotation rad, translation m;
    without a stated target-height prior, whose cost ``unseen_by_data`` states on its own)."""
    c2, p2, n_pts = 0.0, 0.0, 0
    eps = 1e-7
    for Gk, Ck, P in zip(G, C, obj, strict=True):
        Pc = P @ Ck[:3, :3].T + Ck[:3, 3]
        rays = Pc / Pc[:, 2:3]
        T_bt = (Z if setup == "eye-in-hand" else Gk @ Z)
        z_m = (P @ T_bt[:3, :3].T + T_bt[:3, 3])[:, 2]
        Gm = Gk if setup == "eye-in-hand" else np.eye(4)

        def f(dx: F64, dg: F64, r: F64 = rays, zz: F64 = z_m, Gx: Mat4 = Gm) -> F64:
            # left rotation Exp(w) R and added translation, as the covariances and the robot noise are stated
            return _map(perturb(Gx, dg) @ perturb(X, dx), r, zz)

        z6 = np.zeros(6)
        J = np.zeros((len(P), 2, 6))
        Jg = np.zeros((len(P), 2, 6))
        for i in range(6):
            e = np.zeros(6)
            e[i] = eps
            J[:, :, i] = (f(e, z6) - f(-e, z6)) / (2 * eps)
            Jg[:, :, i] = (f(z6, e) - f(z6, -e)) / (2 * eps)
        c2 += float(np.einsum("nai,ij,naj->", J, cov_X_stations, J))
        depth = Pc[:, 2]
        p2 += float(np.sum(2.0 * (sigma_px * depth / camera.fx) ** 2))
        if setup == "eye-in-hand":
            S = np.diag([np.radians(noise.sigma_deg) ** 2] * 3 + [(noise.sigma_mm * 1e-3) ** 2] * 3)
            p2 += float(np.einsum("nai,ij,naj->", Jg, S, Jg))
        n_pts += len(P)
    c = 1e3 * math.sqrt(c2 / max(n_pts, 1))
    p = 1e3 * math.sqrt(p2 / max(n_pts, 1))
    n = len(G)
    ratio = math.hypot(p, c) / p if p > 0 else float("nan")

    def need(r: float, k: float = 1.0) -> int:
        """Stations for which k x the calibration part (1σ, shrinking as 1/sqrt(n)) keeps the ratio <= r."""
        return max(n, math.ceil(n * (k * c / p) ** 2 / (r * r - 1.0))) if p > 0 else n

    return {"true_calibration_map_mm": p, "calibration_part_mm": c, "predicted_ratio_to_true_calibration": ratio,
            "ratio_target": ratio_target, "stations": n, "stations_for_ratio_target": need(ratio_target),
            "stations_for_1.5x_in_19_of_20": need(1.5, WORST_K),
            "what": "RMS over the stations' target points on the target plane (base x/y, mm): 'true calibration' ="
                    " pixel noise" + (" and the robot's pose noise at capture" if setup == "eye-in-hand" else "") +
                    ", what any calibration maps with; 'calibration part' = this estimate's own error from the "
                    "stations' robot noise (1σ, the target height exact); it shrinks as 1/sqrt(stations)"}


def budget_problem(b: dict[str, Any]) -> dict[str, str] | None:
    """A warning when the estimate's own error makes mapped points worse than the target ratio."""
    if not b["predicted_ratio_to_true_calibration"] > b["ratio_target"]:
        return None
    return {"code": "stations_limit_mapping", "severity": "warning",
            "message": f"the calibration's own error ({b['calibration_part_mm']:.3f} mm RMS on the target plane, "
                       f"from the robot's pose noise through {b['stations']} stations) makes mapped points "
                       f"{b['predicted_ratio_to_true_calibration']:.2f}x worse than a perfect calibration's "
                       f"{b['true_calibration_map_mm']:.3f} mm; the solve is already at what these stations hold: "
                       f"capture {b['stations_for_ratio_target']} stations for {b['ratio_target']:g}x, "
                       f"{b['stations_for_1.5x_in_19_of_20']} to stay within 1.5x in 19 of 20 captures (turned "
                       "and moved as widely)"}
