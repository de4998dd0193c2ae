"""Pixel → robot-frame point (mm) with its propagated 1-σ uncertainty.

Two kinds of calibration (the JSON files of docs/cli.md):

- **n-point** (``np.json``): ``(x, y) = H · (u, v)`` on the plane the marks were taught on
  (lens distortion removed first when the calibration carries a camera). Uncertainty from the
  map's parameter covariance plus the pixel noise of the query point.
- **hand-eye** (``he.json``): the pixel's ray, through the camera model, intersected with the
  horizontal working plane ``z = plane_z_mm`` of the robot base frame. ``T_base_cam`` is the
  calibration's ``T_base_cam`` (eye-to-hand) or ``T_base_tool(capture) · T_tool_cam``
  (eye-in-hand, which needs the robot pose at capture; corrected by the calibration's systematic
  robot error when its chosen error model has one). Uncertainty: first-order propagation of
  the hand-eye covariance (6x6), the pixel noise and, eye-in-hand, the robot's stated pose noise at
  capture (the calibration's robot noise model), by numerical Jacobians.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration import CalibrationError
from calibration.camera_model import CameraModel
from calibration.geometry import as_transform, perturb, ur_pose_to_transform
from calibration.npoint import NPointResult

DEFAULT_NPOINT_PIXEL_SIGMA_PX = 0.1


class MappingError(CalibrationError):
    """The pixel cannot be mapped (wrong inputs for this calibration, ray misses the plane...).

    The message says what is wrong; ``inputs`` names the arguments of ``pixel_to_robot`` at fault
    (``plane_z_mm``, ``robot_pose``, ``camera``) and ``need`` what to do with them: ``"give"``
    (missing), ``"leave out"`` (this calibration does not use it) or ``"check"`` (it does not fit).
    A front end words its hint from these in its own names (a command-line flag, a body field).
    """

    def __init__(self, message: str, inputs: tuple[str, ...] = (), need: str = "") -> None:
        super().__init__(message)
        self.inputs = inputs
        self.need = need


@dataclass
class RobotPoint:
    """A mapped point in the robot base frame (mm) with its covariance (mm²)."""

    xyz_mm: NDArray[np.float64]
    cov_mm2: NDArray[np.float64]
    kind: str
    pixel_sigma_px: float

    @property
    def sigma_mm(self) -> NDArray[np.float64]:
        return np.asarray(np.sqrt(np.clip(np.diag(self.cov_mm2), 0.0, None)), dtype=np.float64)

    def to_json(self) -> dict[str, Any]:
        s = self.sigma_mm
        out: dict[str, Any] = {"calibration": self.kind, "x_mm": float(self.xyz_mm[0]), "y_mm": float(self.xyz_mm[1])}
        sig: dict[str, float] = {"x_mm": float(s[0]), "y_mm": float(s[1])}
        if len(self.xyz_mm) > 2 and np.isfinite(self.xyz_mm[2]):
            out["z_mm"] = float(self.xyz_mm[2])
        if len(s) > 2:
            sig["z_mm"] = float(s[2])
        sig["total_mm"] = float(np.sqrt(np.sum(s**2)))
        out["sigma"] = sig
        out["covariance_mm2"] = self.cov_mm2.tolist()
        out["pixel_sigma_px"] = self.pixel_sigma_px
        return out


def _ray_plane(camera: CameraModel, T_base_cam: NDArray[np.float64], uv: NDArray[np.float64], z_m: float,
               ray_cam: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """The pixel's ray (or the given camera-frame ray of it) intersected with the plane z = z_m."""
    d = T_base_cam[:3, :3] @ (camera.unproject(uv.reshape(1, 2))[0] if ray_cam is None else ray_cam)
    o = T_base_cam[:3, 3]
    if abs(d[2]) < 1e-9 * np.linalg.norm(d):
        raise MappingError("the pixel's ray is parallel to the working plane", ("plane_z_mm",), "check")
    s = (z_m - o[2]) / d[2]
    if s <= 0:
        raise MappingError(f"the working plane z = {z_m * 1e3:g} mm lies behind the camera for this pixel",
                           ("plane_z_mm", "robot_pose"), "check")
    return np.asarray(o + s * d, dtype=np.float64)


