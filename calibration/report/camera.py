"""The camera (intrinsics) part of the HTML report, built from ``cam.json`` and the detections.

Everything is recomputed from what is stored (the result JSON, each view's detected points and
its ``T_cam_target``), so the CLI's ``--report`` and the service's ``/calibrations/{id}/report``
are the same report. The residuals follow from the stored poses: at the solver's optimum each
view's pose is optimal for the stored intrinsics, so projecting the target through them gives the
solver's residuals. The figures are drawn in :mod:`calibration.report.camera_plots`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.intrinsics import coverage_counts, uncertainty_summary
from calibration.targets import Target
from calibration.verdict import MAX_PROJECTION_RMS_PX

F64 = NDArray[np.float64]
MAX_VECTORS = 3000
"""Above this many residuals the residual plot shows per-cell RMS and mean vectors instead."""
MAX_THUMBNAILS = 48
GRID_NX = 16


@dataclass
class ViewData:
    image: str
    used: bool
    rms_px: float | None
    reason: str = ""
    outlier: bool = False
    uv: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    residuals_px: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    thumbnail: bytes | None = None
    """A small JPEG of the image (CLI only: the service does not keep images)."""


@dataclass
class CameraReport:
    camera: CameraModel
    result: dict[str, Any]
    views: list[ViewData]
    coverage: NDArray[np.int64]
    uncertainty_map_px: F64
    capture: dict[str, int] = field(default_factory=dict)
    """What the capture did before the solver (``views_tried``, ``views_rejected``: shots without a
    usable target and poses the robot could not reach), when known; see :func:`capture_counts`."""

    @property
    def used(self) -> list[ViewData]:
        return [v for v in self.views if v.used]

    def residuals(self) -> tuple[F64, F64]:
        used = self.used
        if not used:
            return np.zeros((0, 2)), np.zeros((0, 2))
        return np.vstack([v.uv for v in used]), np.vstack([v.residuals_px for v in used])

    def to_json(self) -> dict[str, Any]:
        """The report's figures as rounded JSON (``GET /calibrations/{id}/report?format=json``)."""
        _, r = self.residuals()
        mags = np.linalg.norm(r, axis=1) if len(r) else np.zeros(0)
        return {
            "kind": "camera", "model": self.camera.model, "size": list(self.camera.size),
            "verdict": self.result.get("verdict"),
            "rms_px": _round(self.result.get("rms_px")),
            "views": [{"image": v.image, "used": v.used, "rms_px": _round(v.rms_px), "outlier": v.outlier,
                       **({"reason": v.reason} if v.reason else {})} for v in self.views],
            "rejected_views": [{"image": v.image, "reason": v.reason or "not used"} for v in self.views if not v.used],
            **({"capture": dict(self.capture)} if self.capture else {}),
            "residual_px": {"n": int(len(mags)), "rms": _round(float(np.sqrt(np.mean(mags**2))) if len(mags) else None),
                            "p95": _round(float(np.percentile(mags, 95)) if len(mags) else None)},
            "coverage_points_per_cell": self.coverage.tolist(),
            "uncertainty_map_px": [[_round(x) for x in row] for row in self.uncertainty_map_px],
            "uncertainty_limit_px": MAX_PROJECTION_RMS_PX,
        }


def _round(x: Any, digits: int = 4) -> float | None:
    if x is None or not isinstance(x, int | float) or not math.isfinite(x):
        return None
    return float(f"{x:.{digits}g}")


def capture_counts(result: dict[str, Any], inputs: dict[str, Any]) -> dict[str, int]:
    """The capture's counts as the job reported them (``views_rejected``: views the capture dropped
    before calibrating, not the solver's rejections): from the stored inputs' ``capture`` when the
    routine kept them, else from the verdict's ``coverage_missing.views_tried`` (robot-planned
    capture: every try not given to the solver was rejected); empty when neither is there."""
    kept = inputs.get("capture")
    if isinstance(kept, dict) and {"views_tried", "views_rejected"} <= kept.keys():
        return {"views_tried": int(kept["views_tried"]), "views_rejected": int(kept["views_rejected"])}
    tried = ((result.get("verdict") or {}).get("coverage_missing") or {}).get("views_tried")
    if isinstance(tried, int) and tried >= len(result.get("views") or []):
        return {"views_tried": tried, "views_rejected": tried - len(result.get("views") or [])}
    return {}


def build(result: dict[str, Any], detections: list[dict[str, Any]], target: Target | None,
          images: dict[str, bytes] | None = None, inputs: dict[str, Any] | None = None) -> CameraReport:
    """The report of ``result`` (``cam.json``), ``detections`` (``cellctl detect`` JSON per view).

    Without a target (a camera stored without its detections) the views carry no points and the
    uncertainty map treats the whole image as covered."""
    camera = CameraModel.from_dict(result)
    pts = target.points() if target is not None else None
    lookup = {int(i): k for k, i in enumerate(pts.ids)} if pts is not None else {}
    by_image = {str(d.get("image")): d for d in detections}
    views = []
    for v in result.get("views", []):
        name = str(v.get("image"))
        vd = ViewData(name, bool(v.get("used")), v.get("rms_px"), str(v.get("reason") or ""), bool(v.get("outlier")),
                      thumbnail=(images or {}).get(name))
        det = by_image.get(name)
        T = v.get("T_cam_target")
        if det is not None and det.get("points"):
            ids = [int(p["id"]) for p in det["points"] if int(p["id"]) in lookup]
            uv = np.array([[p["u_px"], p["v_px"]] for p in det["points"] if int(p["id"]) in lookup], dtype=np.float64)
            vd.uv = uv.reshape(-1, 2)
            if T is not None and len(ids) and pts is not None:
                xyz = g.transform_points(np.asarray(T, dtype=np.float64), pts.xyz_m[[lookup[i] for i in ids]])
                vd.residuals_px = camera.project(xyz) - vd.uv  # the solver's sign: projection - observation
        views.append(vd)
    used_uv = np.vstack([v.uv for v in views if v.used and len(v.uv)]) if any(
        v.used and len(v.uv) for v in views) else np.zeros((0, 2))
    coverage = coverage_counts(camera.size, used_uv, GRID_NX)
    cov = np.asarray((result.get("parameters") or {}).get("covariance") or [], dtype=np.float64)
    if cov.size:
        fit = coverage if coverage.sum() else np.ones_like(coverage)
        _, umap = uncertainty_summary(camera, cov, fit)
    else:
        umap = np.full(coverage.shape, np.nan)
    return CameraReport(camera, result, views, coverage, umap, capture_counts(result, inputs or {}))
