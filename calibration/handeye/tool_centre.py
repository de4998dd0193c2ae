"""Tool centre for a fixed camera: turn the tool about z and fit the circle its feature describes.

HALCON's "terminal centre". The robot reports its flange axis, but the camera sees (and a mark
must receive) a feature of the gripper, offset from that axis. Turning the tool about the base
z axis at one flange position moves the feature on a circle: its centre is the flange axis, its
radius and phase the offset.

Model (mm, base frame, through the N-point map so the circle is metric): at flange position
``g`` and tool angle ``rz`` (about base z, counter-clockwise seen from above) the feature lies at
``p = c_g + Rz(rz) · o``. ``o = (dx, dy)`` is the offset in the tool frame — tool x/y along base
x/y at ``rz = 0`` (a tool pointing down included: the offset is what the feature's position
does, not how the flange frame is drawn) — shared by all flange positions; ``c_g`` is the
circle centre, one per flange position, free (so a map or robot offset does not bias ``o``).
Linear least squares in ``(c_g, o)``. 1-σ: the residuals' scatter (``σ² (AᵀA)⁻¹``) plus the
N-point map's own parameter covariance carried through the fit (a scale or rotation error of
the map scales or turns the offset). A free circle fit per position (Kåsa) is reported next to
it as a check of the angles.

Our own code (a small linear model; OpenCV has no tool-centre calibration). The feature is
assumed to lie in the plane the N-point marks were taught on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration import CalibrationError
from calibration.geometry import make_transform
from calibration.npoint import NPointResult, apply_h

F64 = NDArray[np.float64]

MIN_ANGLES: Final = 3
MIN_ARC_DEG: Final = 30.0
FLANGE_TOLERANCE_MM: Final = 0.5
RECOMMENDED_ANGLES: Final = 7


class ToolCentreError(CalibrationError):
    """The rotations cannot give a tool centre (too few angles, too short an arc...); says why."""


@dataclass
class ToolCentreResult:
    offset_mm: F64
    cov_offset_mm2: F64
    rms_mm: float
    positions: list[dict[str, Any]]
    residuals_mm: F64

    @property
    def sigma_offset_mm(self) -> float:
        """RMS 1-σ of the offset vector (sqrt of the covariance's trace), mm."""
        return float(np.sqrt(max(np.trace(self.cov_offset_mm2), 0.0)))

    def to_json(self) -> dict[str, Any]:
        """``tcp.json`` (the command-line contract) plus per-position diagnostics."""
        return {"offset_mm": self.offset_mm.tolist(),
                "rotation_centre_px": [p["centre_px"] for p in self.positions],
                "rms_mm": self.rms_mm,
                "uncertainty": {"offset_mm": self.sigma_offset_mm,
                                "offset_axes_mm": np.sqrt(np.clip(np.diag(self.cov_offset_mm2), 0, None)).tolist(),
                                "offset_covariance_mm2": self.cov_offset_mm2.tolist()},
                "radius_mm": float(np.linalg.norm(self.offset_mm)),
                "phase_deg": float(np.degrees(np.arctan2(self.offset_mm[1], self.offset_mm[0]))),
                "offset_frame": "tool x/y along base x/y at rz = 0; feature = flange + Rz(rz) offset",
                "positions": self.positions}


def _rz(deg: F64) -> F64:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _kasa(xy: F64) -> tuple[F64, float]:
    """Algebraic circle fit: centre and radius."""
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    b = np.sum(xy * xy, axis=1)
    sol = np.linalg.lstsq(A, b, rcond=None)[0]
    c = sol[:2]
    return c, float(np.sqrt(max(sol[2] + c @ c, 0.0)))


def group_by_flange(flange_mm: F64, tolerance_mm: float = FLANGE_TOLERANCE_MM) -> NDArray[np.int64]:
    """Group index per row: rows whose flange positions lie within ``tolerance_mm`` of a group's first."""
    labels = np.full(len(flange_mm), -1, dtype=np.int64)
    centres: list[F64] = []
    for k, f in enumerate(flange_mm):
        for g, c in enumerate(centres):
            if np.linalg.norm(f - c) <= tolerance_mm:
                labels[k] = g
                break
        else:
            centres.append(f)
            labels[k] = len(centres) - 1
    return labels


def _check_group(g_flange: F64, rz: F64) -> float:
    where = f"flange position ({g_flange[0]:.1f}, {g_flange[1]:.1f}) mm"
    if len(rz) < MIN_ANGLES:
        raise ToolCentreError(f"{where}: only {len(rz)} angle(s); a circle needs at least {MIN_ANGLES} (turn the "
                              f"tool to {RECOMMENDED_ANGLES} angles over 90-180 deg there)")
    a = np.sort(np.mod(rz, 360.0))
    gaps = np.diff(np.concatenate([a, [a[0] + 360.0]]))
    arc = float(360.0 - gaps.max())  # the smallest arc holding every angle
    if arc < MIN_ARC_DEG:
        raise ToolCentreError(f"{where}: the angles span only {arc:.1f} deg; an arc under {MIN_ARC_DEG:g} deg "
                              "cannot separate the circle's centre from its radius - turn the tool over 90-180 deg")
    return arc


def fit_tool_centre(uv_px: ArrayLike, flange_mm: ArrayLike, rz_deg: ArrayLike,
                    npoint: NPointResult) -> ToolCentreResult:
    """Tool centre from the feature's pixels ``uv_px`` (N, 2) at flange positions ``flange_mm`` (N, 2)
    and tool angles ``rz_deg`` (N,), mapped to mm by ``npoint`` (see the module docstring)."""
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    fl = np.asarray(flange_mm, dtype=np.float64).reshape(-1, 2)
    rz = np.asarray(rz_deg, dtype=np.float64).reshape(-1)
    if not (len(uv) == len(fl) == len(rz)):
        raise ToolCentreError(f"{len(uv)} pixels, {len(fl)} flange positions and {len(rz)} angles: give one of each "
                              "per row")
    if not (np.all(np.isfinite(uv)) and np.all(np.isfinite(fl)) and np.all(np.isfinite(rz))):
        raise ToolCentreError("the rotations contain NaN or infinity")
    labels = group_by_flange(fl)
    n_g = int(labels.max()) + 1
    arcs = [_check_group(fl[labels == g][0], rz[labels == g]) for g in range(n_g)]
    p = npoint.map(uv)
    R = _rz(rz)
    A = np.zeros((2 * len(p), 2 * n_g + 2))
    for k in range(len(p)):
        A[2 * k: 2 * k + 2, 2 * labels[k]: 2 * labels[k] + 2] = np.eye(2)
        A[2 * k: 2 * k + 2, 2 * n_g:] = R[k]
    sol, *_ = np.linalg.lstsq(A, p.reshape(-1), rcond=None)
    res = (p.reshape(-1) - A @ sol).reshape(-1, 2)
    dof = A.shape[0] - A.shape[1]
    sigma2 = float(np.sum(res * res) / dof) if dof > 0 else float("nan")
    pinv = np.asarray(np.linalg.pinv(A), dtype=np.float64)
    cov = sigma2 * np.linalg.inv(A.T @ A) + _map_covariance(npoint, uv, pinv)
    o = np.asarray(sol[2 * n_g:], dtype=np.float64)
    Hinv = np.linalg.inv(npoint.H)
    positions = []
    for g in range(n_g):
        sel = labels == g
        c = sol[2 * g: 2 * g + 2]
        c_px = apply_h(Hinv, c[None])[0]
        if npoint.camera is not None:  # the map undistorted first: distort the centre back
            cam = npoint.camera
            c_px = cam.normalized_to_pixels(cam.distort(cam.pixels_to_normalized(c_px[None])))[0]
        kc, kr = _kasa(p[sel])
        rg = res[sel]
        positions.append({"flange_mm": fl[sel][0].tolist(), "angles": int(sel.sum()), "arc_deg": arcs[g],
                          "centre_mm": c.tolist(), "centre_px": c_px.tolist(),
                          "flange_axis_vs_reported_mm": float(np.linalg.norm(c - fl[sel][0])),
                          "rms_mm": float(np.sqrt(np.mean(np.sum(rg * rg, axis=1)))),
                          "free_circle": {"centre_mm": kc.tolist(), "radius_mm": kr}})
    rms = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
    return ToolCentreResult(o, np.asarray(cov[2 * n_g:, 2 * n_g:], dtype=np.float64), rms, positions, res)


def _map_H(model: str, H: F64, p: F64) -> F64:
    """``H`` with the N-point model's parameters ``p`` (np.json's covariance order: homography the
    first 8 entries of ``H / H[2, 2]``, affine the top two rows, similarity ``a, b, tx, ty``)."""
    if model == "homography":
        return np.append(p[:8], 1.0).reshape(3, 3)
    if model == "affine":
        return np.vstack([p[:6].reshape(2, 3), [0.0, 0.0, 1.0]])
    ref = np.diag([1.0, -1.0 if np.linalg.det(H[:2, :2]) < 0 else 1.0])
    out = np.eye(3)
    out[:2, :2] = np.array([[p[0], -p[1]], [p[1], p[0]]]) @ ref
    out[:2, 2] = p[2:4]
    return out


def _map_params(model: str, H: F64) -> F64:
    if model == "homography":
        return (H / H[2, 2]).ravel()[:8].copy()
    if model == "affine":
        return H[:2, :].ravel().copy()
    B = H[:2, :2] @ np.diag([1.0, -1.0 if np.linalg.det(H[:2, :2]) < 0 else 1.0])
    return np.array([B[0, 0], B[1, 0], H[0, 2], H[1, 2]])


def _map_covariance(npoint: NPointResult, uv: F64, pinv: F64) -> F64:
    """Covariance of the solution from the N-point map's parameter covariance (first order)."""
    cov_p = np.asarray(npoint.cov_params, dtype=np.float64)
    p0 = _map_params(npoint.model, npoint.H)
    if cov_p.shape != (len(p0), len(p0)) or not np.all(np.isfinite(cov_p)):
        return np.zeros((pinv.shape[0], pinv.shape[0]))  # an np.json without a usable covariance
    xy = npoint.camera.undistort_points(uv) if npoint.camera is not None else uv
    J = np.zeros((2 * len(uv), len(p0)))
    for k in range(len(p0)):
        h = 1e-6 * max(1.0, abs(p0[k]))
        pp, pm = p0.copy(), p0.copy()
        pp[k] += h
        pm[k] -= h
        J[:, k] = (apply_h(_map_H(npoint.model, npoint.H, pp), xy)
                   - apply_h(_map_H(npoint.model, npoint.H, pm), xy)).ravel() / (2 * h)
    S = pinv @ J
    return np.asarray(S @ cov_p @ S.T, dtype=np.float64)


def flange_pose_for_feature(T_base_feature: ArrayLike, offset_tool_m: ArrayLike) -> F64:
    """``T_base_tool`` (flange) that puts the tool's feature at ``T_base_feature``.

    ``offset_tool_m`` is the feature's position in the flange frame (metres), e.g. from
    :func:`tool_offset_vector`; ``T_base_feature`` carries the flange orientation wanted (the
    recipe's rotation). ``T_base_feature = T_base_tool · Trans(offset)``, so
    ``T_base_tool = T_base_feature · Trans(-offset)``.
    """
    T = np.asarray(T_base_feature, dtype=np.float64)
    return np.asarray(T @ make_transform(np.eye(3), -np.asarray(offset_tool_m, dtype=np.float64)), dtype=np.float64)


def tool_offset_vector(offset_mm: ArrayLike, R_base_tool_rz0: ArrayLike) -> F64:
    """The fitted offset ``(dx, dy)`` (mm, tool x/y along base x/y at ``rz = 0``) as a vector in the
    flange frame (metres), given the flange orientation at ``rz = 0`` (``Rz(-rz) · R_base_tool``)."""
    o = np.asarray(offset_mm, dtype=np.float64).reshape(2)
    R0 = np.asarray(R_base_tool_rz0, dtype=np.float64)
    return np.asarray(R0.T @ np.array([o[0], o[1], 0.0]) * 1e-3, dtype=np.float64)
