"""``calibrate_handeye``: checks, closed forms, the error model chosen by leave-one-out, covariance."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration.camera_model import CameraModel
from calibration.handeye.checks import check_conventions, check_motion, find_outlier_stations
from calibration.handeye.closed_form import axxb_residuals, opencv_handeye, solve_pairs, stats
from calibration.handeye.consensus import confirmed_by_held_out, consensus_misses, off_consensus
from calibration.handeye.error_model import ERROR_MODELS, choose_model
from calibration.handeye.frames import (
    make_stations,
    mean_pose,
    predict_cam_target,
    target_from_station,
    transform_error_deg_mm,
)
from calibration.handeye.joint import JointOptions, JointProblem, LMResult
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
    *,
    error_model: str = "auto",
    refine_intrinsics: bool | None = None,
    camera_verdict_ok: bool | None = None,
    camera_covariance: ArrayLike | None = None,
) -> HandEyeResult:
    """Hand-eye calibration of ``setup`` from robot poses and per-image target detections.

    Runs the checks (pose count, robot-pose conventions, degenerate motion, mis-paired images),
    the closed forms, the joint maximum-likelihood refinement, the covariance and leave-one-out
    prediction — the primary quality figure (``quality.loo_prediction_rms_px``).

    ``camera_covariance``: the intrinsics' covariance (order ``fx, fy, cx, cy, dist...``, the camera
    result's ``parameters.covariance``): a prior when the intrinsics are refined jointly, else
    propagated into the reported covariance of X and Z (first order: the solution's sensitivity to
    the intrinsics), so the uncertainty includes the camera's.

    ``error_model``: ``"auto"`` fits every model of ``calibration.handeye.error_model`` and keeps
    the one that predicts held-out stations best (needs ``leave_one_out``; without it the fixed
    prior is used), or one of ``ERROR_MODELS`` by name. ``estimate_robot_noise`` (older flag) asks
    for ``"estimated_iid"``. ``refine_intrinsics``: refine the camera jointly (prior from
    ``camera_covariance`` if given); default on when ``camera_verdict_ok`` is False (the
    intrinsics' own verdict said uncertain), else off. Raises HandEyeError/ConventionError with an
    actionable message when the data cannot give a trustworthy result.
    """
    t_start = time.perf_counter()
    models = _models(error_model, estimate_robot_noise, leave_one_out)
    cov_c = None if camera_covariance is None else _checked_camera_covariance(camera, camera_covariance)
    noise = robot_noise or RobotNoise()
    stations, problems, kept, pair_info = _checked_stations(setup, T_base_tool, detections, camera, target,
                                                            raw_ur_poses, drop_outliers)
    candidates, init_info, X0, Z0 = _closed_forms(setup, stations, camera, kept)
    if sigma_px is None:
        sigma_px = _pixel_sigma(stations)
    intr = camera_verdict_ok is False if refine_intrinsics is None else refine_intrinsics
    options = JointOptions(intrinsics=intr, camera_covariance=cov_c)
    with_loo = leave_one_out and len(stations) > MIN_STATIONS
    fit, model_info = choose_model(setup, stations, camera, sigma_px, noise, X0, Z0, options, models, with_loo)
    misses = consensus_misses(fit.job, fit.res, stations)
    flagged = off_consensus(misses)
    dropped = confirmed_by_held_out(flagged, fit.loo.get("per_pose", [])) if with_loo and drop_outliers else []
    if len(stations) - len(dropped) <= MIN_STATIONS:
        dropped = []
    problems += _consensus_problems(stations, misses, flagged, dropped, with_loo and drop_outliers)
    off = {stations[k].image for k in flagged if k not in dropped}
    if dropped:
        stations = [s for k, s in enumerate(stations) if k not in dropped]
        kept, motion_info, _ = check_motion(setup, [s.G for s in stations], [s.C for s in stations])
        pair_info = {**motion_info, "conventions": pair_info.get("conventions")}
        candidates, init_info, X0, Z0 = _closed_forms(setup, stations, camera, kept)
        with_loo = leave_one_out and len(stations) > MIN_STATIONS
        fit, model_info = choose_model(setup, stations, camera, sigma_px, noise, X0, Z0, options, models, with_loo)
        misses = consensus_misses(fit.job, fit.res, stations)
    job, res, noise = fit.job, fit.res, fit.noise
    if fit.name == "estimated_iid":
        problems.append(Problem("robot_noise_estimated",
                                f"robot noise estimated from the data: {noise.sigma_mm:.3g} mm / "
                                f"{noise.sigma_deg:.3g} deg (1-sigma per axis)"))
    X, Z, _ = job.poses(res.x)
    for name, Xc in candidates.items():
        r, t = transform_error_deg_mm(Xc, X)
        init_info[name].update({"diff_to_refined_deg": r, "diff_to_refined_mm": t})
    cov_X, cov_Z, chi2 = _covariance(res, problems, sigma_px, noise)
    camera_unc = "prior" if (intr and cov_c is not None) else "none"
    if cov_c is not None and not intr:
        dX, dZ = _camera_propagation(job, res, cov_c)
        cov_X, cov_Z, camera_unc = cov_X + dX, cov_Z + dZ, "propagated"
    cam = job.camera_at(res.x)
    station_json, rms_px, d = _station_report(job, res, stations, sigma_px)
    for k, m in enumerate(misses):
        station_json[k]["consensus_rms_px"] = m["rms_px"]
        station_json[k]["off_consensus"] = stations[k].image in off
    rot, tr = axxb_residuals(kept, X)
    result = HandEyeResult(
        setup=setup,  # type: ignore[arg-type]
        X=X, Z=Z, cov_X=cov_X, cov_Z=cov_Z, rms_px=rms_px, sigma_px=sigma_px, chi2_reduced=chi2,
        robot_noise=noise, stations=station_json, consistency={"rot_deg": stats(rot), "trans_mm": stats(tr)},
        init=init_info, problems=problems, pairs=pair_info, corrections=d, camera=cam,
        error_model=model_info, intrinsics_refined=intr, camera_uncertainty=camera_unc,
        camera_initial=camera if intr else None,
    )
    if with_loo:
        result.loo = fit.loo
        for k, e in enumerate(result.loo["per_pose"]):
            station_json[k]["loo_mm"] = e["position_mm"]
            station_json[k]["loo_deg"] = e["rotation_deg"]
            station_json[k]["loo_rms_px"] = e["rms_px"]
    result.time_s = time.perf_counter() - t_start
    return result


def _consensus_problems(stations: Sequence[Station], misses: Sequence[dict[str, Any]], flagged: Sequence[int],
                        dropped: Sequence[int], judged: bool) -> list[Problem]:
    """The warning naming the stations far off the consensus, and whether they were left out
    (``judged``: held-out prediction was run and dropping allowed)."""
    if not flagged:
        return []

    def said(k: int) -> str:
        m = misses[k]
        return (f"{stations[k].image} (#{k}: {m['rms_px']:.1f} px, {m['trans_mm']:.1f} mm / {m['rot_deg']:.2f} deg "
                "from what the others predict)")
    out = []
    if dropped:
        out.append(Problem(
            "station_off_consensus",
            "station(s) " + ", ".join(said(k) for k in dropped) + " lie far off the consensus of the others, and a "
            "calibration without them cannot predict them either: left out of the solution. Check those robot "
            "poses (a pose recorded before the robot settled, a wrong row) or capture them again."))
    kept = [k for k in flagged if k not in dropped]
    if kept:
        out.append(Problem(
            "station_off_consensus",
            "station(s) " + ", ".join(said(k) for k in kept) + " lie far off the consensus of the others; kept ("
            + ("a calibration without them predicts them within the spread of the others" if judged else
               "no leave-one-out run to confirm them") + "). Check those robot poses, or capture them again."))
    return out


def _models(error_model: str, estimate_robot_noise: bool, leave_one_out: bool) -> list[str]:
    if error_model != "auto" and error_model not in ERROR_MODELS:
        raise HandEyeError(f"error_model must be 'auto' or one of {ERROR_MODELS}, got {error_model!r}")
    if estimate_robot_noise:
        return ["estimated_iid"]
    if error_model != "auto":
        return [error_model]
    return list(ERROR_MODELS) if leave_one_out else ["fixed_prior"]


def _checked_stations(setup: str, T_base_tool: Sequence[ArrayLike], detections: Sequence[Detection],
                      camera: CameraModel, target: Target, raw_ur_poses: ArrayLike | None, drop_outliers: bool
                      ) -> tuple[list[Station], list[Problem], list[Any], dict[str, Any]]:
    """Stations that pass the checks (count, outliers, conventions, motion), the problems found,
    the AX = XB pairs kept and the pair statistics."""
    if setup not in SETUPS:
        raise HandEyeError(f"setup must be one of {SETUPS}, got {setup!r}")
    if isinstance(target, Points3D) and len(target.points().ids) < 4:
        raise HandEyeError("the target needs at least 4 points")
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
    kept, pair_info, motion_problems = check_motion(setup, [s.G for s in stations], [s.C for s in stations])
    pair_info["conventions"] = conventions
    return stations, problems + motion_problems, kept, pair_info


def _closed_forms(setup: str, stations: Sequence[Station], camera: CameraModel, kept: list[Any]
                  ) -> tuple[dict[str, Mat4], dict[str, Any], Mat4, Mat4]:
    """Every closed form (ours and OpenCV's five), scored by reprojection; the best starts the
    refinement. Returns (candidates, init info, X0, Z0)."""
    G = [s.G for s in stations]
    C = [s.C for s in stations]
    candidates: dict[str, Mat4] = {"PAIRS_LSQ": solve_pairs(kept)}
    for name in OPENCV_METHODS:
        try:
            Xc = opencv_handeye(setup, G, C, name)
            if np.all(np.isfinite(Xc)) and abs(np.linalg.det(Xc[:3, :3]) - 1) < 1e-3:
                candidates[name] = Xc
        except cv2.error:
            continue
    init_info: dict[str, Any] = {}
    best_name, best_rms, best_X, best_Z = "", np.inf, np.eye(4), np.eye(4)
    for name, Xc in candidates.items():
        Zc = mean_pose([target_from_station(setup, Xc, g, c) for g, c in zip(G, C, strict=True)])
        err = []
        for s in stations:
            Cp = predict_cam_target(setup, Xc, Zc, s.G)
            err.append(camera.project(s.obj @ Cp[:3, :3].T + Cp[:3, 3]) - s.uv)
        e = np.vstack(err)
        rms = float(np.sqrt(np.nanmean(np.sum(e * e, axis=1))))
        init_info[name] = {"reprojection_rms_px": rms}
        if rms < best_rms:
            best_name, best_rms, best_X, best_Z = name, rms, Xc, Zc
    init_info["chosen"] = best_name
    return candidates, init_info, best_X, best_Z


def _pixel_sigma(stations: Sequence[Station]) -> float:
    """Pixel noise (px, per axis, of a point of weight 1) from the weighted per-station PnP residuals,
    which carry no robot noise."""
    ssr = sum(s.pnp_ssr_w for s in stations)
    dof = sum(2 * len(s.obj) for s in stations) - 6 * len(stations)
    return float(max(np.sqrt(ssr / max(dof, 1)), 1e-3))


def _covariance(res: LMResult, problems: list[Problem], sigma_px: float, noise: RobotNoise
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Covariances of X and Z from the whitened normal matrix, scaled up by the reduced chi² when
    the data are noisier than stated (with a problem saying so)."""
    J = np.asarray(res.jac)
    m, npar = J.shape
    chi2 = float(2 * res.cost / max(m - npar, 1))
    try:
        cov = np.linalg.inv(np.einsum("ij,ik->jk", J, J))
    except np.linalg.LinAlgError as exc:
        raise HandEyeError("the joint refinement is singular: the poses do not determine the hand-eye "
                           "transform; add poses rotated about different axes") from exc
    scale = max(1.0, chi2)
    if chi2 > 4.0:
        problems.append(Problem(
            "noise_model", f"the residuals are {np.sqrt(chi2):.1f}x larger than the stated noise "
            f"(pixel {sigma_px:.3g} px, robot {noise.sigma_mm:g} mm / {noise.sigma_deg:g} deg): the robot is "
            "less accurate than stated (absolute kinematic error?); the uncertainty was scaled up accordingly. "
            "Judge the result by its leave-one-out prediction (quality.loo_prediction_rms_px)"))
    return cov[:6, :6] * scale, cov[6:12, 6:12] * scale, chi2


def _checked_camera_covariance(camera: CameraModel, cov: ArrayLike) -> NDArray[np.float64]:
    c = np.asarray(cov, dtype=np.float64)
    n_c = 4 + len(camera.dist)
    if c.shape != (n_c, n_c) or not np.all(np.isfinite(c)):
        raise HandEyeError(f"camera covariance must be {n_c}x{n_c} (fx, fy, cx, cy and the {n_c - 4} distortion "
                           f"coefficients of the {camera.model} model), got shape {c.shape}")
    return c


def _camera_propagation(job: JointProblem, res: LMResult, cov_c: NDArray[np.float64]
                        ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Covariance of X and Z (6x6 each) caused by the camera's own uncertainty ``cov_c`` when the
    intrinsics are held fixed: ``S cov_c Sᵀ`` with ``S = -(J_θᵀ J_θ)⁻¹ J_θᵀ J_c`` the first-order
    sensitivity of the solution to the intrinsics (whitened Jacobians at the solution)."""
    n_c = len(job.c0)
    opts = replace(job.options, intrinsics=True, camera_covariance=None)
    full = JointProblem(job.setup, job.stations, job.camera, job.sigma_px, job.noise, job.X0, job.Z0, opts)
    x = np.concatenate([res.x[:12], np.zeros(n_c), res.x[12:]])
    J = full.jacobian(x, full.residuals(x))
    cam_cols = np.arange(12, 12 + n_c)
    theta = np.setdiff1d(np.arange(J.shape[1]), cam_cols)
    Jt, Jc = J[:, theta], J[:, cam_cols]
    try:
        S = -np.linalg.solve(np.einsum("ij,ik->jk", Jt, Jt), np.einsum("ij,ik->jk", Jt, Jc))
    except np.linalg.LinAlgError as exc:
        raise HandEyeError("the joint refinement is singular: the poses do not determine the hand-eye "
                           "transform; add poses rotated about different axes") from exc
    cov = S[:12] @ cov_c @ S[:12].T
    return cov[:6, :6], cov[6:12, 6:12]


def _station_report(job: JointProblem, res: LMResult, stations: Sequence[Station], sigma_px: float
                    ) -> tuple[list[dict[str, Any]], float, NDArray[np.float64]]:
    """Per-station residuals (unweighted px) and robot corrections; overall RMS; (N, 6) corrections."""
    r_px = res.fun[: 2 * job.n_obs].reshape(-1, 2) * sigma_px / job.w[:, None]
    rms_px = float(np.sqrt(np.mean(np.sum(r_px * r_px, axis=1))))
    d = job.corrections(res.x)
    out: list[dict[str, Any]] = []
    for k, s in enumerate(stations):
        rk = r_px[job.sid == k]
        out.append({
            "image": s.image, "used": True, "points": len(s.obj),
            "rms_px": float(np.sqrt(np.mean(np.sum(rk * rk, axis=1)))),
            "pnp_rms_px": s.pnp_rms_px,
            "robot_correction_mm": float(1e3 * np.linalg.norm(d[k, 3:])),
            "robot_correction_deg": float(np.degrees(np.linalg.norm(d[k, :3]))),
        })
    return out, rms_px, d
