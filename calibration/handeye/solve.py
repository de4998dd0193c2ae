"""``calibrate_handeye``: checks, closed forms, joint refinement, covariance, leave-one-out."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike

from calibration.camera_model import CameraModel
from calibration.handeye.checks import check_conventions, check_motion, find_outlier_stations
from calibration.handeye.closed_form import axxb_residuals, opencv_handeye, solve_pairs, stats
from calibration.handeye.frames import (
    make_stations,
    mean_pose,
    predict_cam_target,
    target_from_station,
    transform_error_deg_mm,
)
from calibration.handeye.joint import JointProblem, refine, vce_robot_noise
from calibration.handeye.model import (
    MIN_STATIONS,
    OPENCV_METHODS,
    RECOMMENDED_STATIONS,
    SETUPS,
    HandEyeError,
    HandEyeResult,
    Mat4,
    Problem,
    RobotNoise,
    Station,
)
from calibration.observations import Detection
from calibration.targets import Points3D, Target


def calibrate_handeye(
    setup: str,
    T_base_tool: Sequence[ArrayLike],
    detections: Sequence[Detection],
    camera: CameraModel,
    target: Target,
    robot_noise: RobotNoise | None = None,
    raw_ur_poses: ArrayLike | None = None,
    sigma_px: float | None = None,
    leave_one_out: bool = True,
    drop_outliers: bool = True,
    estimate_robot_noise: bool = False,
) -> HandEyeResult:
    """Hand-eye calibration of ``setup`` from robot poses and per-image target detections.

    Runs the checks (pose count, robot-pose conventions, degenerate motion, mis-paired images),
    the closed forms, the joint maximum-likelihood refinement, the covariance and (optionally)
    leave-one-out prediction. With ``estimate_robot_noise`` the robot's position and orientation
    sigmas are estimated from the data (variance-component estimation, starting from
    ``robot_noise``) — for real robots whose absolute error is unknown. Raises
    HandEyeError/ConventionError with an actionable message when the data cannot give a
    trustworthy result.
    """
    t_start = time.perf_counter()
    if setup not in SETUPS:
        raise HandEyeError(f"setup must be one of {SETUPS}, got {setup!r}")
    if isinstance(target, Points3D) and len(target.points().ids) < 4:
        raise HandEyeError("the target needs at least 4 points")
    noise = robot_noise or RobotNoise()
    raw = None if raw_ur_poses is None else np.asarray(raw_ur_poses, dtype=np.float64).reshape(-1, 6)
    stations, problems = make_stations(T_base_tool, detections, camera, target)
    if raw is not None:
        keep_names = {s.image for s in stations}
        raw = raw[[k for k, d in enumerate(detections) if d.image in keep_names]]
    if len(stations) < MIN_STATIONS:
        raise HandEyeError(f"hand-eye needs at least {MIN_STATIONS} robot poses with a detected target, got "
                           f"{len(stations)}; capture {RECOMMENDED_STATIONS}-20 poses rotated 15-30 deg about "
                           "different axes")
    if len(stations) < RECOMMENDED_STATIONS:
        problems.append(Problem("few_poses", f"only {len(stations)} poses; {RECOMMENDED_STATIONS}-20 are "
                                "recommended for a reliable result and a meaningful leave-one-out test"))
    G = [s.G for s in stations]
    C = [s.C for s in stations]
    outliers, _ = find_outlier_stations(setup, G, C)
    inl = [k for k in range(len(stations)) if k not in outliers]
    conventions = check_conventions(setup, [G[k] for k in inl], [C[k] for k in inl],
                                    None if raw is None else raw[inl])
    if outliers:
        names = ", ".join(f"{stations[i].image} (#{i})" for i in outliers)
        if not drop_outliers:
            raise HandEyeError(f"image(s) {names} do not match their robot pose (their relative motions disagree "
                               "with what the camera saw); check those rows of poses.csv")
        problems.append(Problem(
            "pose_outlier",
            f"image(s) {names} do not match their robot pose — their relative motions disagree with the "
            "camera's (rotation angle / shift along the axis) far more than the others'; left out of the "
            "solution. Check those rows of poses.csv (shifted or swapped rows are typical)."))
        stations = [stations[k] for k in inl]
        G = [s.G for s in stations]
        C = [s.C for s in stations]
    kept, pair_info, motion_problems = check_motion(setup, G, C)
    problems += motion_problems

    # closed forms
    candidates: dict[str, Mat4] = {"PAIRS_LSQ": solve_pairs(kept)}
    for name in OPENCV_METHODS:
        try:
            Xc = opencv_handeye(setup, G, C, name)
            if np.all(np.isfinite(Xc)) and abs(np.linalg.det(Xc[:3, :3]) - 1) < 1e-3:
                candidates[name] = Xc
        except cv2.error:
            continue

    if sigma_px is None:
        ssr = sum(s.pnp_rms_px**2 * len(s.obj) for s in stations)  # sum of squared residual norms
        dof = sum(2 * len(s.obj) for s in stations) - 6 * len(stations)
        sigma_px = float(max(np.sqrt(ssr / max(dof, 1)), 1e-3))

    def reproj(Xc: Mat4) -> tuple[float, Mat4]:
        Zc = mean_pose([target_from_station(setup, Xc, g, c) for g, c in zip(G, C, strict=True)])
        err = []
        for s in stations:
            Cp = predict_cam_target(setup, Xc, Zc, s.G)
            err.append(camera.project(s.obj @ Cp[:3, :3].T + Cp[:3, 3]) - s.uv)
        e = np.vstack(err)
        return float(np.sqrt(np.nanmean(np.sum(e * e, axis=1)))), Zc

    init_info: dict[str, Any] = {}
    best_name, best_rms, best_X, best_Z = "", np.inf, np.eye(4), np.eye(4)
    for name, Xc in candidates.items():
        rms, Zc = reproj(Xc)
        init_info[name] = {"reprojection_rms_px": rms}
        if rms < best_rms:
            best_name, best_rms, best_X, best_Z = name, rms, Xc, Zc

    job, res = refine(setup, stations, camera, sigma_px, noise, best_X, best_Z)
    if estimate_robot_noise:
        for _ in range(8):
            new = vce_robot_noise(job, res, noise)
            done = (abs(np.log(new.sigma_mm / noise.sigma_mm)) < 0.02
                    and abs(np.log(new.sigma_deg / noise.sigma_deg)) < 0.02)
            noise = new
            X1, Z1, _ = job.poses(res.x)
            job = JointProblem(setup, stations, camera, sigma_px, noise, X1, Z1)
            x1 = res.x.copy()
            x1[:12] = 0.0
            res = job.solve(x1)
            if done:
                break
        problems.append(Problem("robot_noise_estimated",
                                f"robot noise estimated from the data: {noise.sigma_mm:.3g} mm / "
                                f"{noise.sigma_deg:.3g} deg (1-sigma per axis)"))
    X, Z, Gc = job.poses(res.x)
    for name, Xc in candidates.items():
        r, t = transform_error_deg_mm(Xc, X)
        init_info[name].update({"diff_to_refined_deg": r, "diff_to_refined_mm": t})
    init_info["chosen"] = best_name

    # covariance
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    m, npar = J.shape
    chi2 = float(2 * res.cost / max(m - npar, 1))
    try:
        cov = np.linalg.inv(np.einsum("ij,ik->jk", J, J))
    except np.linalg.LinAlgError as exc:
        raise HandEyeError("the joint refinement is singular: the poses do not determine the hand-eye "
                           "transform; add poses rotated about different axes") from exc
    scale = max(1.0, chi2)
    cov_X = cov[:6, :6] * scale
    cov_Z = cov[6:12, 6:12] * scale
    if chi2 > 4.0:
        problems.append(Problem(
            "noise_model", f"the residuals are {np.sqrt(chi2):.1f}x larger than the stated noise "
            f"(pixel {sigma_px:.3g} px, robot {noise.sigma_mm:g} mm / {noise.sigma_deg:g} deg): the robot is "
            "less accurate than stated (absolute kinematic error?); the uncertainty was scaled up accordingly"))

    # residuals per station
    r_px = res.fun[: 2 * job.n_obs].reshape(-1, 2) * sigma_px
    rms_px = float(np.sqrt(np.mean(np.sum(r_px * r_px, axis=1))))
    d = res.x[12:].reshape(job.n, 6)
    station_json: list[dict[str, Any]] = []
    for k, s in enumerate(stations):
        rk = r_px[job.sid == k]
        station_json.append({
            "image": s.image, "used": True, "points": len(s.obj),
            "rms_px": float(np.sqrt(np.mean(np.sum(rk * rk, axis=1)))),
            "pnp_rms_px": s.pnp_rms_px,
            "robot_correction_mm": float(1e3 * np.linalg.norm(d[k, 3:])),
            "robot_correction_deg": float(np.degrees(np.linalg.norm(d[k, :3]))),
        })
    rot, tr = axxb_residuals(kept, X)
    consistency = {"rot_deg": stats(rot), "trans_mm": stats(tr)}
    pair_info["conventions"] = conventions

    result = HandEyeResult(
        setup=setup,  # type: ignore[arg-type]
        X=X, Z=Z, cov_X=cov_X, cov_Z=cov_Z, rms_px=rms_px, sigma_px=sigma_px, chi2_reduced=chi2,
        robot_noise=noise, stations=station_json, consistency=consistency, init=init_info,
        problems=problems, pairs=pair_info, corrections=d, camera=camera,
    )
    if leave_one_out and len(stations) > MIN_STATIONS:
        result.loo = leave_one_out_prediction(setup, stations, camera, sigma_px, noise, X, Z)
        for k, e in enumerate(result.loo["per_pose"]):
            station_json[k]["loo_mm"] = e["position_mm"]
            station_json[k]["loo_deg"] = e["rotation_deg"]
            station_json[k]["loo_rms_px"] = e["rms_px"]
    result.time_s = time.perf_counter() - t_start
    return result


def leave_one_out_prediction(setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float,
                   noise: RobotNoise, X: Mat4, Z: Mat4) -> dict[str, Any]:
    """Refine without station i (warm start), predict its ``T_cam_target`` from its recorded robot
    pose, and compare with what its image shows: target origin distance (mm), rotation (deg) and
    reprojection RMS (px) of the prediction."""
    per: list[dict[str, Any]] = []
    for i, s in enumerate(stations):
        rest = [t for k, t in enumerate(stations) if k != i]
        job = JointProblem(setup, rest, camera, sigma_px, noise, X, Z)
        res = job.solve()
        Xi, Zi, _ = job.poses(res.x)
        Cp = predict_cam_target(setup, Xi, Zi, s.G)
        rdeg, tmm = transform_error_deg_mm(Cp, s.C)
        e = camera.project(s.obj @ Cp[:3, :3].T + Cp[:3, 3]) - s.uv
        per.append({"image": s.image, "position_mm": tmm, "rotation_deg": rdeg,
                    "rms_px": float(np.sqrt(np.mean(np.sum(e * e, axis=1))))})
    pos = np.array([p["position_mm"] for p in per])
    px = np.array([p["rms_px"] for p in per])
    return {"per_pose": per, "position_mm": stats(pos), "rms_px": stats(px)}
