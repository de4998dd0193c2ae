"""Camera models: pinhole intrinsics with OpenCV or division-model lens distortion.

Frames and units (docs/conventions.md): points in the camera frame are metres, x right,
y down, z forward; pixels are ``(u, v)`` with ``(0, 0)`` the centre of the top-left pixel.

Models:
- ``opencv5``: OpenCV's ``(k1, k2, p1, p2, k3)``.
- ``opencv8``: OpenCV's rational model ``(k1, k2, p1, p2, k3, k4, k5, k6)``.
- ``division``: HALCON's single-kappa model in *normalized* coordinates: with ``(x_d, y_d)`` the
  distorted normalized point and ``r_d^2 = x_d^2 + y_d^2``, the undistorted point is
  ``(x_d, y_d) / (1 + kappa * r_d^2)``. Unlike OpenCV's models it has a closed-form inverse in
  both directions, which is why it is implemented here rather than borrowed from OpenCV.
- ``fisheye4``: the Kannala-Brandt equidistant model (OpenCV's ``cv2.fisheye``, ROS's
  ``equidistant``) ``(k1, k2, k3, k4)``: with ``theta = atan(r)`` the angle of the ray to the
  optical axis, the distorted normalized radius is ``theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6
  + k4 theta^8)``. Its polynomial is in the *angle*, not in the pinhole radius that grows without
  bound towards 90 deg, so it describes wide and fisheye lenses that opencv5/8 fold over on
  (rays within 90 deg of the axis: the ``[x, y, 1]`` rays of ``unproject``).
- ``splined``: mrcal's splined stereographic model (``calibration.splined``): the stereographic
  projection plus a cubic B-spline correction over the stereographic plane; ``dist`` is
  ``[Nx, Ny, fov_x_deg, dx (Nx*Ny), dy (Nx*Ny)]`` (its length depends on the grid). For lenses no
  parametric model fits, calibrated from many views (``calibration.intrinsics.splined_solver``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Final, Literal, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calibration import CalibrationError
from calibration import splined as _splined

ModelName = Literal["opencv5", "opencv8", "division", "fisheye4", "splined"]
MODEL_NAMES: Final[tuple[str, ...]] = ("opencv5", "opencv8", "division", "fisheye4", "splined")
N_DIST: Final[dict[str, int]] = {"opencv5": 5, "opencv8": 8, "division": 1, "fisheye4": 4}
"""Distortion coefficient counts of the parametric models (``splined``'s depends on its grid)."""

Points2 = NDArray[np.float64]


class CameraModelError(CalibrationError):
    """A camera model description is malformed (unknown model, wrong coefficient count, ...)."""


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics ``K`` (pixels), distortion ``dist`` of ``model`` and the image size (pixels)."""

    model: ModelName
    width: int
    height: int
    K: NDArray[np.float64]
    dist: NDArray[np.float64] = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        if self.model not in MODEL_NAMES:
            raise CameraModelError(f"unknown camera model {self.model!r}; use one of {MODEL_NAMES}")
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraModelError("K must be a finite 3x3 matrix with positive fx and fy")
        d = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if self.model == "splined":
            try:
                _splined.parse(d)
            except ValueError as exc:
                raise CameraModelError(f"model splined: {exc}") from exc
        elif d.size != (n := N_DIST[self.model]):
            raise CameraModelError(f"model {self.model} needs {n} distortion coefficients, got {d.size}")
        if self.width <= 0 or self.height <= 0:
            raise CameraModelError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", d)

    # -- basic pieces -------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """Image size ``(width, height)`` in pixels."""
        return (self.width, self.height)

    def normalized_to_pixels(self, xy: ArrayLike) -> Points2:
        """Distorted normalized coordinates to pixels through ``K`` (skew honoured)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        K = self.K
        u = K[0, 0] * p[:, 0] + K[0, 1] * p[:, 1] + K[0, 2]
        v = K[1, 1] * p[:, 1] + K[1, 2]
        return np.column_stack([u, v])

    def pixels_to_normalized(self, uv: ArrayLike) -> Points2:
        """Pixels to distorted normalized coordinates through ``K^-1``."""
        p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        K = self.K
        y = (p[:, 1] - K[1, 2]) / K[1, 1]
        x = (p[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.column_stack([x, y])

    # -- distortion ---------------------------------------------------------------------------
    def distort(self, xy: ArrayLike) -> Points2:
        """Ideal normalized coordinates to distorted normalized coordinates."""
        return distort_normalized(self.model, self.dist, xy)

    def undistort_normalized(self, xy_d: ArrayLike) -> Points2:
        """Distorted normalized coordinates to ideal normalized coordinates."""
        return undistort_normalized(self.model, self.dist, xy_d)

    # -- projection ---------------------------------------------------------------------------
    def project(self, points_cam: ArrayLike) -> Points2:
        """(N, 3) points in the camera frame (metres) to (N, 2) pixels.

        Points at or behind the camera (z <= 0) project to NaN.
        """
        P = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = P[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        return self.normalized_to_pixels(self.distort(xy))

    def unproject(self, uv: ArrayLike) -> NDArray[np.float64]:
        """(N, 2) pixels to (N, 3) ray directions ``[x, y, 1]`` in the camera frame."""
        xy = self.undistort_normalized(self.pixels_to_normalized(uv))
        return np.column_stack([xy, np.ones(len(xy))])

    def undistort_points(self, uv: ArrayLike, K_new: ArrayLike | None = None) -> Points2:
        """Pixels of this camera to pixels of a distortion-free pinhole with ``K_new`` (default K)."""
        xy = self.undistort_normalized(self.pixels_to_normalized(uv))
        ideal = CameraModel("opencv5", self.width, self.height,
                            np.asarray(self.K if K_new is None else K_new, dtype=np.float64))
        return ideal.normalized_to_pixels(xy)

    def undistortion_maps(
        self, K_new: ArrayLike | None = None, size: tuple[int, int] | None = None
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """``(map_u, map_v)`` for ``cv2.remap``: for each pixel of the ideal pinhole image with
        ``K_new`` (default K) and ``size`` (default this size), where to sample this camera's image."""
        w, h = size if size is not None else self.size
        Kn = np.asarray(self.K if K_new is None else K_new, dtype=np.float64)
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        y = (vv.ravel() - Kn[1, 2]) / Kn[1, 1]
        x = (uu.ravel() - Kn[0, 2] - Kn[0, 1] * y) / Kn[0, 0]
        uv = self.normalized_to_pixels(self.distort(np.column_stack([x, y])))
        return (uv[:, 0].reshape(h, w).astype(np.float32), uv[:, 1].reshape(h, w).astype(np.float32))

    # -- files --------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The ``cam.json`` core keys (docs/cli.md)."""
        return {
            "model": self.model,
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraModel:
        """Read the core keys of a ``cam.json`` (or a scene's camera block)."""
        missing = [k for k in ("model", "width", "height", "K", "dist") if k not in d]
        if missing:
            raise CameraModelError(f"camera description lacks {', '.join(missing)}")
        return cls(
            model=cast(ModelName, d["model"]),
            width=int(d["width"]),
            height=int(d["height"]),
            K=np.asarray(d["K"], dtype=np.float64),
            dist=np.asarray(d["dist"], dtype=np.float64),
        )

    def with_size(self, width: int, height: int) -> CameraModel:
        """The same lens on a scaled image (K scaled by the size ratio)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return CameraModel(self.model, width, height, K, self.dist.copy())

    # -- HALCON -------------------------------------------------------------------------------
    def to_halcon(self, pixel_pitch_m: float) -> dict[str, float]:
        """HALCON ``area_scan_division`` parameters of a division model.

        ``pixel_pitch_m`` is the sensor cell width Sx in metres (HALCON needs it to split f/Sx).
        Returns Focus (m), Kappa (1/m^2), Sx, Sy (m), Cx, Cy (px), ImageWidth, ImageHeight.
        """
        if self.model != "division":
            raise CameraModelError("only the division model converts to HALCON's area_scan_division")
        f_m = self.fx * pixel_pitch_m
        sy = f_m / self.fy
        return {
            "Focus": f_m,
            "Kappa": float(self.dist[0]) / f_m**2,
            "Sx": pixel_pitch_m,
            "Sy": sy,
            "Cx": self.cx,
            "Cy": self.cy,
            "ImageWidth": float(self.width),
            "ImageHeight": float(self.height),
        }

    @classmethod
    def from_halcon(cls, p: dict[str, float]) -> CameraModel:
        """Division model from HALCON's ``area_scan_division`` parameters (see ``to_halcon``)."""
        f = float(p["Focus"])
        K = np.array([[f / p["Sx"], 0.0, p["Cx"]], [0.0, f / p["Sy"], p["Cy"]], [0.0, 0.0, 1.0]])
        return cls("division", int(p["ImageWidth"]), int(p["ImageHeight"]), K,
                   np.array([float(p["Kappa"]) * f**2]))


def distort_normalized(model: str, dist: ArrayLike, xy: ArrayLike) -> Points2:
    """Ideal normalized points to distorted normalized points under ``model``."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    x, y = p[:, 0], p[:, 1]
    r2 = x * x + y * y
    if model == "division":
        kappa = d[0]
        if kappa == 0.0:
            return p.copy()
        # r_u = r_d / (1 + kappa r_d^2)  =>  r_d = 2 r_u / (1 + sqrt(1 - 4 kappa r_u^2)).
        disc = 1.0 - 4.0 * kappa * r2
        with np.errstate(invalid="ignore"):
            scale = 2.0 / (1.0 + np.sqrt(disc))
        scale[disc < 0] = np.nan
        return p * scale[:, None]
    if model == "splined":
        return _splined.distort(d, p)
    if model == "fisheye4":
        r = np.sqrt(r2)
        th = np.arctan(r)
        t2 = th * th
        thd = th * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(r > 1e-12, thd / np.where(r > 1e-12, r, 1.0), 1.0)
        return p * scale[:, None]
    k1, k2, p1, p2, k3 = d[:5]
    k4, k5, k6 = d[5:8] if d.size >= 8 else (0.0, 0.0, 0.0)
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([xd, yd])


def undistort_normalized(model: str, dist: ArrayLike, xy_d: ArrayLike, iterations: int = 20) -> Points2:
    """Distorted normalized points to ideal normalized points under ``model``.

    Division: closed form. OpenCV models: Newton's method on the 2x2 distortion Jacobian
    (finite differences), to 1e-9 (about 1e-6 px); more precise than ``cv2.undistortPoints``' fixed 5
    fixed-point steps on strongly distorted lenses.
    """
    q = np.asarray(xy_d, dtype=np.float64).reshape(-1, 2)
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    if model == "division":
        r2 = np.sum(q * q, axis=1)
        return q / (1.0 + d[0] * r2)[:, None]
    if model == "fisheye4":
        return _undistort_fisheye4(d, q)
    if model == "splined":
        return _splined.undistort(d, q)
    if not np.any(d):
        return q.copy()
    p = _opencv_initial_guess(d, q)
    h = 1e-7
    for _ in range(iterations):
        f = distort_normalized(model, d, p) - q
        if np.nanmax(np.abs(f), initial=0.0) < 1e-9:  # 1e-9 normalized is ~1e-6 px
            break
        fx = (distort_normalized(model, d, p + [h, 0.0]) - distort_normalized(model, d, p - [h, 0.0])) / (2 * h)
        fy = (distort_normalized(model, d, p + [0.0, h]) - distort_normalized(model, d, p - [0.0, h])) / (2 * h)
        a, b, c, e = fx[:, 0], fy[:, 0], fx[:, 1], fy[:, 1]
        det = a * e - b * c
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (e * f[:, 0] - b * f[:, 1]) / det
            dy = (-c * f[:, 0] + a * f[:, 1]) / det
        p = p - np.column_stack([dx, dy])
    return p


def _opencv_initial_guess(dist: NDArray[np.float64], xy_d: Points2) -> Points2:
    """OpenCV's iterative undistortion (fast, C++) as the starting point for Newton's method."""
    import cv2

    finite = np.all(np.isfinite(xy_d), axis=1)
    out = xy_d.copy()
    if np.any(finite):
        pts = xy_d[finite].reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
        und = cv2.undistortPointsIter(pts, np.eye(3), dist, None, None, crit).reshape(-1, 2)
        out[finite] = und
    return out


def _undistort_fisheye4(d: NDArray[np.float64], q: Points2) -> Points2:
    """Kannala-Brandt: the ray angle ``theta`` from the distorted radius by Newton's method on the
    odd polynomial (to 1e-12 rad), then the pinhole radius ``tan(theta)``. A radius the model
    cannot produce (its polynomial turns back, or theta would reach 90 deg) gives NaN."""
    rd = np.hypot(q[:, 0], q[:, 1])
    th = np.minimum(rd, 1.5)
    for _ in range(30):
        t2 = th * th
        f = th * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3])))) - rd
        df = 1 + t2 * (3 * d[0] + t2 * (5 * d[1] + t2 * (7 * d[2] + t2 * 9 * d[3])))
        with np.errstate(divide="ignore", invalid="ignore"):
            step = f / df
        th = th - step
        if np.nanmax(np.abs(step), initial=0.0) < 1e-12:
            break
    t2 = th * th
    slope = 1 + t2 * (3 * d[0] + t2 * (5 * d[1] + t2 * (7 * d[2] + t2 * 9 * d[3])))
    bad = ~np.isfinite(th) | (th < 0) | (th >= np.pi / 2 - 1e-6) | (slope <= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(rd > 1e-12, np.tan(th) / np.where(rd > 1e-12, rd, 1.0), 1.0)
    scale[bad] = np.nan
    return q * scale[:, None]
