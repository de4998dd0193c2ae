"""Checks before solving: robot-pose conventions, degenerate motion, mis-paired stations."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from calibration.geometry import (
    exp_so3,
    invert,
    log_so3,
    make_transform,
    transform_to_ur_pose,
)
from calibration.handeye.closed_form import axxb_residuals, relative_motions, solve_pairs
from calibration.handeye.frames import (
    hand_pose,
)
from calibration.handeye.model import (
    MAX_PAIR_ANGLE_DEG,
    MIN_AXIS_SPREAD_DEG,
    MIN_PAIR_ANGLE_DEG,
    MIN_STATIONS,
    OUTLIER_FACTOR,
    OUTLIER_FLOOR,
    WARN_AXIS_SPREAD_DEG,
    ConventionError,
    HandEyeError,
    Mat4,
    Problem,
)


# --------------------------------------------------------------------------------------------
# checks before solving
# --------------------------------------------------------------------------------------------
def _rpy(raw: NDArray[np.float64], order: str, degrees: bool) -> Mat4:
    return make_transform(Rotation.from_euler(order, raw[3:6], degrees=degrees).as_matrix(), raw[:3])


def _ur(raw: NDArray[np.float64], rot_scale: float = 1.0, trans_scale: float = 1.0) -> Mat4:
    return make_transform(exp_so3(raw[3:6] * rot_scale), raw[:3] * trans_scale)


_HYPOTHESES: Final[dict[str, tuple[str, str]]] = {
    "inverted": ("the robot poses inverted (T_tool_base instead of T_base_tool)",
                 "invert each robot pose — or, if the poses are right, solve with the other setup "
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


def fit_score(setup: str, G: Sequence[Mat4], C: Sequence[Mat4]) -> tuple[float, float, float] | None:
    """(score, rot_rms_deg, trans_rms_mm) of the pair-filtered closed form, or None if too few pairs.

    The score is a robust consistency measure: the median over pairs of
    ``hypot(rot / 0.1°, trans / 1 mm)``.
    """
    H = [hand_pose(setup, g) for g in G]
    pairs = [p for p in relative_motions(H, C) if MIN_PAIR_ANGLE_DEG <= p[4] <= MAX_PAIR_ANGLE_DEG]
    if len(pairs) < 2:
        return None
    X = solve_pairs(pairs)
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
    given = fit_score(setup, G, C)
    if given is None:
        return {"checked": False, "reason": "too few pairs with enough rotation"}
    fits["as_given"] = {"rot_rms_deg": given[1], "trans_rms_mm": given[2], "score": given[0]}
    best_name, best = "as_given", given
    for name in _HYPOTHESES:
        try:
            alt = fit_score(setup, _hypothesis_poses(name, G, raw), C)
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
    H = [hand_pose(setup, g) for g in G]
    allp = relative_motions(H, C)
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
    axes = np.array([log_so3(p[2][:3, :3]) for p in kept])
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
            f"15-30 deg about a second axis (spread >= {WARN_AXIS_SPREAD_DEG:g} deg recommended).", alternative="dof4")
    if spread < WARN_AXIS_SPREAD_DEG:
        problems.append(Problem("low_axis_spread",
                                f"rotation axes span only {spread:.1f} deg; the result is weakly determined — "
                                "add poses rotated about other axes"))
    return kept, info, problems


def screw_invariants(T: Mat4) -> tuple[float, float]:
    """Rotation angle (deg) and translation along the rotation axis (mm): invariant under conjugation."""
    w = log_so3(T[:3, :3])
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
    H = [hand_pose(setup, g) for g in G]
    M = np.zeros((n, n))
    for i, j, A, B, _ in relative_motions(H, C):
        aa, da = screw_invariants(A)
        ab, db = screw_invariants(B)
        M[i, j] = M[j, i] = float(np.hypot((aa - ab) / 0.1, (da - db) / 1.0))
    score = np.array([np.median(np.delete(M[i], i)) for i in range(n)])
    med = float(np.median(score))
    flagged = [int(i) for i in np.flatnonzero(score > max(OUTLIER_FACTOR * med, OUTLIER_FLOOR))]
    if n - len(flagged) < MIN_STATIONS:
        return [], score
    return flagged, score
