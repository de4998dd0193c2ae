"""4-DOF hand-eye: robots whose tool only turns about the base z axis (SCARA, delta, top-down picking).

Our own code: OpenCV has no 4-DOF hand-eye (HALCON's ``calibrate_hand_eye`` for SCARA does).
Conventions as ``calibration.handeye``: ``G_i = T_base_tool``, ``C_i = T_cam_target``;
eye-in-hand ``X = T_tool_cam``, ``Z = T_base_target``; eye-to-hand ``X = T_base_cam``,
``Z = T_tool_target``; ``Z = H_i X C_i`` with ``H_i = G_i`` or ``inv(G_i)``. Metres, radians.

The motion. Every robot orientation is ``R_i = Rz(θ_i) R_0`` (``R_0`` the first station's, a
tool pointing down is fine). Rotations about one axis leave one thing unseen: moving the camera
along the tool's z axis together with the target along the base z axis (eye-to-hand: the camera
along base z, the target along tool z) changes no image. Everything else — the camera's tilt
against the tool, its turn about z, its x/y — is seen. The unseen part is fixed by the target's
height: ``target_z`` is the base-frame z of the target origin (eye-in-hand), or of the target
origin at the *first* pose of the file (eye-to-hand, the target moving with the tool).

Solution.

1. Closed form: the camera-frame axis of every relative target rotation is the tool z axis seen
   from the camera, which gives the tilt ``R_tilt``; then ``cos ψ, sin ψ`` of the turn about z and
   the translations are linear in ``Z = H_i X C_i`` over all stations (least squares).
2. Joint refinement on reprojection (maximum likelihood, as the 6-DOF solver): ``X`` (6),
   ``Z`` (5: its translation along the unseen direction held at ``target_z``) and a small pose
   correction per station with the stated robot noise as a Gaussian prior.
3. Covariance of ``X`` from the normal matrix, scaled by the reduced χ² when the data are
   noisier than stated, plus the stated uncertainty of ``target_z`` along the unseen direction.

The result is a ``he.json`` like the 6-DOF one (``calibration.measure.pixel_to_robot`` maps pixels with
it unchanged) with ``"dof": 4`` and ``"fixed_by_constraint"`` saying what the height fixed.
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
from calibration.geometry import as_transform, exp_so3, invert, make_transform, rot_z, rotation_angle
from calibration.handeye.dof4_budget import budget_problem, mapping_budget
from calibration.handeye.dof4_checks import check_dof4_motion, pair_residuals
from calibration.handeye.model import HandEyeError, RobotNoise
from calibration.handeye.stations import StationProblem
from calibration.observations import Detection
from calibration.pose import PoseEstimationError, estimate_pose
from calibration.targets import Target

Mat4 = NDArray[np.float64]
F64 = NDArray[np.float64]
SETUPS: Final = ("eye-in-hand", "eye-to-hand")
MIN_STATIONS: Final = 3
RECOMMENDED_STATIONS: Final = 8
DEFAULT_TARGET_Z_SIGMA_MM: Final = 0.1


@dataclass
class Station4:
    image: str
    G: Mat4
    obj: F64
    uv: F64
    C: Mat4
    pnp_rms_px: float


def make_stations4(T_base_tool: Sequence[ArrayLike], detections: Sequence[Detection], camera: CameraModel,
                   target: Target) -> tuple[list[Station4], list[dict[str, str]]]:
    """Pair robot poses with detections and give each station its ``T_cam_target`` (PnP)."""
    if len(T_base_tool) != len(detections):
        raise HandEyeError(f"{len(T_base_tool)} robot poses but {len(detections)} images: each image needs "
                           "exactly one robot pose (check poses.csv)")
    tp = target.points()
    lookup = {int(i): k for k, i in enumerate(tp.ids)}
    out: list[Station4] = []
    problems: list[dict[str, str]] = []
    for k, (G_raw, det) in enumerate(zip(T_base_tool, detections, strict=True)):
        G = as_transform(G_raw, f"robot pose {k} ({det.image})")
        if not det.found or len(det.ids) < 4:
            problems.append({"code": "view_not_used", "severity": "warning",
                             "message": f"{det.image}: target not found ({det.reason or 'too few points'}); left out"})
            continue
        unknown = [int(i) for i in det.ids if int(i) not in lookup]
        if unknown:
            raise HandEyeError(f"{det.image}: point ids {unknown[:5]} are not on the target; wrong target file?")
        obj = tp.xyz_m[[lookup[int(i)] for i in det.ids]]
        uv = np.asarray(det.uv, dtype=np.float64).reshape(-1, 2)
        try:
            pose = estimate_pose(camera, obj, uv)
        except PoseEstimationError as exc:
            raise HandEyeError(f"{det.image}: target pose failed: {exc}") from exc
        out.append(Station4(det.image, G, obj, uv, pose.T_cam_target, pose.rms_px))
    return out, problems


def closed_form_dof4(setup: str, G: Sequence[Mat4], C: Sequence[Mat4], target_z_m: float,
                     G_ref: Mat4) -> tuple[Mat4, Mat4]:
    """``(X, Z)`` in closed form from 4-DOF motion; ``G_ref`` is the pose ``target_z_m`` refers to
    (eye-to-hand) and whose orientation is ``R_0``."""
    R0 = G_ref[:3, :3]
    theta = np.array([np.arctan2(*(g[:3, :3] @ R0.T)[[1, 0], 0]) for g in G])
    # H*_i = [Rz(phi_i), s_i]: the robot with R_0 taken out (module docstring)
    if setup == "eye-in-hand":
        phi = theta
        s = np.array([g[:3, 3] for g in G])
        z_star = target_z_m
    else:
        phi = -theta
        s = np.array([-rot_z(-th) @ g[:3, 3] for th, g in zip(theta, G, strict=True)])
        z_star = target_z_m - G_ref[2, 3]
    n_acc = np.zeros(3)
    w_acc = 0.0
    for i in range(len(G)):
        for j in range(i + 1, len(G)):
            d = float(np.angle(np.exp(1j * (phi[i] - phi[j]))))
            if not np.radians(3.0) <= abs(d) <= np.radians(170.0):
                continue
            B = C[j] @ invert(C[i])
            b = Rotation.from_matrix(B[:3, :3]).as_rotvec()
            n_acc += d * b
            w_acc += d * d
    if w_acc == 0.0:
        raise HandEyeError("the tool turns less than 3 deg between every two stations: turn it by 20-90 deg "
                           "about z between stations")
    n = n_acc / np.linalg.norm(n_acc)  # tool z axis seen in the camera (X*^T e_z)
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(n, ez)
    ang = float(np.arctan2(np.linalg.norm(axis), n @ ez))
    R_tilt = exp_so3(axis / np.linalg.norm(axis) * ang) if np.linalg.norm(axis) > 1e-12 else np.eye(3)
    rows, rhs = [], []
    for k, Ck in enumerate(C):
        p = R_tilt @ Ck[:3, 3]
        Rh = rot_z(phi[k])
        M = np.zeros((3, 7))  # unknowns: cos psi, sin psi, t_X (3), t_Z x, t_Z y
        M[:, 0] = -Rh @ np.array([p[0], p[1], 0.0])
        M[:, 1] = -Rh @ np.array([-p[1], p[0], 0.0])
        M[:, 2:5] = -Rh
        M[0, 5] = M[1, 6] = 1.0
        rows.append(M)
        rhs.append(s[k] + np.array([0.0, 0.0, p[2]]) - np.array([0.0, 0.0, z_star]))
    A, b = np.vstack(rows), np.concatenate(rhs)
    if np.linalg.matrix_rank(A, tol=1e-9 * np.linalg.norm(A)) < 7:
        raise HandEyeError("the stations do not determine a 4-DOF hand-eye: move the flange in x and y between "
                           "stations as well as turning the tool about z")
    sol = np.linalg.lstsq(A, b, rcond=None)[0]
    R_X = rot_z(float(np.arctan2(sol[1], sol[0]))) @ R_tilt
    R_Z = Rotation.from_matrix(np.array([rot_z(ph) @ R_X @ Ck[:3, :3] for ph, Ck in zip(phi, C, strict=True)])).mean()
    # translations again with the rotation fixed
    rows, rhs = [], []
    for k, Ck in enumerate(C):
        Rh = rot_z(phi[k])
        M = np.zeros((3, 5))
        M[:, 0:3] = -Rh
        M[0, 3] = M[1, 4] = 1.0
        rows.append(M)
        rhs.append(Rh @ R_X @ Ck[:3, 3] + s[k] - np.array([0.0, 0.0, z_star]))
    t = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    X_star = make_transform(R_X, t[:3])
    Z_star = make_transform(R_Z.as_matrix(), [t[3], t[4], z_star])
    T0 = make_transform(R0, np.zeros(3))
    if setup == "eye-in-hand":
        return invert(T0) @ X_star, Z_star
    return X_star, invert(T0) @ Z_star


class _Joint4(StationProblem):
    """Reprojection with X (6), Z (5: its translation moves only across the unseen direction) and
    the per-station robot corrections (``calibration.handeye.stations``)."""

    n_lead = 11

    def __init__(self, setup: str, st: Sequence[Station4], camera: CameraModel, sigma_px: float,
                 noise: RobotNoise, X0: Mat4, Z0: Mat4, gauge_Z: F64) -> None:
        super().__init__(setup, st, camera, sigma_px, noise)
        self.X0, self.Z0 = X0, Z0
        u1 = np.cross(gauge_Z, [1.0, 0.0, 0.0] if abs(gauge_Z[0]) < 0.9 else [0.0, 1.0, 0.0])
        u1 /= np.linalg.norm(u1)
        self.U = np.column_stack([u1, np.cross(gauge_Z, u1)])  # Z's translation moves in this plane only

    def lead(self, x: F64) -> tuple[Mat4, Mat4]:
        X = make_transform(exp_so3(x[0:3]) @ self.X0[:3, :3], self.X0[:3, 3] + x[3:6])
        Z = make_transform(exp_so3(x[6:9]) @ self.Z0[:3, :3], self.Z0[:3, 3] + self.U @ x[9:11])
        return X, Z


@dataclass
class HandEyeDof4Result:
    setup: str
    X: Mat4
    Z: Mat4
    cov_X: F64
    cov_Z: F64
    json: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return self.json


def calibrate_handeye_dof4(setup: str, T_base_tool: Sequence[ArrayLike], detections: Sequence[Detection],
                           camera: CameraModel, target: Target, target_z_mm: float,
                           robot_noise: RobotNoise | None = None, target_z_sigma_mm: float = DEFAULT_TARGET_Z_SIGMA_MM,
                           sigma_px: float | None = None, max_tilt_deg: float = 1.0,
                           leave_one_out: bool = True) -> HandEyeDof4Result:
    """4-DOF hand-eye of ``setup`` (module docstring); ``target_z_mm`` in the base frame (mm).

    Raises HandEyeError with the reason and the fix: fewer than 3 stations, poses that are not
    4-DOF (a tool tilted more than ``max_tilt_deg`` against the first pose), no turn, no x/y motion.
    """
    t_start = time.perf_counter()
    if setup not in SETUPS:
        raise HandEyeError(f"setup must be one of {SETUPS}, got {setup!r}")
    if not (np.isfinite(target_z_mm) and abs(target_z_mm) < 1e5):
        raise HandEyeError(f"the target origin's height target_z_mm must be a finite height in mm (base frame), "
                           f"got {target_z_mm}")
    if not (target_z_sigma_mm >= 0 and np.isfinite(target_z_sigma_mm)):
        raise HandEyeError("the target height's uncertainty must be >= 0 mm")
    noise = robot_noise or RobotNoise()
    if len(T_base_tool) == 0:
        raise HandEyeError("no robot poses given")
    G_ref = as_transform(T_base_tool[0], "robot pose 0")
    stations, problems = make_stations4(T_base_tool, detections, camera, target)
    if len(stations) < MIN_STATIONS:
        raise HandEyeError(f"4-DOF hand-eye needs at least {MIN_STATIONS} stations with a detected target, got "
                           f"{len(stations)}; capture {RECOMMENDED_STATIONS}-20, turned 20-90 deg about z and "
                           "moved in x/y")
    if len(stations) < RECOMMENDED_STATIONS:
        problems.append({"code": "few_poses", "severity": "warning",
                         "message": f"only {len(stations)} stations; {RECOMMENDED_STATIONS}-20 are recommended"})
    G = [s.G for s in stations]
    C = [s.C for s in stations]
    motion = check_dof4_motion(G, G_ref, max_tilt_deg)
    z_m = target_z_mm * 1e-3
    X0, Z0 = closed_form_dof4(setup, G, C, z_m, G_ref)
    X_cf = X0
    if sigma_px is None:
        ssr = sum(s.pnp_rms_px**2 * len(s.obj) for s in stations)
        dof = sum(2 * len(s.obj) for s in stations) - 6 * len(stations)
        sigma_px = float(max(np.sqrt(ssr / max(dof, 1)), 1e-3))
    ez = np.array([0.0, 0.0, 1.0])
    gauge_Z = ez if setup == "eye-in-hand" else G_ref[:3, :3].T @ ez
    gauge_X = G_ref[:3, :3].T @ ez if setup == "eye-in-hand" else ez
    x, job = np.zeros(0), None
    for _ in range(2):  # re-linearise once at the solution
        job = _Joint4(setup, stations, camera, sigma_px, noise, X0, Z0, gauge_Z)
        x0 = np.zeros(11 + 6 * job.n) if x.size == 0 else np.concatenate([np.zeros(11), x[11:]])
        sol = least_squares(job.residuals, x0, jac=job.jacobian, method="lm", x_scale="jac", max_nfev=100)
        x = sol.x
        X0, Z0, _ = job.poses(x)
    if job is None:  # pragma: no cover
        raise HandEyeError("refinement did not run")
    J = job.jacobian(x)
    r = sol.fun
    chi2 = float(r @ r / max(len(r) - J.shape[1], 1))
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError as exc:
        raise HandEyeError("the 4-DOF refinement is singular: turn the tool more and move it in x/y") from exc
    scale = max(1.0, chi2)
    cov_X = np.asarray(cov[:6, :6] * scale, dtype=np.float64)
    budget = mapping_budget(setup, [s.G for s in stations], [s.C for s in stations], [s.obj for s in stations],
                            X0, Z0, cov_X.copy(), camera, sigma_px, noise)
    if (bp := budget_problem(budget)) is not None:
        problems.append(bp)
    cov_X[3:, 3:] += (target_z_sigma_mm * 1e-3) ** 2 * np.outer(gauge_X, gauge_X)
    cov_Z = np.zeros((6, 6))
    cov_Z[:3, :3] = cov[6:9, 6:9] * scale
    cov_Z[3:, 3:] = job.U @ cov[9:11, 9:11] @ job.U.T * scale + (target_z_sigma_mm * 1e-3) ** 2 * np.outer(
        gauge_Z, gauge_Z)
    X, Z = X0, Z0
    if chi2 > 4.0:
        problems.append({"code": "noise_model", "severity": "warning",
                         "message": f"the residuals are {np.sqrt(chi2):.1f}x larger than the stated noise (pixel "
                                    f"{sigma_px:.3g} px, robot {noise.sigma_mm:g} mm / {noise.sigma_deg:g} deg); "
                                    "the uncertainty was scaled up accordingly"})
    r_px = r[: 2 * len(job.obj)].reshape(-1, 2) * sigma_px
    d = x[11:].reshape(job.n, 6)
    poses = []
    for k, s in enumerate(stations):
        rk = r_px[job.sid == k]
        poses.append({"image": s.image, "used": True, "points": len(s.obj),
                      "rms_px": float(np.sqrt(np.mean(np.sum(rk * rk, axis=1)))), "pnp_rms_px": s.pnp_rms_px,
                      "robot_correction_mm": float(1e3 * np.linalg.norm(d[k, 3:])),
                      "robot_correction_deg": float(np.degrees(np.linalg.norm(d[k, :3])))})
    rot, tr = pair_residuals(setup, G, C, X)
    init_rot = float(np.degrees(rotation_angle(X_cf[:3, :3].T @ X[:3, :3])))
    init_mm = float(1e3 * np.linalg.norm(X_cf[:3, 3] - X[:3, 3]))
    names = ("T_tool_cam", "T_base_target") if setup == "eye-in-hand" else ("T_base_cam", "T_tool_target")
    fixed_what = ("T_tool_cam translation along the tool z axis" if setup == "eye-in-hand"
                  else "T_base_cam translation along the base z axis")
    fixed = {"constraint": "target origin height in the base frame" +
                           ("" if setup == "eye-in-hand" else " at the first pose of the file"),
             "target_z_mm": target_z_mm, "target_z_sigma_mm": target_z_sigma_mm,
             "fixed": [fixed_what, f"{names[1]} translation along the "
                                   f"{'base' if setup == 'eye-in-hand' else 'tool'} z axis"],
             "unseen_direction_X": gauge_X.tolist(), "unseen_direction_Z": gauge_Z.tolist(),
             "observed": ["rotation of the camera about z", "tilt between tool and camera (rotation about x, y)",
                          "x/y translation"],
             "not_determined_by_data": unseen_by_data(setup, [s.C for s in stations], target_z_sigma_mm)}
    errors = [p for p in problems if p["severity"] == "error"]
    out: dict[str, Any] = {
        "setup": setup, "dof": 4, names[0]: X.tolist(), names[1]: Z.tolist(),
        "fixed_by_constraint": fixed,
        "rms_px": float(np.sqrt(np.mean(np.sum(r_px * r_px, axis=1)))),
        "rot_deg": _stats(rot), "trans_mm": _stats(tr),
        "uncertainty": {"rot_deg": float(np.degrees(np.sqrt(np.trace(cov_X[:3, :3])))),
                        "trans_mm": float(1e3 * np.sqrt(np.trace(cov_X[3:, 3:]))),
                        "covariance": cov_X.tolist(),
                        "covariance_order": "rotation rad (left perturbation R = Exp(w) R), translation m",
                        "target_rot_deg": float(np.degrees(np.sqrt(np.trace(cov_Z[:3, :3])))),
                        "target_trans_mm": float(1e3 * np.sqrt(np.trace(cov_Z[3:, 3:]))),
                        "target_covariance": cov_Z.tolist()},
        "pixel_sigma_px": sigma_px, "chi2_reduced": chi2,
        "robot_noise": {"sigma_mm": noise.sigma_mm, "sigma_deg": noise.sigma_deg, "estimated": False,
                        "model": "per axis, base frame: position N(0, sigma_mm^2), orientation Exp(w) with "
                                 "w ~ N(0, sigma_deg^2)"},
        "motion": motion, "poses": poses, "mapping_budget": budget,
        "leave_one_out": (_leave_one_out(setup, stations, camera, sigma_px, noise, X, Z, gauge_Z)
                          if leave_one_out and len(stations) > MIN_STATIONS else {}),
        "init": {"closed_form_diff_to_refined_deg": init_rot, "closed_form_diff_to_refined_mm": init_mm},
        "time_s": time.perf_counter() - t_start, "camera": camera.to_dict(),
        "verdict": {"ok": not errors, "problems": problems},
    }
    return HandEyeDof4Result(setup, X, Z, cov_X, cov_Z, out)


def unseen_by_data(setup: str, C: Sequence[Mat4], target_z_sigma_mm: float) -> dict[str, Any]:
    """What 4-DOF stations cannot determine, what it costs a mapping, and what to add to determine it.

    ``C``: the stations' ``T_cam_target`` (metres). A height error ``dz`` of the target moves the camera by
    ``dz`` along the unseen direction: pixels mapped onto a plane given on its own (``plane_z_mm``)
    then scale by ``dz / working distance`` about the point under the camera, i.e. ``r dz / d`` mm at
    ``r`` mm from it (base x/y); pixels mapped onto the target's own stated plane are unaffected."""
    d_mm = float(1e3 * np.median([c[2, 3] for c in C])) if len(C) else float("nan")
    cam = "the camera's height on the tool (T_tool_cam along the tool z axis)" if setup == "eye-in-hand" else \
        "the fixed camera's height (T_base_cam along the base z axis)"
    return {
        "parameter": cam,
        "why": "turns about one vertical axis and x/y/z moves show the same images when the camera and the "
               "target shift together along that axis, so the images fix only their sum; target_z_mm fixes it",
        "tool_offset": "the tool's own offset (TCP) along its z axis is not seen by the camera at all: pick "
                       "heights rely on the robot's TCP setting (calib tcp measures its x/y only)",
        "working_distance_mm": d_mm,
        "map_error_mm_per_mm_of_height_at_100mm_from_nadir": 100.0 / d_mm if d_mm > 0 else float("nan"),
        "from_target_z_sigma_mm_at_100mm_from_nadir": 100.0 * target_z_sigma_mm / d_mm if d_mm > 0 else float("nan"),
        "to_determine_it": ["measure the target's height target_z_mm with the tool tip touching the plate "
                            "(a calibrated TCP) and state its uncertainty (target_z_sigma_mm)",
                            "or add 3+ stations with the tool tilted 15-30 deg about x and y and solve 6-DOF "
                            "(only on an arm that can tilt)",
                            "map onto the target's own plane (plane_z_mm = target_z_mm) where the height "
                            "error cancels"],
    }


