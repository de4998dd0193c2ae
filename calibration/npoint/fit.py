"""N-point (jog-to-mark) image→robot mapping: affine, similarity or homography.

Pairs ``(u_px, v_px) → (x_mm, y_mm)``: an image point and the robot point the tool was jogged
to. Three models, all written as a 3x3 ``H`` mapping ``[u, v, 1]`` to ``[x_mm, y_mm, 1]`` (up to
scale):

- ``similarity``: rotation, uniform scale, translation **and, when the data need it, a
  reflection** (a camera looking down at the robot's table usually sees the robot's XY plane
  mirrored; OpenCV's ``estimateAffinePartial2D`` cannot represent that — docs/field-notes.md).
  Fitted in closed form (Umeyama) with and without a reflection; the better one is kept and
  ``reflection`` says which.
- ``affine``: HALCON's ``vector_to_hom_mat2d``: linear least squares.
- ``homography``: ``cv2.findHomography`` (all points, least squares + LM); exact for a tilted
  camera over a plane once lens distortion is removed (``camera=`` undistorts first).

With no model given, each model's leave-one-out (LOO) error is computed and the simplest model
whose LOO RMS is within 25 % of the best is chosen (similarity < affine < homography). The
predicted 1-σ error over the field (max and RMS over the convex hull of the marks) comes from
the parameter covariance, with the noise level estimated from the fit's residuals.

``affine`` in the result holds HALCON's ``hom_mat2d_to_affine_par`` parameters of the affine fit,
for our ``(u, v) → (x, y)`` matrix: ``A = R(phi) · Slant_y(theta) · diag(sx, sy)`` with
``Slant_y(theta) = [[1, -sin theta], [0, cos theta]]``; sx, sy > 0; a reflection shows as
``|theta| > 90°``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration import CalibrationError
from calibration.camera_model import CameraModel

MODELS: Final[tuple[str, ...]] = ("similarity", "affine", "homography")
MIN_POINTS: Final[dict[str, int]] = {"similarity": 2, "affine": 3, "homography": 4}
N_PARAMS: Final[dict[str, int]] = {"similarity": 4, "affine": 6, "homography": 8}
SELECTION_TOLERANCE: Final = 1.25

F64 = NDArray[np.float64]


class NPointError(CalibrationError):
    """The N-point pairs cannot give a mapping (too few, duplicate or collinear marks, bad model)."""


def apply_h(H: ArrayLike, uv: ArrayLike) -> F64:
    """Map (N, 2) points through a 3x3 homogeneous matrix."""
    M = np.asarray(H, dtype=np.float64)
    p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    q = p @ M[:2, :2].T + M[:2, 2]
    w = p @ M[2, :2] + M[2, 2]
    return q / w[:, None]


def _fit_affine(uv: F64, xy: F64) -> F64:
    A = np.column_stack([uv, np.ones(len(uv))])
    sol = np.linalg.lstsq(A, xy, rcond=None)[0]
    H = np.eye(3)
    H[:2, :] = sol.T
    return H


def _umeyama(src: F64, dst: F64) -> tuple[F64, float]:
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    s0, d0 = src - ms, dst - md
    U, S, Vt = np.linalg.svd(d0.T @ s0 / len(src))
    D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    var = np.mean(np.sum(s0 * s0, axis=1))
    scale = float(np.trace(np.diag(S) @ D) / var)
    H = np.eye(3)
    H[:2, :2] = scale * R
    H[:2, 2] = md - scale * R @ ms
    res = float(np.sum((apply_h(H, src) - dst) ** 2))
    return H, res


def _fit_similarity(uv: F64, xy: F64) -> F64:
    H_plain, r_plain = _umeyama(uv, xy)
    flip = np.diag([1.0, -1.0, 1.0])
    H_ref, r_ref = _umeyama(uv * [1.0, -1.0], xy)
    H_ref = H_ref @ flip
    return H_plain if r_plain <= r_ref else H_ref


def _fit_homography(uv: F64, xy: F64) -> F64:
    H, _ = cv2.findHomography(uv.reshape(-1, 1, 2), xy.reshape(-1, 1, 2), 0)
    if H is None:
        raise NPointError("homography fit failed (degenerate mark layout)")
    return np.asarray(H, dtype=np.float64) / H[2, 2]


FITTERS: Final[dict[str, Callable[[F64, F64], F64]]] = {
    "similarity": _fit_similarity, "affine": _fit_affine, "homography": _fit_homography,
}


def fit_model(model: str, uv: F64, xy: F64) -> F64:
    """3x3 ``H`` of ``model`` fitted to (N, 2) pixels and (N, 2) robot mm."""
    return FITTERS[model](uv, xy)


def _params(model: str, H: F64) -> F64:
    if model == "homography":
        return (H / H[2, 2]).ravel()[:8].copy()
    if model == "affine":
        return H[:2, :].ravel().copy()
    # similarity: (a, b) with the 2x2 block [[a, -b], [b, a]] · diag(1, ±1), then tx, ty
    ref = np.linalg.det(H[:2, :2]) < 0
    B = H[:2, :2] @ np.diag([1.0, -1.0 if ref else 1.0])
    return np.array([B[0, 0], B[1, 0], H[0, 2], H[1, 2], 1.0 if ref else 0.0])


def _from_params(model: str, p: F64) -> F64:
    if model == "homography":
        return np.append(p[:8], 1.0).reshape(3, 3)
    if model == "affine":
        return np.vstack([p[:6].reshape(2, 3), [0.0, 0.0, 1.0]])
    a, b, tx, ty, ref = p
    H = np.eye(3)
    H[:2, :2] = np.array([[a, -b], [b, a]]) @ np.diag([1.0, -1.0 if ref > 0.5 else 1.0])
    H[:2, 2] = [tx, ty]
    return H


def _jacobian(model: str, H: F64, uv: F64) -> F64:
    """d(mapped point)/d(params): (2N, n_params), central differences."""
    p = _params(model, H)
    n = N_PARAMS[model]
    J = np.zeros((2 * len(uv), n))
    for k in range(n):
        h = 1e-6 * max(1.0, abs(p[k]))
        pp, pm = p.copy(), p.copy()
        pp[k] += h
        pm[k] -= h
        J[:, k] = (apply_h(_from_params(model, pp), uv) - apply_h(_from_params(model, pm), uv)).ravel() / (2 * h)
    return J


def affine_par(H: ArrayLike) -> dict[str, float]:
    """HALCON ``hom_mat2d_to_affine_par`` of the affine part of ``H`` (see the module docstring)."""
    M = np.asarray(H, dtype=np.float64)
    M = M / M[2, 2]
    a, b, c, d = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
    phi = float(np.arctan2(c, a))
    sx = float(np.hypot(a, c))
    cp, sp = np.cos(phi), np.sin(phi)
    b1, d1 = cp * b + sp * d, -sp * b + cp * d
    sy = float(np.hypot(b1, d1))
    theta = float(np.arctan2(-b1, d1))
    return {"sx": sx, "sy": sy, "phi_deg": float(np.degrees(phi)), "theta_deg": float(np.degrees(theta)),
            "tx_mm": float(M[0, 2]), "ty_mm": float(M[1, 2])}


def check_layout(uv: F64, xy: F64) -> None:
    """Reject too few, non-finite, duplicate or collinear marks with a message naming them."""
    if uv.shape != xy.shape or uv.ndim != 2 or uv.shape[1] != 2:
        raise NPointError("pairs need (u_px, v_px) and (x_mm, y_mm) for every mark")
    n = len(uv)
    if n < 3:
        raise NPointError(f"N-point needs at least 3 marks (got {n}); 9 marks spread over the field are typical")
    if not (np.all(np.isfinite(uv)) and np.all(np.isfinite(xy))):
        raise NPointError("pairs contain NaN or infinity")
    for name, pts, tol, unit in (("image", uv, 0.5, "px"), ("robot", xy, 0.01, "mm")):
        d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
        i, j = np.nonzero(np.triu(d < tol, 1))
        if i.size:
            raise NPointError(f"duplicate marks: pairs {int(i[0]) + 1} and {int(j[0]) + 1} have the same {name} "
                              f"point (within {tol} {unit}); jog to distinct marks")
        c = pts - pts.mean(axis=0)
        s = np.linalg.svd(c, compute_uv=False)
        if s[1] < 1e-3 * s[0]:
            raise NPointError(f"the marks' {name} points are (nearly) collinear (spread ratio {s[1] / s[0]:.2g}); "
                              "use marks spread over the field in both directions, not along a line")


def loo_errors_mm(model: str, uv: F64, xy: F64) -> F64:
    """Leave-one-out error (mm) of each mark: the map fitted without it, evaluated at its pixel
    (``uv`` as the map takes them: undistorted when the map has a camera)."""
    err = np.zeros(len(uv))
    for i in range(len(uv)):
        m = np.arange(len(uv)) != i
        H = fit_model(model, uv[m], xy[m])
        err[i] = float(np.linalg.norm(apply_h(H, uv[i : i + 1])[0] - xy[i]))
    return err


def _hull_grid(uv: F64, n: int = 40) -> F64:
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    g = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n)), axis=-1).reshape(-1, 2)
    contour = hull.reshape(-1, 1, 2).astype(np.float32)
    inside = np.array([cv2.pointPolygonTest(contour, (float(u), float(v)), False) >= 0 for u, v in g])
    return np.vstack([g[inside], hull])


@dataclass
class NPointResult:
    model: str
    H: F64
    rms_mm: float
    residuals_mm: F64
    sigma_mm: float
    """Per-coordinate noise estimated from the residuals."""
    cov_params: F64
    loo_rms_mm: dict[str, float]
    field_sigma_mm: dict[str, Any]
    affine: dict[str, float]
    reflection: bool
    camera: CameraModel | None = None
    notes: list[str] = field(default_factory=list)

    def map(self, uv_px: ArrayLike) -> F64:
        """Pixels (raw, as the camera delivers them) to robot mm."""
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        if self.camera is not None:
            uv = self.camera.undistort_points(uv)
        return apply_h(self.H, uv)

    def map_covariance(self, uv_px: ArrayLike, pixel_sigma_px: float = 0.0) -> F64:
        """(N, 2, 2) covariance (mm²) of mapped points: model parameters plus pixel noise."""
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        if self.camera is not None:
            uv = self.camera.undistort_points(uv)
        J = _jacobian(self.model, self.H, uv).reshape(len(uv), 2, -1)
        cov = np.einsum("nik,kl,njl->nij", J, self.cov_params, J)
        if pixel_sigma_px > 0:
            h = 1e-3
            du = (apply_h(self.H, uv + [h, 0]) - apply_h(self.H, uv - [h, 0])) / (2 * h)
            dv = (apply_h(self.H, uv + [0, h]) - apply_h(self.H, uv - [0, h])) / (2 * h)
            Jp = np.stack([du, dv], axis=2)
            cov = cov + pixel_sigma_px**2 * np.einsum("nik,njk->nij", Jp, Jp)
        return np.asarray(cov)

    def to_json(self) -> dict[str, Any]:
        """``np.json`` (docs/cli.md) plus diagnostics."""
        out: dict[str, Any] = {
            "model": self.model,
            "H": self.H.tolist(),
            "rms_mm": self.rms_mm,
            "affine": self.affine,
            "reflection": self.reflection,
            "residuals_mm": self.residuals_mm.tolist(),
            "sigma_mm": self.sigma_mm,
            "loo_rms_mm": self.loo_rms_mm,
            "field_sigma_mm": self.field_sigma_mm,
            "covariance": self.cov_params.tolist(),
            "notes": self.notes,
        }
        if self.camera is not None:
            out["camera"] = self.camera.to_dict()
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> NPointResult:
        """Read an ``np.json`` written by ``to_json``."""
        try:
            model = str(d["model"])
            H = np.asarray(d["H"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise NPointError(f"not an n-point calibration (needs 'model' and 'H'): {exc}") from exc
        if model not in MODELS or H.shape != (3, 3):
            raise NPointError(f"n-point calibration: model must be one of {MODELS} and H 3x3")
        n = N_PARAMS[model]
        cov = np.asarray(d.get("covariance", np.zeros((n, n))), dtype=np.float64)
        cam = CameraModel.from_dict(d["camera"]) if "camera" in d else None
        return cls(model, H, float(d.get("rms_mm", 0.0)), np.asarray(d.get("residuals_mm", []), dtype=np.float64),
                   float(d.get("sigma_mm", 0.0)), cov, dict(d.get("loo_rms_mm", {})),
                   dict(d.get("field_sigma_mm", {})), dict(d.get("affine", affine_par(H))),
                   bool(d.get("reflection", np.linalg.det(H[:2, :2]) < 0)), cam, list(d.get("notes", [])))


def fit_npoint(uv_px: ArrayLike, xy_mm: ArrayLike, model: str | None = None,
               camera: CameraModel | None = None) -> NPointResult:
    """Fit the image→robot map from N pairs; choose the model by leave-one-out when ``model`` is None."""
    uv_raw = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    xy = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
    if model is not None and model not in MODELS:
        raise NPointError(f"model must be one of {MODELS}, got {model!r}")
    check_layout(uv_raw, xy)
    uv = camera.undistort_points(uv_raw) if camera is not None else uv_raw
    n = len(uv)
    notes: list[str] = []
    loo: dict[str, float] = {}
    for m in MODELS:
        if n >= MIN_POINTS[m] + 1 and 2 * (n - 1) > N_PARAMS[m]:
            loo[m] = float(np.sqrt(np.mean(loo_errors_mm(m, uv, xy) ** 2)))
    if model is None:
        if not loo:
            raise NPointError(f"{n} marks are too few to choose a model by leave-one-out; name the model "
                              "(affine, similarity or homography) or "
                              "jog to more marks (9 are typical)")
        best = min(loo.values())
        model = next(m for m in MODELS if m in loo and loo[m] <= SELECTION_TOLERANCE * best)
        notes.append(f"model chosen by leave-one-out: {model} (simplest within {SELECTION_TOLERANCE - 1:.0%} of "
                     f"the best LOO RMS {best:.4g} mm)")
    if n < MIN_POINTS[model]:
        raise NPointError(f"model {model} needs at least {MIN_POINTS[model]} marks, got {n}")
    H = fit_model(model, uv, xy)
    res = apply_h(H, uv) - xy
    r = np.linalg.norm(res, axis=1)
    npar = N_PARAMS[model]
    dof = 2 * n - npar
    sigma = float(np.sqrt(np.sum(res**2) / dof)) if dof > 0 else float("nan")
    J = _jacobian(model, H, uv)
    if dof > 0:
        cov = sigma**2 * np.linalg.pinv(J.T @ J)
    else:
        cov = np.full((npar, npar), np.nan)
        notes.append("exactly determined: no redundancy, no uncertainty estimate; jog to more marks")
    grid = _hull_grid(uv)
    Jg = _jacobian(model, H, grid).reshape(len(grid), 2, -1)
    var = np.einsum("nik,kl,nil->n", Jg, cov, Jg)
    field_sigma = {"max": float(np.sqrt(np.max(var))), "rms": float(np.sqrt(np.mean(var))),
                   "over": "convex hull of the marks"}
    aff = affine_par(_fit_affine(uv, xy))
    reflection = bool(np.linalg.det(H[:2, :2]) < 0)
    if model == "similarity" and reflection:
        notes.append("the map contains a reflection (image y down, robot y up is typical); the similarity includes it")
    return NPointResult(model, H, float(np.sqrt(np.mean(r**2))), r, sigma,
                        np.asarray(cov, dtype=np.float64), loo, field_sigma, aff, reflection,
                        camera, notes)
