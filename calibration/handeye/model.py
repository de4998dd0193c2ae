"""Hand-eye data types: setups, limits, errors, the stated robot noise, stations and the result."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Final, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration import CalibrationError
from calibration.camera_model import CameraModel
from calibration.geometry import invert

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


class HandEyeError(CalibrationError):
    """The data cannot give a trustworthy hand-eye calibration; the message says why and what to do.

    ``alternative``: another solver of this library that suits the data when the cell moves that
    way (``"dof4"``: the 4-DOF solver, for a SCARA or a top-down-only cell, given the target's
    height), or ``""``. A front end words the way to it (a command, a routine's parameter).
    """

    def __init__(self, message: str, alternative: str = "") -> None:
        super().__init__(message)
        self.alternative = alternative


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
    w: NDArray[np.float64] | None = None
    """(n,) relative weights of the points (1 / their relative detection uncertainty), or None (all 1)."""
    pnp_ssr_w: float = 0.0
    """Weighted sum of squared PnP residuals (px²): the pixel noise estimate's raw material."""


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
    """The camera used: the given one, or the jointly refined one (``intrinsics_refined``)."""
    error_model: dict[str, Any] = field(default_factory=dict)
    """Which robot error model was used and how each candidate predicted held-out stations."""
    intrinsics_refined: bool = False
    camera_initial: CameraModel | None = None
    """The camera the solve started from (given), kept when the intrinsics were refined: ``camera``
    is then the one to map through, and this one says which intrinsics calibration it began with."""
    camera_uncertainty: str = "none"
    """How the camera's covariance entered ``cov_X``/``cov_Z``: ``"prior"`` (joint intrinsics
    refinement with the camera's covariance as its prior), ``"propagated"`` (intrinsics held fixed,
    their covariance propagated to first order) or ``"none"`` (no camera covariance given)."""

    def predict_cam_target(self, T_base_tool: Mat4) -> Mat4:
        """Predicted ``T_cam_target`` of a new station with recorded robot pose ``T_base_tool``,
        through the chosen error model (its systematic correction, if any)."""
        G = np.asarray(T_base_tool, dtype=np.float64).copy()
        A = self.error_model.get("systematic_A")
        if A is not None:
            G[:3, 3] = G[:3, 3] + np.asarray(A) @ (G[:3, 3] - np.asarray(self.error_model["t_mean_m"]))
        H = G if self.setup == "eye-in-hand" else invert(G)
        return np.asarray(invert(self.X) @ invert(H) @ self.Z, dtype=np.float64)

    def predict_pixels(self, T_base_tool: Mat4, points_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 2) predicted pixels of target points ``points_m`` (target frame, m) at a new station."""
        if self.camera is None:
            raise HandEyeError("this result carries no camera model; pixels cannot be predicted")
        C = self.predict_cam_target(T_base_tool)
        return self.camera.project(np.asarray(points_m, dtype=np.float64) @ C[:3, :3].T + C[:3, 3])

    @property
    def uncertainty_rot_deg(self) -> float:
        return float(np.degrees(np.sqrt(np.trace(self.cov_X[:3, :3]))))

    @property
    def uncertainty_trans_mm(self) -> float:
        return float(1e3 * np.sqrt(np.trace(self.cov_X[3:, 3:])))

    def to_json(self) -> dict[str, Any]:
        """``he.json`` (docs/cli.md) plus diagnostics."""
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
                "camera": self.camera_uncertainty,
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
            "quality": {
                "loo_prediction_rms_px": self.loo.get("prediction_rms_px"),
                "primary": "loo_prediction_rms_px: each station's target points predicted from its recorded "
                           "robot pose by a calibration without it (pixel RMS over all held-out points)",
            },
            "error_model": self.error_model,
            "intrinsics_refined": self.intrinsics_refined,
            "time_s": self.time_s,
            **({"camera": self.camera.to_dict()} if self.camera is not None else {}),
            **({"camera_initial": self.camera_initial.to_dict()}
               if self.intrinsics_refined and self.camera_initial is not None else {}),
            "verdict": {"ok": not errors, "problems": [p.to_json() for p in self.problems]},
        }
