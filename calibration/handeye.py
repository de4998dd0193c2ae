"""Hand-eye calibration (eye-in-hand and eye-to-hand) with checks, joint refinement and uncertainty.

Conventions (shared/INTERFACES.md §1): ``T_a_b`` maps frame ``b`` into frame ``a``; SI inside.

Model. With ``G_i = T_base_tool`` of station ``i`` and ``C_i = T_cam_target`` seen in its image:

- eye-in-hand: ``C_i = inv(T_tool_cam) · inv(G_i) · T_base_target``;
- eye-to-hand: ``C_i = inv(T_base_cam) · G_i · T_tool_target``.

Both are ``H_i · X · C_i = Z`` with ``H_i = G_i`` (eye-in-hand) or ``inv(G_i)`` (eye-to-hand),
``X`` the hand-eye transform and ``Z`` the constant target pose; relative motions give
``A X = X B`` with ``A = inv(H_j) H_i`` and ``B = C_j inv(C_i)``.

What is OpenCV's and what is ours:

- the closed-form initial solutions are OpenCV's ``cv2.calibrateHandEye`` (TSAI, PARK, HORAUD,
  ANDREFF, DANIILIDIS; eye-to-hand by passing the inverted robot poses, as OpenCV documents) plus
  our own pair-filtered least-squares (Kabsch on the rotation logs, then linear translation),
  which drops pairs whose relative rotation is too small or near 180°;
- the per-station target pose is ``calibration.pnp.estimate_pose`` (OpenCV's PnP on undistorted
  points, refined on pixels through our camera model; any lens model, division included);
- the **joint refinement** is ours: a maximum-likelihood estimate over ``X``, ``Z`` and a small
  pose correction per station, minimising the reprojection error of every target point in every
  image plus a Gaussian prior on the corrections (the stated robot noise model). Treating the
  recorded robot poses as exact was 2–10x worse (shared/FIELD_NOTES.md).

Robot noise model (stated, used by the prior and by the benchmark's generator): the recorded
flange pose ``G_i`` differs from the true one by an orientation error ``Exp(w_i)`` applied in the
base frame and a position error ``v_i`` (base frame), ``w_i ~ N(0, σ_r² I)``, ``v_i ~ N(0, σ_t² I)``
— σ per axis. Pixel noise σ_px is estimated from the per-station PnP residuals (which carry no
robot noise) unless given.

Uncertainty: the 6x6 covariance of ``X`` in the parametrisation ``R = Exp(ω) R̂`` (ω in radians,
base/left perturbation) and ``t = t̂ + v`` (metres), from the Gauss-Newton normal matrix of the
whitened problem, scaled up by the reduced χ² when the data are noisier than stated. The reported
``uncertainty.rot_deg`` and ``trans_mm`` are the RMS rotation angle sqrt(trace Σ_ω) and RMS
translation distance sqrt(trace Σ_v), 1-σ.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import as_transform, invert, make_transform, rotation_angle, transform_to_ur_pose
from calibration.observations import Detection
from calibration.pnp import PoseEstimationError, estimate_pose
from calibration.targets import Points3D, Target

Setup = Literal["eye-in-hand", "eye-to-hand"]
SETUPS: Final[tuple[str, ...]] = ("eye-in-hand", "eye-to-hand")

OPENCV_METHODS: Final[dict[str, int]] = {
    "TSAI": cv2.CALIB_HAND_EYE_TSAI,
    "PARK": cv2.CALIB_HAND_EYE_PARK,
    "HORAUD": cv2.CALIB_HAND_EYE_HORAUD,
    "ANDREFF": cv2.CALIB_HAND_EYE_ANDREFF,
    "DANIILIDIS": cv2.CALIB_HAND_EYE_DANIILIDIS,
}

MIN_STATIONS: Final = 3
RECOMMENDED_STATIONS: Final = 8
MIN_PAIR_ANGLE_DEG: Final = 3.0
MAX_PAIR_ANGLE_DEG: Final = 170.0
MIN_AXIS_SPREAD_DEG: Final = 5.0
WARN_AXIS_SPREAD_DEG: Final = 15.0
OUTLIER_FACTOR: Final = 8.0
OUTLIER_FLOOR: Final = 3.0

Mat4 = NDArray[np.float64]


class HandEyeError(ValueError):
    """The data cannot give a trustworthy hand-eye calibration; the message says why and what to do."""


class ConventionError(HandEyeError):
    """The robot poses fit far better under another convention (inverted, mm, Euler angles)."""


@dataclass(frozen=True)
class RobotNoise:
    """Stated robot pose noise, per axis, 1-σ: position (mm) and orientation (deg)."""

    sigma_mm: float = 0.05
    sigma_deg: float = 0.01

    def __post_init__(self) -> None:
        if not (self.sigma_mm > 0 and self.sigma_deg > 0):
            raise HandEyeError("robot noise sigmas must be positive (e.g. 0.05 mm and 0.01 deg for a UR)")


@dataclass
class Problem:
    code: str
    message: str
    severity: Literal["error", "warning"] = "warning"

    def to_json(self) -> dict[str, str]:
        return {"code": self.code, "message": self.message, "severity": self.severity}


@dataclass
class Station:
    """One robot pose with the target pose seen in its image."""

    image: str
    G: Mat4
    """Recorded ``T_base_tool``."""
    ids: NDArray[np.int64]
    obj: NDArray[np.float64]
    """(n, 3) target points (metres, target frame) of the detected ids."""
    uv: NDArray[np.float64]
    C: Mat4 = field(default_factory=lambda: np.eye(4))
    """``T_cam_target`` from PnP."""
    pnp_rms_px: float = 0.0


@dataclass
class HandEyeResult:
    setup: Setup
    X: Mat4
    """``T_tool_cam`` (eye-in-hand) or ``T_base_cam`` (eye-to-hand)."""
    Z: Mat4
    """``T_base_target`` (eye-in-hand) or ``T_tool_target`` (eye-to-hand)."""
    cov_X: NDArray[np.float64]
    cov_Z: NDArray[np.float64]
    rms_px: float
    sigma_px: float
    chi2_reduced: float
    robot_noise: RobotNoise
    stations: list[dict[str, Any]]
    consistency: dict[str, Any]
    init: dict[str, Any]
    problems: list[Problem]
    pairs: dict[str, Any]
    corrections: NDArray[np.float64]
    """(N, 6) per used station: orientation (rad) and position (m) corrections of the robot pose."""
    loo: dict[str, Any] = field(default_factory=dict)
    time_s: float = 0.0
    camera: CameraModel | None = None

    @property
    def uncertainty_rot_deg(self) -> float:
        return float(np.degrees(np.sqrt(np.trace(self.cov_X[:3, :3]))))

    @property
    def uncertainty_trans_mm(self) -> float:
        return float(1e3 * np.sqrt(np.trace(self.cov_X[3:, 3:])))

    def to_json(self) -> dict[str, Any]:
        """``he.json`` (shared/INTERFACES.md §4) plus diagnostics."""
        names = ("T_tool_cam", "T_base_target") if self.setup == "eye-in-hand" else ("T_base_cam", "T_tool_target")
        errors = [p for p in self.problems if p.severity == "error"]
        return {
            "setup": self.setup,
            names[0]: self.X.tolist(),
            names[1]: self.Z.tolist(),
            "rms_px": self.rms_px,
            "rot_deg": self.consistency["rot_deg"],
            "trans_mm": self.consistency["trans_mm"],
            "uncertainty": {
                "rot_deg": self.uncertainty_rot_deg,
                "trans_mm": self.uncertainty_trans_mm,
                "covariance": self.cov_X.tolist(),
                "covariance_order": "rotation rad (left perturbation R = Exp(w) R), translation m",
                "target_rot_deg": float(np.degrees(np.sqrt(np.trace(self.cov_Z[:3, :3])))),
                "target_trans_mm": float(1e3 * np.sqrt(np.trace(self.cov_Z[3:, 3:]))),
                "target_covariance": self.cov_Z.tolist(),
            },
            "pixel_sigma_px": self.sigma_px,
            "chi2_reduced": self.chi2_reduced,
            "robot_noise": {
                "sigma_mm": self.robot_noise.sigma_mm,
                "sigma_deg": self.robot_noise.sigma_deg,
                "estimated": any(p.code == "robot_noise_estimated" for p in self.problems),
                "model": "per axis, base frame: position N(0, sigma_mm^2), orientation Exp(w) with "
                         "w ~ N(0, sigma_deg^2)",
            },
            "poses": self.stations,
            "pairs": self.pairs,
            "init": self.init,
            "leave_one_out": self.loo,
            "time_s": self.time_s,
            **({"camera": self.camera.to_dict()} if self.camera is not None else {}),
            "verdict": {"ok": not errors, "problems": [p.to_json() for p in self.problems]},
        }


# --------------------------------------------------------------------------------------------
# small SE(3) helpers
# --------------------------------------------------------------------------------------------
def _exp_so3(w: ArrayLike) -> NDArray[np.float64]:
    return Rotation.from_rotvec(np.asarray(w, dtype=np.float64)).as_matrix()


def _log_so3(R: ArrayLike) -> NDArray[np.float64]:
    """Rotation vector of a rotation matrix (closed form; scipy near 180°, where it is ill-conditioned)."""
    M = np.asarray(R, dtype=np.float64)
    th = float(np.arccos(np.clip((M[0, 0] + M[1, 1] + M[2, 2] - 1.0) / 2.0, -1.0, 1.0)))
    v = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    if th < 1e-6:
        return 0.5 * v
    if th > np.pi - 1e-3:
        return np.asarray(Rotation.from_matrix(M).as_rotvec(), dtype=np.float64)
    return th / (2.0 * np.sin(th)) * v


def _perturb(T: Mat4, p: ArrayLike) -> Mat4:
    """``[Exp(w) R, t + v]`` for ``p = (w, v)``."""
    q = np.asarray(p, dtype=np.float64)
    return make_transform(_exp_so3(q[:3]) @ T[:3, :3], T[:3, 3] + q[3:6])


def _mean_pose(Ts: Sequence[Mat4]) -> Mat4:
    R = Rotation.from_matrix(np.array([T[:3, :3] for T in Ts])).mean().as_matrix()
    return make_transform(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def _hand(setup: str, G: Mat4) -> Mat4:
    return G if setup == "eye-in-hand" else invert(G)


def predict_cam_target(setup: str, X: Mat4, Z: Mat4, G: Mat4) -> Mat4:
    """Predicted ``T_cam_target`` of a station with robot pose ``G`` (see the module docstring)."""
    return invert(X) @ invert(_hand(setup, G)) @ Z


def target_from_station(setup: str, X: Mat4, G: Mat4, C: Mat4) -> Mat4:
    """``Z = H X C``: the target pose (base or tool frame) implied by one station."""
    return _hand(setup, G) @ X @ C


# --------------------------------------------------------------------------------------------
# per-station target pose
# --------------------------------------------------------------------------------------------
def station_pose(camera: CameraModel, obj: NDArray[np.float64], uv: NDArray[np.float64]) -> tuple[Mat4, float]:
    """``T_cam_target`` of one view (``calibration.pnp.estimate_pose``: OpenCV's PnP on undistorted
    points, then a refinement on pixels through the full camera model). Returns (T, rms_px)."""
    try:
        pose = estimate_pose(camera, obj, uv)
    except PoseEstimationError as exc:
        raise HandEyeError(f"target pose of a station failed: {exc}") from exc
    return pose.T_cam_target, pose.rms_px


def make_stations(T_base_tool: Sequence[ArrayLike], detections: Sequence[Detection], camera: CameraModel,
                  target: Target, min_points: int = 4) -> tuple[list[Station], list[Problem]]:
    """Pair robot poses with detections, compute each station's ``T_cam_target``.

    Views where the target was not found (or with fewer than ``min_points`` points) are left out
    and reported as warnings.
    """
    if len(T_base_tool) != len(detections):
        raise HandEyeError(f"{len(T_base_tool)} robot poses but {len(detections)} images: each image needs "
                           "exactly one robot pose (check poses.csv)")
    tp = target.points()
    lookup = {int(i): k for k, i in enumerate(tp.ids)}
    stations: list[Station] = []
    problems: list[Problem] = []
    for k, (G_raw, det) in enumerate(zip(T_base_tool, detections, strict=True)):
        G = as_transform(G_raw, f"robot pose {k} ({det.image})")
        if not det.found or len(det.ids) < min_points:
            why = det.reason or f"only {len(det.ids)} points"
            problems.append(Problem("view_not_used", f"{det.image}: target not found ({why}); view left out"))
            continue
        unknown = [int(i) for i in det.ids if int(i) not in lookup]
        if unknown:
            raise HandEyeError(f"{det.image}: point ids {unknown[:5]} are not on the target; wrong target file?")
        idx = np.array([lookup[int(i)] for i in det.ids])
        obj = tp.xyz_m[idx]
        uv = np.asarray(det.uv, dtype=np.float64).reshape(-1, 2)
        st = Station(det.image, G, np.asarray(det.ids, dtype=np.int64), obj, uv)
        st.C, st.pnp_rms_px = station_pose(camera, obj, uv)
        stations.append(st)
    return stations, problems


# --------------------------------------------------------------------------------------------
# closed forms and AX = XB statistics
# --------------------------------------------------------------------------------------------
def _pairs(H: Sequence[Mat4], C: Sequence[Mat4]) -> list[tuple[int, int, Mat4, Mat4, float]]:
    out = []
    for i in range(len(H)):
        for j in range(i + 1, len(H)):
            A = invert(H[j]) @ H[i]
            B = C[j] @ invert(C[i])
            out.append((i, j, A, B, float(np.degrees(rotation_angle(A[:3, :3])))))
    return out


def _solve_pairs(pairs: Sequence[tuple[int, int, Mat4, Mat4, float]]) -> Mat4:
    """Least-squares AX = XB over the given pairs: rotation by Kabsch on the rotation vectors
    (``log R_A = R_X log R_B``), translation by linear least squares."""
    a = np.array([_log_so3(A[:3, :3]) for _, _, A, _, _ in pairs])
    b = np.array([_log_so3(B[:3, :3]) for _, _, _, B, _ in pairs])
    U, _, Vt = np.linalg.svd(a.T @ b)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    M = np.vstack([A[:3, :3] - np.eye(3) for _, _, A, _, _ in pairs])
    y = np.concatenate([R @ B[:3, 3] - A[:3, 3] for _, _, A, B, _ in pairs])
    t = np.linalg.lstsq(M, y, rcond=None)[0]
    return make_transform(R, t)


def axxb_residuals(pairs: Sequence[tuple[int, int, Mat4, Mat4, float]], X: Mat4) -> tuple[NDArray[np.float64],
                                                                                           NDArray[np.float64]]:
    """Per pair: rotation (deg) and translation (mm) of ``inv(A X) · X B``."""
    rot, tr = [], []
    Xi = invert(X)
    for _, _, A, B, _ in pairs:
        E = Xi @ invert(A) @ X @ B
        rot.append(np.degrees(rotation_angle(E[:3, :3])))
        tr.append(1e3 * np.linalg.norm((A @ X)[:3, 3] - (X @ B)[:3, 3]))
    return np.array(rot), np.array(tr)


def _stats(x: NDArray[np.float64]) -> dict[str, float]:
    if x.size == 0:
        return {"mean": float("nan"), "rms": float("nan"), "max": float("nan")}
    return {"mean": float(np.mean(x)), "rms": float(np.sqrt(np.mean(x * x))), "max": float(np.max(x))}


def opencv_handeye(setup: str, G: Sequence[Mat4], C: Sequence[Mat4], method: str) -> Mat4:
    """One of OpenCV's closed forms; eye-to-hand passes ``inv(G)`` as OpenCV documents."""
    H = [_hand(setup, g) for g in G]
    R, t = cv2.calibrateHandEye([h[:3, :3] for h in H], [h[:3, 3] for h in H],
                                [c[:3, :3] for c in C], [c[:3, 3] for c in C], method=OPENCV_METHODS[method])
    return make_transform(np.asarray(R), np.asarray(t).ravel())


