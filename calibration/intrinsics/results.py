"""Intrinsics results (per view and overall), limits and the error type."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from calibration import CalibrationError
from calibration.camera_model import CameraModel

F64 = NDArray[np.float64]

MIN_VIEWS: Final = 3
"""Fewer views cannot determine fx, fy, cx, cy from a planar target (Zhang)."""
MIN_POINTS_PER_VIEW: Final = 6
POINT_OUTLIER_SIGMAS: Final = 5.0
VIEW_OUTLIER_FACTOR: Final = 3.0
JACKKNIFE_GROUPS: Final = 10
JACKKNIFE_MIN_VIEWS: Final = 8
"""Fewer views give too few replicates: the jackknife's own noise and upward bias then inflated
honest sets (rendered sets of 6 views: median actual/reported 0.37-0.47 with it, 0.66 without)."""
JACKKNIFE_MIN_COVER: Final = 3
"""The jackknife is compared with the analytic covariance on cells at least this many views saw."""


class IntrinsicsError(CalibrationError):
    """The data cannot produce a calibration (too few views or points, degenerate geometry)."""


class CrossValidationError(IntrinsicsError):
    """Cross-validation cannot run on these data (k too large for the usable views, a fold fails);
    the calibration itself may still be fine."""


# --------------------------------------------------------------------------------------------
# results


@dataclass
class ViewResult:
    """One image's part in the calibration."""

    image: str
    used: bool
    n_points: int = 0
    rms_px: float = float("nan")
    reason: str = ""
    outlier: bool = False
    n_outlier_points: int = 0
    T_cam_target: F64 | None = None
    ids: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    uv: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    residuals_px: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    corner_sigma_px: float = float("nan")
    """Median 1-sigma precision the detector stated for this view's points (px), NaN without."""

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"image": self.image, "rms_px": fin(self.rms_px), "used": self.used,
                               "n_points": self.n_points}
        if len(self.residuals_px):
            # the view's worst corner and its detector's stated precision beside the RMS: a view
            # whose residuals far exceed what its corners claim is a bad view (blur, a moved board)
            out["max_px"] = fin(float(np.max(np.hypot(*self.residuals_px.T))))
        if np.isfinite(self.corner_sigma_px):
            out["corner_sigma_px"] = fin(self.corner_sigma_px)
        if self.reason:
            out["reason"] = self.reason
        if self.outlier:
            out["outlier"] = True
        if self.n_outlier_points:
            out["n_outlier_points"] = self.n_outlier_points
        if self.T_cam_target is not None:
            out["T_cam_target"] = self.T_cam_target.tolist()
        return out


@dataclass
class IntrinsicsResult:
    """A calibrated camera with its residuals, parameter covariance, uncertainty and verdict."""

    camera: CameraModel
    rms_px: float
    sigma_px: float
    views: list[ViewResult]
    param_names: list[str]
    covariance: F64
    """Intrinsics covariance (order of ``param_names``), marginalised over the view poses."""
    uncertainty: dict[str, Any]
    verdict: dict[str, Any]
    coverage: NDArray[np.int64]
    """(ny, nx) count of observed points per image cell (used views)."""
    uncertainty_map_px: F64
    """(ny, nx) 1-sigma projection uncertainty at each cell centre (rotation compensated)."""
    iterations: int = 0
    time_s: float = 0.0
    board_warp: dict[str, Any] | None = None
    """The target's solved warp (``calibrate(board_warp=True)``): heights (mm) and their 1-sigma."""
    view_rejection: dict[str, Any] | None = None
    """The influence test's summary (``calibrate(reject_views=True)``): rule, false-alarm rate, the
    residual scale and each rejected view with its projection shift and statistic."""
    regularisation: dict[str, Any] | None = None
    """The regularised solve's rule and weights (``calibrate(regularise=True)``), None when unregularised."""

    @property
    def param_sigmas(self) -> dict[str, float]:
        return {n: float(np.sqrt(max(self.covariance[i, i], 0.0))) for i, n in enumerate(self.param_names)}

    def to_json(self) -> dict[str, Any]:
        """The camera result file (docs/cli.md ``cam.json``)."""
        out = self.camera.to_dict()
        out["rms_px"] = fin(self.rms_px)
        out["views"] = [v.to_json() for v in self.views]
        out["rejected_views"] = [{"image": v.image, "reason": v.reason} for v in self.views if not v.used]
        out["uncertainty"] = self.uncertainty
        out["verdict"] = self.verdict
        out["parameters"] = {
            "names": self.param_names,
            "sigma": [self.param_sigmas[n] for n in self.param_names],
            "covariance": self.covariance.tolist(),
        }
        out["residual_sigma_px"] = fin(self.sigma_px)
        out["n_views_used"] = sum(v.used for v in self.views)
        out["n_points_used"] = int(sum(v.n_points for v in self.views if v.used))
        out["solver"] = {"iterations": self.iterations, "time_s": round(self.time_s, 3)}
        if self.board_warp is not None:
            out["board_warp"] = self.board_warp
        if self.view_rejection is not None:
            out["view_rejection"] = self.view_rejection
        if self.regularisation is not None:
            out["regularisation"] = self.regularisation
        return out


def fin(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