def _leave_one_out(setup: str, stations: Sequence[Station4], camera: CameraModel, sigma_px: float,
                   noise: RobotNoise, X: Mat4, Z: Mat4, gauge_Z: F64) -> dict[str, Any]:
    """Refit without station i (warm start), predict what its recorded pose shows, compare with its
    image: target origin distance (mm), rotation (deg) and reprojection RMS (px) of the prediction."""
    per = []
    for i, s in enumerate(stations):
        job = _Joint4(setup, [t for k, t in enumerate(stations) if k != i], camera, sigma_px, noise, X, Z, gauge_Z)
        sol = least_squares(job.residuals, np.zeros(11 + 6 * job.n), jac=job.jacobian, method="lm",
                            x_scale="jac", max_nfev=20)
        Xi, Zi, _ = job.poses(sol.x)
        Cp = invert(Xi) @ (invert(s.G) if setup == "eye-in-hand" else s.G) @ Zi
        e = camera.project(s.obj @ Cp[:3, :3].T + Cp[:3, 3]) - s.uv
        per.append({"image": s.image, "position_mm": float(1e3 * np.linalg.norm(Cp[:3, 3] - s.C[:3, 3])),
                    "rotation_deg": float(np.degrees(rotation_angle(Cp[:3, :3].T @ s.C[:3, :3]))),
                    "rms_px": float(np.sqrt(np.mean(np.sum(e * e, axis=1))))})
    return {"per_pose": per, "position_mm": _stats(np.array([p["position_mm"] for p in per])),
            "rms_px": _stats(np.array([p["rms_px"] for p in per]))}


def _stats(x: F64) -> dict[str, float]:
    if x.size == 0:
        return {"mean": float("nan"), "rms": float("nan"), "max": float("nan")}
    return {"mean": float(np.mean(x)), "rms": float(np.sqrt(np.mean(x * x))), "max": float(np.max(x))}