# --------------------------------------------------------------------------------------------
# checks before solving
# --------------------------------------------------------------------------------------------
def _rpy(raw: NDArray[np.float64], order: str, degrees: bool) -> Mat4:
    return make_transform(Rotation.from_euler(order, raw[3:6], degrees=degrees).as_matrix(), raw[:3])


def _ur(raw: NDArray[np.float64], rot_scale: float = 1.0, trans_scale: float = 1.0) -> Mat4:
    return make_transform(_exp_so3(raw[3:6] * rot_scale), raw[:3] * trans_scale)


_HYPOTHESES: Final[dict[str, tuple[str, str]]] = {
    "inverted": ("the robot poses inverted (T_tool_base instead of T_base_tool)",
                 "invert each robot pose — or, if the poses are right, use the other --setup "
                 "(eye-in-hand data solved as eye-to-hand looks exactly like inverted poses)"),
    "mm": ("the robot positions read as millimetres",
           "poses.csv needs metres (UR's TCP pose form): divide x, y, z by 1000"),
    "rpy_rad": ("rx, ry, rz read as roll-pitch-yaw Euler angles in radians (R = Rz(rz)·Ry(ry)·Rx(rx))",
                "poses.csv needs UR's rotation vector: convert with UR's rpy2rotvec or "
                "scipy Rotation.from_euler('xyz', [rx, ry, rz]).as_rotvec()"),
    "rpy_deg": ("rx, ry, rz read as roll-pitch-yaw Euler angles in degrees (R = Rz(rz)·Ry(ry)·Rx(rx))",
                "poses.csv needs UR's rotation vector in radians: convert with "
                "scipy Rotation.from_euler('xyz', [rx, ry, rz], degrees=True).as_rotvec()"),
    "xyz_intrinsic_rad": ("rx, ry, rz read as intrinsic X-Y'-Z'' Euler angles in radians (R = Rx·Ry·Rz)",
                          "poses.csv needs UR's rotation vector: convert with "
                          "scipy Rotation.from_euler('XYZ', [rx, ry, rz]).as_rotvec()"),
    "rotvec_deg": ("the rotation vector read in degrees",
                   "poses.csv needs the rotation vector in radians: multiply rx, ry, rz by pi/180"),
}


