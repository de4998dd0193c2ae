"""Robot stations for a hand-eye calibration, chosen one at a time from what has been captured.

Our own planner (OpenCV and the solvers take stations as given). Every station is the start pose
rotated about the plate's centre ``P`` (base frame) and moved along the line of sight:

- eye-in-hand, the camera swings about the plate, which therefore stays where it was in the image;
- eye-to-hand, the plate turns about its own centre in front of the fixed camera.

Candidates span tilts (about axes across the line of sight, up to ``max_tilt_deg``), spins (about
the line of sight, up to ``max_spin_deg``) and distances (the start distance times
``1 ± distance_range``). A candidate is kept when the robot's own pose rule accepts it
(``check_pose``: envelope and tool cone) and the plate, predicted through the current estimate of
the hand-eye transform, lies inside the image with a margin and is not seen too obliquely. The
next station is the kept candidate that adds the most information about the hand-eye transform:
a relative rotation by θ about the unit axis ``a`` constrains the translation (and the rotation)
across ``a`` by ``4 sin²(θ/2) (I − a aᵀ)`` (from ``(R_A − I) t_X = …``); the planner maximises the
log-determinant of the sum over all station pairs, so rotations about well-separated axes win,
and until the distances span ``distance_range`` a candidate that widens them gets a bonus.

The estimate starts as a guess (eye-in-hand: the camera frame at the tool's; eye-to-hand: the
plate's frame at the tool's) and is replaced by the pair-filtered closed form of
``calibration.handeye`` as soon as the stations allow. Lengths are metres, angles degrees.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.handeye import (
    MAX_PAIR_ANGLE_DEG,
    MIN_PAIR_ANGLE_DEG,
    WARN_AXIS_SPREAD_DEG,
    hand_pose,
    mean_pose,
    predict_cam_target,
    relative_motions,
    solve_pairs,
    target_from_station,
)
from calibration.targets import Target

Mat4 = NDArray[np.float64]

MIN_ROTATION_DEG = 15.0
"""A relative rotation counts towards "rotation about an axis" from this angle (the checks ask 15-30)."""
MIN_AXIS_SEPARATION_DEG = 45.0
"""Two such rotations count as about different axes when their axes are this far apart."""
IMAGE_MARGIN = 0.03
"""The predicted plate must keep this fraction of the image size from every border."""
MAX_VIEW_ANGLE_DEG = 50.0
"""Most obliquity (plate normal against the line of sight) a planned view may have."""
NEAR_FAILED_DEG = 8.0
NEAR_FAILED_M = 0.03
"""A candidate this close (rotation and position) to a station that gave nothing is left out."""
AZIMUTHS = 16
TILT_FRACTIONS = (0.6, 1.0)
SPIN_FRACTIONS = (-1.0, -0.5, 0.0, 0.5, 1.0)


@dataclass
class Station:
    """One captured station: the recorded robot pose and the plate's pose seen from it."""

    T_base_tool: Mat4
    T_cam_target: Mat4
    purpose: str


@dataclass
class Candidate:
    purpose: str
    T_base_tool: Mat4
    distance_factor: float


@dataclass
class Coverage:
    """What the stations so far give, against the goals (``missing`` names what they lack)."""

    stations: int
    axis_spread_deg: float
    """The solver's measure: the largest angle of a relative rotation axis from their principal axis."""
    axis_separation_deg: float
    """Largest angle between the axes of two relative rotations of at least ``MIN_ROTATION_DEG``."""
    max_rotation_deg: float
    distance_range: float
    """(largest - smallest) camera-to-plate distance over their median."""
    missing: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"stations": self.stations, "axis_spread_deg": round(self.axis_spread_deg, 2),
                "axis_separation_deg": round(self.axis_separation_deg, 2),
                "max_rotation_deg": round(self.max_rotation_deg, 2),
                "distance_range": round(self.distance_range, 4), "missing": list(self.missing)}


def pair_information(A: Mat4) -> NDArray[np.float64]:
    """3x3 information a relative motion ``A`` gives about the hand-eye translation (see module)."""
    return rotation_information(np.asarray(A, dtype=np.float64)[None, :3, :3])


