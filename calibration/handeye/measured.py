"""Hand-eye from a measured target frame (the space-robot paper: base, flange and 3D target
measured with a laser tracker), from one station up — no AX=XB motion needed.

Eye-in-hand: ``T_base_target`` measured; ``C_i = inv(X) · inv(G_i) · Z`` gives ``X = T_tool_cam``
from every station. Eye-to-hand: ``T_tool_target`` measured; ``C_i = inv(X) · G_i · Z`` gives
``X = T_base_cam``. (``G_i = T_base_tool``, ``C_i = T_cam_target``; metres, radians.)

Estimate (ours; maximum likelihood under stated noise): ``X`` (6), a correction of the measured
frame with the tracker's noise as a Gaussian prior (6) and a correction per station of the
recorded robot pose with the robot's noise as prior (6 each), minimising the reprojection error
of every target point (pixel noise estimated from the per-station PnP residuals unless stated).
Noise models (1-σ per axis): robot — ``calibration.handeye``'s (orientation ``Exp(w)`` and
position in the base frame); tracker — the same form on the measured frame (in the frame it is
expressed in: base for ``T_base_target``, tool for ``T_tool_target``). Covariance of ``X`` from
the normal matrix, scaled by the reduced χ² when the data are noisier than stated; its
``uncertainty`` block has the 6-DOF hand-eye's form, so ``calibration.measure.pixel_to_robot`` maps
pixels with the result unchanged. :func:`compare_handeye` checks an AX=XB result against it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import as_transform, invert, make_transform, perturb, rotation_angle
from calibration.handeye.dof4 import Station4, make_stations4
from calibration.handeye.model import HandEyeError, RobotNoise
from calibration.handeye.stations import StationProblem
from calibration.observations import Detection
from calibration.targets import Target

Mat4 = NDArray[np.float64]
F64 = NDArray[np.float64]
SETUPS: Final = ("eye-in-hand", "eye-to-hand")
DEFAULT_TRACKER = RobotNoise(0.03, 0.005)


def x_from_station(setup: str, G: Mat4, Z: Mat4, C: Mat4) -> Mat4:
    """The hand-eye transform one station gives with the measured frame ``Z``."""
    return (invert(G) if setup == "eye-in-hand" else G) @ Z @ invert(C)


class _JointMeasured(StationProblem):
    """Reprojection with X (6), a correction of the measured frame with the tracker's prior (6) and
    the per-station robot corrections (``calibration.handeye.stations``)."""

    n_lead = 12

    def __init__(self, setup: str, st: Sequence[Station4], camera: CameraModel, sigma_px: float,
                 robot: RobotNoise, tracker: RobotNoise, X0: Mat4, Z_meas: Mat4) -> None:
        super().__init__(setup, st, camera, sigma_px, robot)
        self.sig = np.array([np.radians(tracker.sigma_deg)] * 3 + [tracker.sigma_mm * 1e-3] * 3)
        self.X0, self.Z0 = X0, Z_meas

    def lead(self, x: F64) -> tuple[Mat4, Mat4]:
        return perturb(self.X0, x[:6]), perturb(self.Z0, x[6:12])

    def lead_prior(self, x: F64) -> F64:
        return np.asarray(x[6:12] / self.sig, dtype=np.float64)

    def lead_prior_jacobian(self) -> F64:
        J = np.zeros((6, self.n_lead))
        J[np.arange(6), 6 + np.arange(6)] = 1.0 / self.sig
        return J


@dataclass
class MeasuredHandEyeResult:
    setup: str
    X: Mat4
    cov_X: F64
    json: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return self.json


def calibrate_handeye_measured(setup: str, T_base_tool: Sequence[ArrayLike], detections: Sequence[Detection],
                               camera: CameraModel, target: Target, T_measured: ArrayLike,
                               robot_noise: RobotNoise | None = None, tracker_noise: RobotNoise | None = None,
                               sigma_px: float | None = None) -> MeasuredHandEyeResult:
    """Hand-eye of ``setup`` with the measured frame ``T_measured`` (eye-in-hand ``T_base_target``,
    eye-to-hand ``T_tool_target``, metres); see the module docstring. Raises HandEyeError."""
    t0 = time.perf_counter()
    if setup not in SETUPS:
        raise HandEyeError(f"setup must be one of {SETUPS}, got {setup!r}")
    name_Z = "T_base_target" if setup == "eye-in-hand" else "T_tool_target"
    Z_meas = as_transform(T_measured, f"measured {name_Z}")
    robot = robot_noise or RobotNoise()
    tracker = tracker_noise or DEFAULT_TRACKER
    stations, problems = make_stations4(T_base_tool, detections, camera, target)
    if not stations:
        raise HandEyeError("no station with a detected target: the measured frame needs at least one image of it")
    Xs = [x_from_station(setup, s.G, Z_meas, s.C) for s in stations]
    X0 = make_transform(Rotation.from_matrix(np.array([x[:3, :3] for x in Xs])).mean().as_matrix(),
                        np.mean([x[:3, 3] for x in Xs], axis=0))
    if sigma_px is None:
        ssr = sum(s.pnp_rms_px**2 * len(s.obj) for s in stations)
        dof = sum(2 * len(s.obj) for s in stations) - 6 * len(stations)
        sigma_px = float(max(np.sqrt(ssr / max(dof, 1)), 1e-3))
    job = _JointMeasured(setup, stations, camera, sigma_px, robot, tracker, X0, Z_meas)
    sol = least_squares(job.residuals, np.zeros(12 + 6 * job.n), jac=job.jacobian, method="lm", x_scale="jac",
                        max_nfev=100)
    X, Z, _ = job.poses(sol.x)
    job2 = _JointMeasured(setup, stations, camera, sigma_px, robot, tracker, X, Z_meas)
    x1 = sol.x.copy()
    x1[:6] = 0.0
    sol = least_squares(job2.residuals, x1, jac=job2.jacobian, method="lm", x_scale="jac", max_nfev=50)
    X, Z, _ = job2.poses(sol.x)
    J = job2.jacobian(sol.x)
    r = sol.fun
    chi2 = float(r @ r / max(len(r) - J.shape[1], 1))
    try:
        cov = np.linalg.inv(J.T @ J) * max(1.0, chi2)
    except np.linalg.LinAlgError as exc:
        raise HandEyeError("the measured-frame solution is singular (no usable target points?)") from exc
    cov_X = np.asarray(cov[:6, :6], dtype=np.float64)
    if chi2 > 4.0:
        problems.append({"code": "noise_model", "severity": "warning",
                         "message": f"the residuals are {np.sqrt(chi2):.1f}x larger than the stated noise (pixel "
                                    f"{sigma_px:.3g} px, robot {robot.sigma_mm:g} mm / {robot.sigma_deg:g} deg, "
                                    f"tracker {tracker.sigma_mm:g} mm / {tracker.sigma_deg:g} deg); the uncertainty "
                                    "was scaled up accordingly"})
    n_px = 2 * len(job2.uv)
    r_px = r[:n_px].reshape(-1, 2) * sigma_px
    spread = [float(np.degrees(rotation_angle(x[:3, :3].T @ X[:3, :3]))) for x in Xs]
    poses = [{"image": s.image, "points": len(s.obj), "pnp_rms_px": s.pnp_rms_px,
              "rms_px": float(np.sqrt(np.mean(np.sum(r_px[job2.sid == k] ** 2, axis=1)))),
              "single_station_diff_deg": spread[k],
              "single_station_diff_mm": float(1e3 * np.linalg.norm(Xs[k][:3, 3] - X[:3, 3]))}
             for k, s in enumerate(stations)]
    name_X = "T_tool_cam" if setup == "eye-in-hand" else "T_base_cam"
    dZ = sol.x[6:12]
    out: dict[str, Any] = {
        "setup": setup, "method": "measured_frame", name_X: X.tolist(), name_Z: Z.tolist(),
        "measured": {name_Z: Z_meas.tolist(), "correction_deg": float(np.degrees(np.linalg.norm(dZ[:3]))),
                     "correction_mm": float(1e3 * np.linalg.norm(dZ[3:]))},
        "stations": len(stations), "rms_px": float(np.sqrt(np.mean(np.sum(r_px * r_px, axis=1)))),
        "uncertainty": {"rot_deg": float(np.degrees(np.sqrt(np.trace(cov_X[:3, :3])))),
                        "trans_mm": float(1e3 * np.sqrt(np.trace(cov_X[3:, 3:]))),
                        "covariance": cov_X.tolist(),
                        "covariance_order": "rotation rad (left perturbation R = Exp(w) R), translation m"},
        "pixel_sigma_px": sigma_px, "chi2_reduced": chi2,
        "robot_noise": {"sigma_mm": robot.sigma_mm, "sigma_deg": robot.sigma_deg, "estimated": False,
                        "model": "per axis, base frame: position N(0, sigma_mm^2), orientation Exp(w) with "
                                 "w ~ N(0, sigma_deg^2)"},
        "tracker_noise": {"sigma_mm": tracker.sigma_mm, "sigma_deg": tracker.sigma_deg,
                          "model": f"per axis, on the measured {name_Z}, the robot's form"},
        "poses": poses, "time_s": time.perf_counter() - t0, "camera": camera.to_dict(),
        "verdict": {"ok": True, "problems": problems},
    }
    return MeasuredHandEyeResult(setup, X, cov_X, out)


def compare_handeye(he: dict[str, Any], measured: MeasuredHandEyeResult) -> dict[str, Any]:
    """Difference of an (AX=XB) ``he.json`` from the measured-frame result: rotation (deg),
    translation (mm) and the translation difference in units of the combined 1-σ."""
    key = "T_tool_cam" if measured.setup == "eye-in-hand" else "T_base_cam"
    if he.get("setup") != measured.setup or key not in he:
        raise HandEyeError(f"the hand-eye to check must be an {measured.setup} he.json with {key}")
    A = as_transform(np.asarray(he[key], dtype=np.float64), key)
    d_rot = float(np.degrees(rotation_angle(A[:3, :3].T @ measured.X[:3, :3])))
    dv = A[:3, 3] - measured.X[:3, 3]
    cov_a = np.asarray(he.get("uncertainty", {}).get("covariance", np.zeros((6, 6))), dtype=np.float64)
    S = cov_a[3:, 3:] + measured.cov_X[3:, 3:]
    w = Rotation.from_matrix(A[:3, :3] @ measured.X[:3, :3].T).as_rotvec()
    Sr = cov_a[:3, :3] + measured.cov_X[:3, :3]
    return {"rot_deg": d_rot, "trans_mm": float(1e3 * np.linalg.norm(dv)),
            "trans_sigmas": float(np.sqrt(dv @ np.linalg.solve(S, dv))) if np.linalg.det(S) > 0 else float("nan"),
            "rot_sigmas": float(np.sqrt(w @ np.linalg.solve(Sr, w))) if np.linalg.det(Sr) > 0 else float("nan"),
            "note": "sigmas: Mahalanobis distance under both results' covariances (about 1-3 when they agree)"}