def _hypothesis_poses(name: str, G: Sequence[Mat4], raw: NDArray[np.float64]) -> list[Mat4]:
    if name == "as_given":
        return list(G)
    if name == "inverted":
        return [invert(g) for g in G]
    if name == "mm":
        return [make_transform(g[:3, :3], g[:3, 3] * 1e-3) for g in G]
    if name == "rpy_rad":
        return [_rpy(r, "xyz", False) for r in raw]
    if name == "rpy_deg":
        return [_rpy(r, "xyz", True) for r in raw]
    if name == "xyz_intrinsic_rad":
        return [_rpy(r, "XYZ", False) for r in raw]
    if name == "rotvec_deg":
        return [_ur(r, rot_scale=np.pi / 180) for r in raw]
    raise KeyError(name)


def _fit_score(setup: str, G: Sequence[Mat4], C: Sequence[Mat4]) -> tuple[float, float, float] | None:
    """(score, rot_rms_deg, trans_rms_mm) of the pair-filtered closed form, or None if too few pairs.

    The score is a robust consistency measure: the median over pairs of
    ``hypot(rot / 0.1°, trans / 1 mm)``.
    """
    H = [_hand(setup, g) for g in G]
    pairs = [p for p in _pairs(H, C) if MIN_PAIR_ANGLE_DEG <= p[4] <= MAX_PAIR_ANGLE_DEG]
    if len(pairs) < 2:
        return None
    X = _solve_pairs(pairs)
    rot, tr = axxb_residuals(pairs, X)
    score = float(np.median(np.hypot(rot / 0.1, tr / 1.0)))
    return score, float(np.sqrt(np.mean(rot**2))), float(np.sqrt(np.mean(tr**2)))


