"""Frame algebra of the hand-eye model (``H_i X C_i = Z``) and the per-station target poses."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import (
    as_transform,
    invert,
    make_transform,
    rotation_angle,
)
from calibration.geometry import perturb as perturb  # the one copy; the hand-eye solvers import it from here
from calibration.handeye.model import (
    HandEyeError,
    Mat4,
    Problem,
    Station,
)
from calibration.observations import Detection, point_weights
from calibration.pose import PoseEstimationError, estimate_pose
from calibration.targets import Target


# --------------------------------------------------------------------------------------------
# small SE(3) helpers (``perturb``: ``calibration.geometry.perturb``)
# --------------------------------------------------------------------------------------------
def mean_pose(Ts: Sequence[Mat4]) -> Mat4:
    R = Rotation.from_matrix(np.array([T[:3, :3] for T in Ts])).mean().as_matrix()
    return make_transform(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def hand_pose(setup: str, G: Mat4) -> Mat4:
    return G if setup == "eye-in-hand" else invert(G)


def predict_cam_target(setup: str, X: Mat4, Z: Mat4, G: Mat4) -> Mat4:
    """Predicted ``T_cam_target`` of a station with robot pose ``G`` (see the module docstring)."""
    return invert(X) @ invert(hand_pose(setup, G)) @ Z


def target_from_station(setup: str, X: Mat4, G: Mat4, C: Mat4) -> Mat4:
    """``Z = H X C``: the target pose (base or tool frame) implied by one station."""
    return hand_pose(setup, G) @ X @ C


# --------------------------------------------------------------------------------------------
# per-station target pose
# --------------------------------------------------------------------------------------------
def station_pose(camera: CameraModel, obj: NDArray[np.float64], uv: NDArray[np.float64],
                 weights: NDArray[np.float64] | None = None) -> tuple[Mat4, float]:
    """``T_cam_target`` of one view (``calibration.pose.pnp.estimate_pose``: OpenCV's PnP on undistorted
    points, then a refinement on pixels through the full camera model, weighted by ``weights``).
    Returns (T, unweighted rms_px)."""
    try:
        pose = estimate_pose(camera, obj, uv, weights)
    except PoseEstimationError as exc:
        raise HandEyeError(f"target pose of a station failed: {exc}") from exc
    return pose.T_cam_target, pose.rms_px


def make_stations(T_base_tool: Sequence[ArrayLike], detections: Sequence[Detection], camera: CameraModel,
                  target: Target, min_points: int = 4) -> tuple[list[Station], list[Problem]]:
    """Pair robot poses with detections, compute each station's ``T_cam_target``.

    Views where the target was not found (or with fewer than ``min_points`` points) are left out
    and reported as warnings. Points carry relative weights from their detection uncertainty
    (``Detection.uv_sigma_px``, normalised over all stations by ``point_weights``).
    """
    if len(T_base_tool) != len(detections):
        raise HandEyeError(f"{len(T_base_tool)} robot poses but {len(detections)} images: each image needs "
                           "exactly one robot pose (check poses.csv)")
    tp = target.points()
    lookup = {int(i): k for k, i in enumerate(tp.ids)}
    stations: list[Station] = []
    problems: list[Problem] = []
    sigmas: list[NDArray[np.float64] | None] = []
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
        uv = np.asarray(det.uv, dtype=np.float64).reshape(-1, 2)
        stations.append(Station(det.image, G, np.asarray(det.ids, dtype=np.int64), tp.xyz_m[idx], uv))
        sigmas.append(None if det.uv_sigma_px is None else np.asarray(det.uv_sigma_px, dtype=np.float64))
    for st, w in zip(stations, point_weights(sigmas, [len(s.obj) for s in stations]), strict=True):
        st.w = w
        st.C, st.pnp_rms_px = station_pose(camera, st.obj, st.uv, w)
        Cp = st.C
        e = (camera.project(st.obj @ Cp[:3, :3].T + Cp[:3, 3]) - st.uv) * w[:, None]
        st.pnp_ssr_w = float(np.sum(e * e))
    return stations, problems


def transform_error_deg_mm(A: Mat4, B: Mat4) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) difference of two transforms."""
    r = rotation_angle(A[:3, :3].T @ B[:3, :3])
    return float(np.degrees(r)), float(1e3 * np.linalg.norm(A[:3, 3] - B[:3, 3]))