def _matrix(calib: dict[str, Any], key: str) -> NDArray[np.float64]:
    try:
        return as_transform(np.asarray(calib[key], dtype=np.float64), key)
    except KeyError:
        raise MappingError(f"hand-eye calibration lacks {key}") from None


def _systematic_corrected(calib: dict[str, Any], G: NDArray[np.float64]) -> NDArray[np.float64]:
    """The robot pose with the calibration's systematic position correction applied, when its chosen
    error model has one (``error_model.systematic_A``: ``t_true = t_rec + A (t_rec - t_mean)``, base
    frame, metres): X was estimated together with it, so it must be mapped through it too."""
    em = calib.get("error_model") or {}
    A, t_mean = em.get("systematic_A"), em.get("t_mean_m")
    if A is None or t_mean is None:
        return G
    try:
        A_m = np.asarray(A, dtype=np.float64).reshape(3, 3)
        t0 = np.asarray(t_mean, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise MappingError("he.json error_model.systematic_A must be 3x3 and t_mean_m 3 numbers (metres)") from None
    out = G.copy()
    out[:3, 3] = G[:3, 3] + A_m @ (G[:3, 3] - t0)
    return out


def map_handeye(calib: dict[str, Any], uv_px: ArrayLike, camera: CameraModel, plane_z_mm: float,
                robot_pose: ArrayLike | None = None, pixel_sigma_px: float | None = None,
                with_uncertainty: bool = True) -> RobotPoint:
    """Map a pixel with a ``he.json`` calibration onto the plane ``z = plane_z_mm`` (base frame).

    ``robot_pose`` (eye-in-hand only): ``T_base_tool`` at capture, 4x4 or UR ``[x, y, z, rx, ry, rz]``.
    """
    setup = calib.get("setup")
    uv = np.asarray(uv_px, dtype=np.float64).reshape(2)
    if not np.all(np.isfinite(uv)):
        raise MappingError("the pixel coordinates must be finite numbers")
    if setup == "eye-in-hand":
        X = _matrix(calib, "T_tool_cam")
        if robot_pose is None:
            raise MappingError("eye-in-hand: the robot pose at capture is needed", ("robot_pose",), "give")
        rp = np.asarray(robot_pose, dtype=np.float64)
        G = ur_pose_to_transform(rp) if rp.size == 6 else as_transform(rp, "robot pose")
        G = _systematic_corrected(calib, G)
    elif setup == "eye-to-hand":
        X = _matrix(calib, "T_base_cam")
        if robot_pose is not None:
            raise MappingError("eye-to-hand: the camera is fixed, the robot pose is not used", ("robot_pose",),
                               "leave out")
        G = np.eye(4)
    else:
        raise MappingError(f"not a hand-eye calibration: setup is {setup!r} (eye-in-hand or eye-to-hand)")
    unc = calib.get("uncertainty", {})
    cov_X = np.asarray(unc.get("covariance", np.zeros((6, 6))), dtype=np.float64).reshape(6, 6)
    noise = calib.get("robot_noise", {})
    sig_px = float(calib.get("pixel_sigma_px", 0.1) if pixel_sigma_px is None else pixel_sigma_px)
    z = plane_z_mm * 1e-3

    ray0 = camera.unproject(uv.reshape(1, 2))[0]  # shared by every perturbation that leaves the pixel alone

    def f(p: NDArray[np.float64]) -> NDArray[np.float64]:
        Xp = perturb(X, p[0:6])
        Gp = perturb(G, p[8:14])
        T = Gp @ Xp if setup == "eye-in-hand" else Xp
        return _ray_plane(camera, T, uv + p[6:8], z, None if p[6] or p[7] else ray0)

    p0 = np.zeros(14)
    x0 = f(p0)
    if not with_uncertainty:  # the point alone (e.g. a direction probe): skip the 28 Jacobian rays
        return RobotPoint(x0 * 1e3, np.full((3, 3), np.nan), f"hand-eye ({setup})", sig_px)
    J = np.zeros((3, 14))
    for k in range(14):
        h = 1e-4 if k in (6, 7) else 1e-7
        pp, pm = p0.copy(), p0.copy()
        pp[k] += h
        pm[k] -= h
        J[:, k] = (f(pp) - f(pm)) / (2 * h)
    S = np.zeros((14, 14))
    S[:6, :6] = cov_X
    S[6, 6] = S[7, 7] = sig_px**2
    if setup == "eye-in-hand":
        sr = np.radians(float(noise.get("sigma_deg", 0.0)))
        st = float(noise.get("sigma_mm", 0.0)) * 1e-3
        S[8:11, 8:11] = np.eye(3) * sr**2
        S[11:14, 11:14] = np.eye(3) * st**2
    cov = J @ S @ J.T * 1e6
    return RobotPoint(x0 * 1e3, cov, f"hand-eye ({setup})", sig_px)


def map_npoint(calib: dict[str, Any] | NPointResult, uv_px: ArrayLike, camera: CameraModel | None = None,
               plane_z_mm: float | None = None, pixel_sigma_px: float | None = None) -> RobotPoint:
    """Map a pixel with an ``np.json`` calibration; ``camera`` overrides the one stored in it."""
    res = calib if isinstance(calib, NPointResult) else NPointResult.from_json(calib)
    if camera is not None:
        res.camera = camera
    uv = np.asarray(uv_px, dtype=np.float64).reshape(1, 2)
    if not np.all(np.isfinite(uv)):
        raise MappingError("the pixel coordinates must be finite numbers")
    sig = DEFAULT_NPOINT_PIXEL_SIGMA_PX if pixel_sigma_px is None else float(pixel_sigma_px)
    xy = res.map(uv)[0]
    cov = np.nan_to_num(res.map_covariance(uv, sig)[0], nan=0.0)
    z = float("nan") if plane_z_mm is None else float(plane_z_mm)
    return RobotPoint(np.array([xy[0], xy[1], z]), cov, f"n-point ({res.model})", sig)


def pixel_to_robot(calib: dict[str, Any], uv_px: ArrayLike, *, camera: CameraModel | None = None,
                   plane_z_mm: float | None = None, robot_pose: ArrayLike | None = None,
                   pixel_sigma_px: float | None = None) -> RobotPoint:
    """A pixel to a robot-frame point in mm with its 1-σ uncertainty, for either calibration kind.

    ``calib`` is the parsed ``np.json`` or ``he.json``. Hand-eye needs ``plane_z_mm`` (the working
    plane's height in the base frame), a camera (given or stored in the calibration) and,
    eye-in-hand, ``robot_pose`` at capture.
    """
    if not isinstance(calib, dict):
        raise MappingError("the calibration must be a JSON object (np.json or he.json)")
    if "setup" in calib:
        cam = camera
        if cam is None and "camera" in calib:
            cam = CameraModel.from_dict(calib["camera"])
        if cam is None:
            raise MappingError("hand-eye mapping needs the camera model", ("camera",), "give")
        if plane_z_mm is None:
            raise MappingError("hand-eye mapping needs the working plane's height", ("plane_z_mm",), "give")
        return map_handeye(calib, uv_px, cam, float(plane_z_mm), robot_pose, pixel_sigma_px)
    if "H" in calib and "model" in calib:
        if robot_pose is not None:
            raise MappingError("an n-point calibration maps pixels of a fixed camera, the robot pose is not used",
                               ("robot_pose",), "leave out")
        return map_npoint(calib, uv_px, camera, plane_z_mm, pixel_sigma_px)
    raise MappingError("not a calibration this command knows: expected np.json (model, H) or he.json (setup, ...)")