def check_conventions(setup: str, G: Sequence[Mat4], C: Sequence[Mat4],
                      raw_ur_poses: ArrayLike | None = None) -> dict[str, Any]:
    """Fit the closed form under each robot-pose convention; raise ConventionError when another
    convention fits far better (5x) than the given one and the given one fits badly.

    ``raw_ur_poses`` are the file's ``x, y, z, rx, ry, rz`` rows (exact for the Euler hypotheses);
    without them they are recovered from ``G``. Never changes the data: it only reports.
    """
    raw = (np.asarray(raw_ur_poses, dtype=np.float64).reshape(-1, 6) if raw_ur_poses is not None
           else np.array([transform_to_ur_pose(g) for g in G]))
    fits: dict[str, Any] = {}
    given = _fit_score(setup, G, C)
    if given is None:
        return {"checked": False, "reason": "too few pairs with enough rotation"}
    fits["as_given"] = {"rot_rms_deg": given[1], "trans_rms_mm": given[2], "score": given[0]}
    best_name, best = "as_given", given
    for name in _HYPOTHESES:
        try:
            alt = _fit_score(setup, _hypothesis_poses(name, G, raw), C)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if alt is None:
            continue
        fits[name] = {"rot_rms_deg": alt[1], "trans_rms_mm": alt[2], "score": alt[0]}
        if alt[0] < best[0]:
            best_name, best = name, alt
    if best_name != "as_given" and given[0] > 3.0 and best[0] < 0.2 * given[0]:
        what, fix = _HYPOTHESES[best_name]
        raise ConventionError(
            f"robot pose convention: the data fit far better with {what} — AX=XB residual "
            f"{best[1]:.3g} deg / {best[2]:.3g} mm instead of {given[1]:.3g} deg / {given[2]:.3g} mm as given. "
            f"Fix: {fix}. Nothing was changed.")
    return {"checked": True, "fits": fits}