def rotation_information(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """The summed ``pair_information`` of relative rotations ``R`` (n, 3, 3); pairs outside the
    solver's usable angles (``MIN_PAIR_ANGLE_DEG``-``MAX_PAIR_ANGLE_DEG``) give nothing."""
    if len(R) == 0:
        return np.zeros((3, 3))
    # Angle from the trace, axis from the skew part (2 sin(theta) a): the usable angles stay off 0 and 180.
    cos_t = np.clip((np.einsum("nii->n", R) - 1.0) / 2.0, -1.0, 1.0)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    theta = np.arccos(cos_t)
    use = (theta >= math.radians(MIN_PAIR_ANGLE_DEG)) & (theta <= math.radians(MAX_PAIR_ANGLE_DEG))
    if not np.any(use):
        return np.zeros((3, 3))
    a = v[use] / np.linalg.norm(v[use], axis=1, keepdims=True)
    k = 2.0 * (1.0 - cos_t[use])  # 4 sin^2(theta / 2)
    return np.asarray(k.sum() * np.eye(3) - np.einsum("n,ni,nj->ij", k, a, a), dtype=np.float64)


@dataclass
class StationPlanner:
    """Chooses the next station (see the module docstring)."""

    setup: str
    camera: CameraModel
    target: Target
    T0: Mat4
    """The start pose (the plate in view)."""
    C0: Mat4
    """``T_cam_target`` seen from the start pose."""
    check_pose: Callable[[Mat4], None]
    """The robot's own pose rule; raises (``MotionRejected``) for a pose it refuses."""
    max_tilt_deg: float
    max_spin_deg: float
    distance_range: float
    stations: list[Station] = field(default_factory=list)
    tried: set[str] = field(default_factory=set)
    failed: list[Mat4] = field(default_factory=list)
    """Poses whose shot was rejected or whose move was refused: their neighbours are left out too."""
    X: Mat4 = field(init=False)
    Z: Mat4 = field(init=False)
    estimated: bool = field(init=False, default=False)
    _R_stations: NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.centre_m = self.target.points().xyz_m.mean(axis=0)
        pts = self.target.points().xyz_m
        extent = getattr(self.target, "extent_m", None)
        if extent is not None:
            x0, y0, x1, y1 = extent()
            pts = np.vstack([pts, [[x0, y0, 0], [x1, y0, 0], [x0, y1, 0], [x1, y1, 0]]])
        self.outline_m = pts
        if self.setup == "eye-in-hand":
            self.X = np.eye(4)  # the camera frame taken as the tool's until the stations tell
            self.Z = target_from_station(self.setup, self.X, self.T0, self.C0)
        else:
            self.Z = np.eye(4)  # the plate's frame taken as the tool's until the stations tell
            self.X = self.T0 @ self.Z @ g.invert(self.C0)
        self.d0_m = float(np.linalg.norm(self.C0[:3, :3] @ self.centre_m + self.C0[:3, 3]))
        self.stations.append(Station(self.T0.copy(), self.C0.copy(), "start"))

    # -- what has been captured -------------------------------------------------------------------
    def observe(self, T_base_tool: Mat4, T_cam_target: Mat4, purpose: str) -> None:
        """A station captured with the plate seen; the estimate is redone from all stations."""
        self.stations.append(Station(np.array(T_base_tool, dtype=np.float64), np.array(T_cam_target), purpose))
        self._estimate()

    def failed_at(self, T_base_tool: Mat4) -> None:
        """The station at ``T_base_tool`` gave nothing (shot rejected, move refused)."""
        self.failed.append(np.array(T_base_tool, dtype=np.float64))

    def _near_failed(self, T: Mat4) -> bool:
        """Whether ``T`` is within ``NEAR_FAILED_DEG`` and ``NEAR_FAILED_M`` of a failed station: the
        rotation angle of ``R_T^T R_F`` (from its trace) and the distance of the origins, for every failed
        pose at once (``geometry.transform_error``'s numbers; the planner asks it of ~500 candidates a station)."""
        if not self.failed:
            return False
        F = np.asarray(self.failed)
        close = np.linalg.norm(F[:, :3, 3] - T[:3, 3], axis=1) < NEAR_FAILED_M
        if not np.any(close):
            return False
        trace = np.einsum("ij,nij->n", T[:3, :3], F[close, :3, :3])  # trace(R_T^T R_F), each failed pose
        rot_deg = np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))
        return bool(np.any(rot_deg < NEAR_FAILED_DEG))

    def _estimate(self) -> None:
        H = [hand_pose(self.setup, s.T_base_tool) for s in self.stations]
        C = [s.T_cam_target for s in self.stations]
        pairs = [p for p in relative_motions(H, C) if MIN_PAIR_ANGLE_DEG <= p[4] <= MAX_PAIR_ANGLE_DEG]
        if _axis_spread_deg([p[2] for p in pairs]) < 5.0:
            return  # the closed form needs rotations about two axes
        X = solve_pairs(pairs)
        if not np.all(np.isfinite(X)):
            return
        self.X = X
        self.Z = mean_pose([target_from_station(self.setup, X, s.T_base_tool, s.T_cam_target)
                            for s in self.stations])
        self.estimated = True

    def distances_m(self) -> list[float]:
        return [float(np.linalg.norm(s.T_cam_target[:3, :3] @ self.centre_m + s.T_cam_target[:3, 3]))
                for s in self.stations]

    def coverage(self, min_stations: int) -> Coverage:
        H = [hand_pose(self.setup, s.T_base_tool) for s in self.stations]
        motions = [invert_mul(H[j], H[i]) for i in range(len(H)) for j in range(i + 1, len(H))]
        angles = [math.degrees(float(np.linalg.norm(g.log_so3(A[:3, :3])))) for A in motions]
        usable = [A for A, a in zip(motions, angles, strict=True) if MIN_PAIR_ANGLE_DEG <= a <= MAX_PAIR_ANGLE_DEG]
        big = [A for A, a in zip(motions, angles, strict=True) if MIN_ROTATION_DEG <= a <= MAX_PAIR_ANGLE_DEG]
        d = self.distances_m()
        cov = Coverage(len(self.stations), _axis_spread_deg(usable), _axis_separation_deg(big),
                       max(angles, default=0.0), (max(d) - min(d)) / float(np.median(d)))
        if cov.stations < min_stations:
            cov.missing.append(f"stations: {cov.stations} of {min_stations} captured")
        if cov.axis_separation_deg < MIN_AXIS_SEPARATION_DEG:
            cov.missing.append(f"rotation about two axes: relative rotations of at least {MIN_ROTATION_DEG:g} deg "
                               f"span only {cov.axis_separation_deg:.1f} deg of axis direction "
                               f"(at least {MIN_AXIS_SEPARATION_DEG:g} wanted)")
        if cov.axis_spread_deg < WARN_AXIS_SPREAD_DEG:
            cov.missing.append(f"axis spread: {cov.axis_spread_deg:.1f} deg (at least {WARN_AXIS_SPREAD_DEG:g} wanted)")
        if cov.distance_range < self.distance_range:
            cov.missing.append(f"distances: they span {100 * cov.distance_range:.1f} % of the median distance "
                               f"({100 * self.distance_range:.0f} % wanted)")
        return cov

    # -- planning ----------------------------------------------------------------------------------
    def next(self) -> tuple[Candidate | None, dict[str, int]]:
        """The most informative candidate not tried yet, and why the others were left out (counts)."""
        info = self._information()
        base = _logdet(info)
        self._R_stations = self._hand_rotations()
        d = self.distances_m()
        span = max(d) - min(d)
        widen = span < self.distance_range * float(np.median(d))
        best: tuple[float, Candidate] | None = None
        left_out: dict[str, int] = {}
        cands = [cand for cand in self.candidates() if cand.purpose not in self.tried]
        for cand, why in zip(cands, self._refusals(cands), strict=True):
            if why:
                left_out[why] = left_out.get(why, 0) + 1
                continue
            gain = _logdet(info + self._information_with(cand.T_base_tool)) - base
            d_new = self.d0_m * cand.distance_factor
            widened = max(max(d), d_new) - min(min(d), d_new) - span
            if widen:
                gain += 0.5 * min(widened / (self.distance_range * self.d0_m), 1.0)
            if best is None or gain > best[0]:
                best = (gain, cand)
        if best is not None:
            self.tried.add(best[1].purpose)
        return (best[1] if best else None), left_out

    def candidates(self) -> list[Candidate]:
        """Every station the planner may choose: tilts x spins x distances about the plate's centre."""
        P = self._centre_base()
        cam = self._camera_centre_base(self.T0)
        v = (P - cam) / np.linalg.norm(P - cam)
        e1 = self.T0[:3, 0] - v * float(self.T0[:3, 0] @ v)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(v, e1)
        # Until the stations give an estimate, the plate's place is a guess: move by less.
        tilts = TILT_FRACTIONS if self.estimated else TILT_FRACTIONS[:1]
        spins = SPIN_FRACTIONS if self.estimated else tuple(f for f in SPIN_FRACTIONS if abs(f) <= 0.5)
        out: list[Candidate] = []
        spin = {sf: g.rotvec_to_matrix(v * math.radians(sf * self.max_spin_deg)) for sf in spins}
        for k_az in range(AZIMUTHS):
            phi = 2 * math.pi * k_az / AZIMUTHS
            axis = math.cos(phi) * e1 + math.sin(phi) * e2
            for tf in tilts:
                tilt = g.rotvec_to_matrix(axis * math.radians(tf * self.max_tilt_deg))
                for sf in spins:
                    R = tilt @ spin[sf]
                    name = (f"tilt {tf * self.max_tilt_deg:.0f} deg towards {360 * k_az / AZIMUTHS:.0f} deg, "
                            f"spin {sf * self.max_spin_deg:+.0f} deg")
                    out += self._at_distances(name, R, P, v)
        for sf in spins:
            if sf:
                R = spin[sf]
                out += self._at_distances(f"spin {sf * self.max_spin_deg:+.0f} deg", R, P, v)
        return out

    def _at_distances(self, name: str, R: NDArray[np.float64], P: NDArray[np.float64],
                      v: NDArray[np.float64]) -> list[Candidate]:
        out = []
        rotated = np.eye(4)
        rotated[:3, :3] = R @ self.T0[:3, :3]
        rotated[:3, 3] = P + R @ (self.T0[:3, 3] - P)
        factors = (1.0 - self.distance_range, 1.0, 1.0 + self.distance_range) if self.estimated else (1.0,)
        for f in factors:
            T = rotated.copy()
            # Along the line of sight: the camera backs away (eye-in-hand), the plate moves away (eye-to-hand).
            step = (f - 1.0) * self.d0_m
            T[:3, 3] += -step * (R @ v) if self.setup == "eye-in-hand" else step * v
            out.append(Candidate(f"{name}, distance x{f:.2f}", T, f))
        return out

    def _refusals(self, cands: list[Candidate]) -> list[str]:
        """Why each of ``cands`` cannot be a station ('' when it can), in this order: the robot's own
        pose rule, a failed station next to it, the plate behind the camera, (partly) outside the image,
        seen too obliquely. The plate's outline is projected for all candidates at once (each point's
        pixel is its own: the same numbers as one candidate at a time)."""
        why = [""] * len(cands)
        Cs: list[Mat4] = []
        kept: list[int] = []
        for i, cand in enumerate(cands):
            try:
                self.check_pose(cand.T_base_tool)
            except Exception as exc:  # noqa: BLE001 - the robot's own rule: any refusal leaves the pose out
                # One count per kind of refusal, whatever the numbers in it.
                why[i] = "refused by the robot's limits: " + re.sub(r"-?\d+(\.\d+)?", "N", str(exc).split(";")[0])
                continue
            if self._near_failed(cand.T_base_tool):
                why[i] = "next to a station that gave nothing"
                continue
            kept.append(i)
            Cs.append(predict_cam_target(self.setup, self.X, self.Z, cand.T_base_tool))
        if not kept:
            return why
        C = np.asarray(Cs)
        xyz = np.einsum("pj,cij->cpi", self.outline_m, C[:, :3, :3]) + C[:, None, :3, 3]  # (candidate, point, 3)
        behind = np.any(xyz[:, :, 2] <= 0, axis=1)
        with np.errstate(all="ignore"):  # a candidate with points behind the camera is refused as such
            uv = self.camera.project(xyz.reshape(-1, 3)).reshape(len(kept), -1, 2)
        w, h = self.camera.width, self.camera.height
        m = IMAGE_MARGIN * np.array([w, h])
        inside = np.all(np.isfinite(uv) & (uv >= m) & (uv <= np.array([w - 1, h - 1]) - m), axis=(1, 2))
        centre = np.einsum("cij,j->ci", C[:, :3, :3], self.centre_m) + C[:, :3, 3]
        for k, i in enumerate(kept):
            if behind[k]:
                why[i] = "plate behind the camera"
            elif not inside[k]:
                why[i] = "plate predicted (partly) outside the image"
            else:
                cos_view = abs(float(C[k, :3, 2] @ centre[k])) / float(np.linalg.norm(centre[k]))
                if math.degrees(math.acos(min(1.0, cos_view))) > MAX_VIEW_ANGLE_DEG:
                    why[i] = f"plate seen more obliquely than {MAX_VIEW_ANGLE_DEG:g} deg"
        return why

    # -- information -------------------------------------------------------------------------------
    def _hand_rotations(self) -> NDArray[np.float64]:
        return np.array([hand_pose(self.setup, s.T_base_tool)[:3, :3] for s in self.stations])

    def _information(self) -> NDArray[np.float64]:
        R = self._hand_rotations()
        i, j = np.triu_indices(len(R), 1)
        # The relative motion inv(H_j) H_i: its rotation R_j^T R_i.
        return rotation_information(np.einsum("nki,nkj->nij", R[j], R[i]))

    def _information_with(self, T_base_tool: Mat4) -> NDArray[np.float64]:
        Rc = hand_pose(self.setup, T_base_tool)[:3, :3]
        return rotation_information(np.einsum("nki,kj->nij", self._R_stations, Rc))

    # -- frames ------------------------------------------------------------------------------------
    def _centre_base(self) -> NDArray[np.float64]:
        """The plate's centre in the base frame at the start pose (current estimate)."""
        T_base_target = self.Z if self.setup == "eye-in-hand" else self.T0 @ self.Z
        return np.asarray(T_base_target[:3, :3] @ self.centre_m + T_base_target[:3, 3], dtype=np.float64)

    def _camera_centre_base(self, T_base_tool: Mat4) -> NDArray[np.float64]:
        T_base_cam = T_base_tool @ self.X if self.setup == "eye-in-hand" else self.X
        return np.asarray(T_base_cam[:3, 3], dtype=np.float64)


def invert_mul(A: Mat4, B: Mat4) -> Mat4:
    """``inv(A) @ B`` for rigid transforms."""
    return np.asarray(g.invert(A) @ B, dtype=np.float64)


def _logdet(M: NDArray[np.float64]) -> float:
    # The small ridge keeps the measure finite while the stations are still degenerate.
    return float(np.linalg.slogdet(M + 1e-3 * np.eye(3))[1])


def _axis_spread_deg(motions: list[Mat4]) -> float:
    """The solver's rotation-axis spread: largest angle of an axis from the principal axis."""
    if not motions:
        return 0.0
    axes = np.array([g.log_so3(A[:3, :3]) for A in motions])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    _, V = np.linalg.eigh(axes.T @ axes)
    return float(np.degrees(np.arccos(np.clip(np.abs(axes @ V[:, -1]), 0.0, 1.0))).max())


def _axis_separation_deg(motions: list[Mat4]) -> float:
    """Largest angle between the (unsigned) axes of two relative rotations."""
    if len(motions) < 2:
        return 0.0
    axes = np.array([g.log_so3(A[:3, :3]) for A in motions])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip(np.abs(axes @ axes.T).min(), 0.0, 1.0))))