def check_motion(setup: str, G: Sequence[Mat4], C: Sequence[Mat4]
                 ) -> tuple[list[tuple[int, int, Mat4, Mat4, float]], dict[str, Any], list[Problem]]:
    """Pair filtering and rotation-diversity checks; raises HandEyeError on degenerate motion."""
    H = [_hand(setup, g) for g in G]
    allp = _pairs(H, C)
    angles = np.array([p[4] for p in allp])
    problems: list[Problem] = []
    if angles.size == 0 or angles.max() < MIN_PAIR_ANGLE_DEG:
        raise HandEyeError(
            f"degenerate motion: the robot poses differ (almost) only by translation — the largest relative "
            f"rotation is {angles.max() if angles.size else 0.0:.2f} deg; hand-eye rotation cannot be determined. "
            "Rotate the tool by 15-30 deg between poses about at least two different axes.")
    kept = [p for p in allp if MIN_PAIR_ANGLE_DEG <= p[4] <= MAX_PAIR_ANGLE_DEG]
    small = int(np.sum(angles < MIN_PAIR_ANGLE_DEG))
    big = int(np.sum(angles > MAX_PAIR_ANGLE_DEG))
    if small or big:
        problems.append(Problem(
            "pairs_dropped",
            f"{small} pose pair(s) with relative rotation < {MIN_PAIR_ANGLE_DEG:g} deg and {big} near 180 deg "
            f"(> {MAX_PAIR_ANGLE_DEG:g} deg) were dropped from the closed form and the AX=XB statistics "
            f"({len(kept)} of {len(allp)} pairs kept)"))
    if len(kept) < 2:
        raise HandEyeError(f"only {len(kept)} pose pair(s) have a usable relative rotation "
                           f"({MIN_PAIR_ANGLE_DEG:g}-{MAX_PAIR_ANGLE_DEG:g} deg); add poses rotated 15-30 deg "
                           "about at least two different axes")
    axes = np.array([_log_so3(p[2][:3, :3]) for p in kept])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    w, V = np.linalg.eigh(axes.T @ axes)
    principal = V[:, -1]
    off = np.degrees(np.arccos(np.clip(np.abs(axes @ principal), 0.0, 1.0)))
    spread = float(off.max())
    info = {"pairs_total": len(allp), "pairs_used": len(kept), "dropped_small": small, "dropped_near_180": big,
            "axis_spread_deg": spread, "max_rotation_deg": float(angles.max())}
    if spread < MIN_AXIS_SPREAD_DEG:
        raise HandEyeError(
            f"degenerate motion: all relative rotations are about nearly one axis (axis spread {spread:.2f} deg, "
            f"axis ≈ {np.round(principal, 3).tolist()} in the {'base' if setup == 'eye-to-hand' else 'tool'} "
            f"frame); the hand-eye translation along it is undetermined. Add poses that rotate "
            f"15-30 deg about a second axis (spread >= {WARN_AXIS_SPREAD_DEG:g} deg recommended).")
    if spread < WARN_AXIS_SPREAD_DEG:
        problems.append(Problem("low_axis_spread",
                                f"rotation axes span only {spread:.1f} deg; the result is weakly determined — "
                                "add poses rotated about other axes"))
    return kept, info, problems


def _screw(T: Mat4) -> tuple[float, float]:
    """Rotation angle (deg) and translation along the rotation axis (mm): invariant under conjugation."""
    w = _log_so3(T[:3, :3])
    ang = float(np.linalg.norm(w))
    d = float(abs(T[:3, 3] @ (w / ang))) if ang > 1e-9 else float(np.linalg.norm(T[:3, 3]))
    return float(np.degrees(ang)), 1e3 * d


def find_outlier_stations(setup: str, G: Sequence[Mat4], C: Sequence[Mat4]) -> tuple[list[int], NDArray[np.float64]]:
    """Stations whose image does not match their robot pose (e.g. rows of poses.csv shifted).

    Uses the screw invariants of AX = XB, which hold whatever X is: the rotation angle of A equals
    that of B, and so does the translation along the rotation axis. A station's score is the median
    over its pairs of ``hypot(Δangle / 0.1°, Δaxial / 1 mm)``; it is flagged when that is > 8x the
    median score and > 3 (i.e. 0.3° or 3 mm). A mis-paired station spoils all its pairs, a good one
    only its pair with the bad one, so the median separates them without any prior solution.
    Returns (flagged indices, score per station).
    """
    n = len(G)
    H = [_hand(setup, g) for g in G]
    M = np.zeros((n, n))
    for i, j, A, B, _ in _pairs(H, C):
        aa, da = _screw(A)
        ab, db = _screw(B)
        M[i, j] = M[j, i] = float(np.hypot((aa - ab) / 0.1, (da - db) / 1.0))
    score = np.array([np.median(np.delete(M[i], i)) for i in range(n)])
    med = float(np.median(score))
    flagged = [int(i) for i in np.flatnonzero(score > max(OUTLIER_FACTOR * med, OUTLIER_FLOOR))]
    if n - len(flagged) < MIN_STATIONS:
        return [], score
    return flagged, score


# --------------------------------------------------------------------------------------------
# joint refinement
# --------------------------------------------------------------------------------------------
class _Joint:
    """Maximum-likelihood refinement over X, Z and per-station robot pose corrections."""

    def __init__(self, setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float,
                 noise: RobotNoise, X0: Mat4, Z0: Mat4) -> None:
        self.setup, self.camera, self.sigma_px = setup, camera, sigma_px
        self.sig_t = noise.sigma_mm * 1e-3
        self.sig_r = np.radians(noise.sigma_deg)
        self.X0, self.Z0 = X0, Z0
        self.G = np.array([s.G for s in stations])
        self.n = len(stations)
        self.obj = np.vstack([s.obj for s in stations])
        self.uv = np.vstack([s.uv for s in stations])
        self.sid = np.concatenate([np.full(len(s.obj), k) for k, s in enumerate(stations)])
        self.n_obs = len(self.obj)

    def poses(self, x: NDArray[np.float64]) -> tuple[Mat4, Mat4, NDArray[np.float64]]:
        X = _perturb(self.X0, x[0:6])
        Z = _perturb(self.Z0, x[6:12])
        d = x[12:].reshape(self.n, 6)
        Rd = Rotation.from_rotvec(d[:, :3]).as_matrix()
        Gc = self.G.copy()
        Gc[:, :3, :3] = Rd @ self.G[:, :3, :3]
        Gc[:, :3, 3] = self.G[:, :3, 3] + d[:, 3:]
        return X, Z, Gc

    def cam_target(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        X, Z, Gc = self.poses(x)
        Xi = invert(X)
        if self.setup == "eye-to-hand":
            Hinv = Gc
        else:
            Hinv = np.zeros_like(Gc)
            Rt = np.transpose(Gc[:, :3, :3], (0, 2, 1))
            Hinv[:, :3, :3] = Rt
            Hinv[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, Gc[:, :3, 3])
            Hinv[:, 3, 3] = 1.0
        return np.einsum("ij,njk,kl->nil", Xi, Hinv, Z)

    def residuals(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        C = self.cam_target(x)
        Cs = C[self.sid]
        P = np.einsum("nij,nj->ni", Cs[:, :3, :3], self.obj) + Cs[:, :3, 3]
        r_px = (self.camera.project(P) - self.uv).ravel() / self.sigma_px
        d = x[12:].reshape(self.n, 6)
        prior = np.concatenate([d[:, :3].ravel() / self.sig_r, d[:, 3:].ravel() / self.sig_t])
        return np.concatenate([np.nan_to_num(r_px, nan=1e6), prior])

    def jacobian(self, x: NDArray[np.float64], r0: NDArray[np.float64]) -> NDArray[np.float64]:
        """Forward differences exploiting the structure: 12 evaluations for X and Z, and 6 for all
        station corrections at once (station k's residuals depend only on its own correction)."""
        h = 1e-7
        J = np.zeros((len(r0), len(x)))
        for a in range(12):
            xp = x.copy()
            xp[a] += h
            J[:, a] = (self.residuals(xp) - r0) / h
        rows_px = np.repeat(self.sid, 2)
        n_px = 2 * self.n_obs
        for a in range(6):
            xp = x.copy()
            xp[12 + a :: 6] += h
            col = (self.residuals(xp) - r0) / h
            for k in range(self.n):
                sel = np.flatnonzero(rows_px == k)
                J[sel, 12 + 6 * k + a] = col[sel]
            prior_row = n_px + (3 * self.n + 3 * np.arange(self.n) + a - 3 if a >= 3 else 3 * np.arange(self.n) + a)
            J[prior_row, 12 + 6 * np.arange(self.n) + a] = col[prior_row]
        return J

    def solve(self, x0: NDArray[np.float64] | None = None, max_iter: int = 50) -> _LMResult:
        """Levenberg-Marquardt (dense normal equations; a few hundred parameters at most)."""
        x = np.zeros(12 + 6 * self.n) if x0 is None else x0.copy()
        r = self.residuals(x)
        cost = float(r @ r)
        lam = 1e-3
        J = self.jacobian(x, r)
        for _ in range(max_iter):
            # einsum, not BLAS: multithreaded BLAS spin-waits badly on a loaded 2-core machine
            A = np.einsum("ij,ik->jk", J, J)
            g = np.einsum("ij,i->j", J, r)
            improved = False
            for _ in range(12):
                dx = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
                rn = self.residuals(x + dx)
                cn = float(rn @ rn)
                if cn < cost:
                    improved = True
                    break
                lam *= 10.0
            if not improved:
                break
            x = x + dx
            rel = (cost - cn) / max(cost, 1e-300)
            r, cost = rn, cn
            lam = max(lam / 10.0, 1e-9)
            J = self.jacobian(x, r)
            if rel < 1e-10:
                break
        return _LMResult(x=x, fun=r, jac=J, cost=0.5 * cost)


@dataclass
class _LMResult:
    x: NDArray[np.float64]
    fun: NDArray[np.float64]
    jac: NDArray[np.float64]
    cost: float


def _vce_robot_noise(job: _Joint, res: _LMResult, noise: RobotNoise) -> RobotNoise:
    """One variance-component step for the two robot groups (orientation, position).

    Each prior row has one non-zero, so its leverage is ``J_ii² (JᵀJ)⁻¹_cc``; the group's new
    variance is the old one times ``Σ r² / Σ (1 - h)`` (Förstner's estimator)."""
    J = res.jac
    Ninv = np.linalg.inv(np.einsum("ij,ik->jk", J, J))
    base = 2 * job.n_obs
    n = job.n
    out = []
    for g, sig in ((0, np.radians(noise.sigma_deg)), (1, noise.sigma_mm * 1e-3)):
        rows = base + 3 * n * g + np.arange(3 * n)
        cols = 12 + 6 * np.repeat(np.arange(n), 3) + 3 * g + np.tile(np.arange(3), n)
        h = J[rows, cols] ** 2 * Ninv[cols, cols]
        red = max(float(np.sum(1.0 - h)), 1e-9)
        factor = float(res.fun[rows] @ res.fun[rows]) / red
        out.append(sig * np.sqrt(max(factor, 1e-6)))
    return RobotNoise(sigma_mm=max(float(out[1]) * 1e3, 1e-4), sigma_deg=max(float(np.degrees(out[0])), 1e-5))


def _refine(setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float, noise: RobotNoise,
            X0: Mat4, Z0: Mat4) -> tuple[_Joint, Any]:
    job = _Joint(setup, stations, camera, sigma_px, noise, X0, Z0)
    res = job.solve()
    # Re-linearise once at the solution (small-angle parametrisation stays accurate).
    X, Z, _ = job.poses(res.x)
    job2 = _Joint(setup, stations, camera, sigma_px, noise, X, Z)
    x1 = res.x.copy()
    x1[:12] = 0.0
    res2 = job2.solve(x1)
    return job2, res2


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
    candidates: dict[str, Mat4] = {"PAIRS_LSQ": _solve_pairs(kept)}
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
        Zc = _mean_pose([target_from_station(setup, Xc, g, c) for g, c in zip(G, C, strict=True)])
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

    job, res = _refine(setup, stations, camera, sigma_px, noise, best_X, best_Z)
    if estimate_robot_noise:
        for _ in range(8):
            new = _vce_robot_noise(job, res, noise)
            done = (abs(np.log(new.sigma_mm / noise.sigma_mm)) < 0.02
                    and abs(np.log(new.sigma_deg / noise.sigma_deg)) < 0.02)
            noise = new
            X1, Z1, _ = job.poses(res.x)
            job = _Joint(setup, stations, camera, sigma_px, noise, X1, Z1)
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
    consistency = {"rot_deg": _stats(rot), "trans_mm": _stats(tr)}
    pair_info["conventions"] = conventions

    result = HandEyeResult(
        setup=setup,  # type: ignore[arg-type]
        X=X, Z=Z, cov_X=cov_X, cov_Z=cov_Z, rms_px=rms_px, sigma_px=sigma_px, chi2_reduced=chi2,
        robot_noise=noise, stations=station_json, consistency=consistency, init=init_info,
        problems=problems, pairs=pair_info, corrections=d, camera=camera,
    )
    if leave_one_out and len(stations) > MIN_STATIONS:
        result.loo = _leave_one_out(setup, stations, camera, sigma_px, noise, X, Z)
        for k, e in enumerate(result.loo["per_pose"]):
            station_json[k]["loo_mm"] = e["position_mm"]
            station_json[k]["loo_deg"] = e["rotation_deg"]
            station_json[k]["loo_rms_px"] = e["rms_px"]
    result.time_s = time.perf_counter() - t_start
    return result


def transform_error_deg_mm(A: Mat4, B: Mat4) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) difference of two transforms."""
    r = rotation_angle(A[:3, :3].T @ B[:3, :3])
    return float(np.degrees(r)), float(1e3 * np.linalg.norm(A[:3, 3] - B[:3, 3]))


def _leave_one_out(setup: str, stations: Sequence[Station], camera: CameraModel, sigma_px: float,
                   noise: RobotNoise, X: Mat4, Z: Mat4) -> dict[str, Any]:
    """Refine without station i (warm start), predict its ``T_cam_target`` from its recorded robot
    pose, and compare with what its image shows: target origin distance (mm), rotation (deg) and
    reprojection RMS (px) of the prediction."""
    per: list[dict[str, Any]] = []
    for i, s in enumerate(stations):
        rest = [t for k, t in enumerate(stations) if k != i]
        job = _Joint(setup, rest, camera, sigma_px, noise, X, Z)
        res = job.solve()
        Xi, Zi, _ = job.poses(res.x)
        Cp = predict_cam_target(setup, Xi, Zi, s.G)
        rdeg, tmm = transform_error_deg_mm(Cp, s.C)
        e = camera.project(s.obj @ Cp[:3, :3].T + Cp[:3, 3]) - s.uv
        per.append({"image": s.image, "position_mm": tmm, "rotation_deg": rdeg,
                    "rms_px": float(np.sqrt(np.mean(np.sum(e * e, axis=1))))})
    pos = np.array([p["position_mm"] for p in per])
    px = np.array([p["rms_px"] for p in per])
    return {"per_pose": per, "position_mm": _stats(pos), "rms_px": _stats(px)}


# --------------------------------------------------------------------------------------------
# virtual-cell data (tests and bench/handeye.py)
# --------------------------------------------------------------------------------------------
@dataclass
class SimulatedHandEye:
    """Generated hand-eye data with its truth."""

    setup: str
    camera: CameraModel
    target: Target
    X_true: Mat4
    Z_true: Mat4
    G_true: list[Mat4]
    G_recorded: list[Mat4]
    C_true: list[Mat4]
    detections: list[Detection]


def simulate_handeye(setup: str, n_poses: int, rng: np.random.Generator, *, camera: CameraModel,
                     target: Target, robot_noise: RobotNoise | None = None, pixel_sigma_px: float = 0.05,
                     distance_m: tuple[float, float] = (0.38, 0.52), max_tilt_deg: float = 35.0,
                     max_roll_deg: float = 60.0, X_true: Mat4 | None = None, Z_true: Mat4 | None = None
                     ) -> SimulatedHandEye:
    """Virtual-cell stations: target poses in the camera spread over distance, tilt (about a
    random in-plane axis) and roll, robot poses from the truth through the model of this module,
    then the recorded robot poses perturbed by ``robot_noise`` (the module's noise model) and the
    projected points by Gaussian pixel noise. Every station sees the whole target."""
    tp = target.points()
    centre = tp.xyz_m.mean(axis=0)
    if X_true is None:
        X_true = (make_transform(_exp_so3([0.05, -0.08, 1.6]), [0.032, -0.051, 0.085]) if setup == "eye-in-hand"
                  else make_transform(_exp_so3([2.9, 0.35, -0.2]), [0.45, -0.12, 0.95]))
    if Z_true is None:
        Z_true = (make_transform(_exp_so3([0.02, -0.03, 0.7]), [0.55, 0.05, 0.02]) if setup == "eye-in-hand"
                  else make_transform(_exp_so3([0.1, 3.0, 0.05]), [0.01, 0.02, 0.12]))
    Cs: list[Mat4] = []
    while len(Cs) < n_poses:
        z = rng.uniform(*distance_m)
        p = np.array([rng.uniform(-0.12, 0.12) * z, rng.uniform(-0.08, 0.08) * z, z])
        ang = np.radians(rng.uniform(0.3, 1.0) * max_tilt_deg)
        phi = rng.uniform(0, 2 * np.pi)
        roll = np.radians(rng.uniform(-max_roll_deg, max_roll_deg))
        R = _exp_so3(ang * np.array([np.cos(phi), np.sin(phi), 0.0])) @ _exp_so3([0.0, 0.0, roll])
        Cm = make_transform(R, p - R @ centre)
        uv = camera.project(tp.xyz_m @ R.T + Cm[:3, 3])
        if np.all(np.isfinite(uv)) and np.all((uv > 20) & (uv < np.array(camera.size) - 21)):
            Cs.append(Cm)
    noise = robot_noise or RobotNoise()
    G_true, G_rec, dets = [], [], []
    for k, Cm in enumerate(Cs):
        G = Z_true @ invert(Cm) @ invert(X_true) if setup == "eye-in-hand" else X_true @ Cm @ invert(Z_true)
        G_true.append(G)
        w = rng.normal(0.0, np.radians(noise.sigma_deg), 3)
        v = rng.normal(0.0, noise.sigma_mm * 1e-3, 3)
        G_rec.append(_perturb(G, np.concatenate([w, v])))
        uv = camera.project(tp.xyz_m @ Cm[:3, :3].T + Cm[:3, 3]) + rng.normal(0.0, pixel_sigma_px, (len(tp.ids), 2))
        dets.append(Detection(f"view{k:02d}.png", True, tp.ids.copy(), uv, image_size=camera.size))
    return SimulatedHandEye(setup, camera, target, X_true, Z_true, G_true, G_rec, Cs, dets)
