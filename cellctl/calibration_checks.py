"""Can a calibration file's camera project its own image, and is its covariance a covariance?

``POST /calibrations`` and ``cellctl store add`` refuse (422, ``invalid_calibration``) what the pick
would only fail on later (issue 34: a distortion of 1e300 was stored, then a pick answered 500):

- ``K`` must be ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``: upper triangular, last row exactly
  ``0 0 1``, ``fx`` and ``fy`` positive and at most :data:`MAX_FOCAL_PX`, their ratio within
  :data:`MAX_ASPECT`, the skew ``|s|`` at most :data:`MAX_SKEW_RATIO` x ``fx`` (real sensors have
  square pixels on a rectangular grid: a skew of a few percent is already a broken calibration);
- every distortion coefficient at most :data:`MAX_DIST_COEFF` in magnitude, and the lens model
  must map its own image: a 9 x 9 grid of pixels over the image's central half (:data:`CORE`: half
  its width and height around the centre) is undistorted to rays and projected back, and every
  pixel must come back finite and within :data:`ROUND_TRIP_PX` (a model whose distortion folds over
  there cannot be used at all). The same test over the whole image, corners included, only adds a
  note when it fails: a polynomial fitted on views that did not reach the corners often folds over
  there, and such a camera still serves the region it was calibrated on.
- a covariance (the camera's ``parameters.covariance``, a hand-eye's ``uncertainty.covariance``, an
  n-point's ``covariance``) must be square, symmetric and positive semi-definite (smallest
  eigenvalue not below ``-1e-9`` x the largest).
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np

from cellctl.calibration_file import CalibrationFileError

MAX_FOCAL_PX: Final = 1e6
MAX_ASPECT: Final = 5.0
"""fy / fx (and fx / fy) at most this."""
MAX_SKEW_RATIO: Final = 0.05
"""|K[0][1]| / fx at most this."""
MAX_DIST_COEFF: Final = 1e4
ROUND_TRIP_PX: Final = 0.5
GRID: Final = 9
CORE: Final = 0.5
"""The share of the image's width and height (around its centre) that a camera must map both ways."""


class CheckFailed(CalibrationFileError):
    """A check failed; the message says what and what to do (the caller adds which file and field)."""


def check_intrinsics(K_in: Any, dist_in: Any, model: str, width: int, height: int) -> list[str]:
    """Raise :class:`CheckFailed` unless the camera ``(K, dist)`` is upper triangular and projects its image;
    answers notes (the image's corners beyond what the model maps)."""
    from calibration.camera_model import CameraModel

    K = np.asarray(K_in, dtype=np.float64)
    dist = np.asarray(dist_in, dtype=np.float64).ravel()
    if K.shape != (3, 3):
        raise CheckFailed("K must be a 3x3 matrix [[fx,0,cx],[0,fy,cy],[0,0,1]]")
    if K[1, 0] != 0.0 or K[2, 0] != 0.0 or K[2, 1] != 0.0 or K[2, 2] != 1.0:
        raise CheckFailed(f"K must be upper triangular with last row 0 0 1 ([[fx,s,cx],[0,fy,cy],[0,0,1]]); its "
                          f"lower part is {K[1, 0]:g}, [{K[2, 0]:g} {K[2, 1]:g} {K[2, 2]:g}]")
    fx, fy, skew = float(K[0, 0]), float(K[1, 1]), float(K[0, 1])
    if not (0 < fx <= MAX_FOCAL_PX and 0 < fy <= MAX_FOCAL_PX):
        raise CheckFailed(f"the focal lengths fx {fx:g}, fy {fy:g} px must be positive and at most {MAX_FOCAL_PX:g} px")
    if max(fx / fy, fy / fx) > MAX_ASPECT:
        raise CheckFailed(f"fx {fx:g} and fy {fy:g} px differ by more than a factor {MAX_ASPECT:g}: no sensor has "
                          "such pixels")
    if abs(skew) > MAX_SKEW_RATIO * fx:
        raise CheckFailed(f"the skew K[0][1] {skew:g} px is beyond {MAX_SKEW_RATIO:g} x fx ({MAX_SKEW_RATIO * fx:g} "
                          "px): sensor rows and columns are perpendicular; calibrate again (skew 0)")
    if dist.size and float(np.abs(dist).max()) > MAX_DIST_COEFF:
        raise CheckFailed(f"a distortion coefficient ({float(np.abs(dist).max()):g}) is beyond {MAX_DIST_COEFF:g} in "
                          "magnitude: no lens distorts so; calibrate again")
    camera = CameraModel(model, width, height, K, dist)  # type: ignore[arg-type]
    core = _round_trip_fails(camera, CORE)
    if core is not None:
        raise CheckFailed(f"the camera cannot project its own image: the pixel ({core[0]:.0f}, {core[1]:.0f}) does not "
                          f"map back to itself through the distortion (off by more than {ROUND_TRIP_PX:g} px); the "
                          "distortion coefficients are wrong for this image size; calibrate again")
    edge = _round_trip_fails(camera, 1.0)
    if edge is not None:
        return [f"the distortion model does not map the image's outer part (pixel ({edge[0]:.0f}, {edge[1]:.0f})) "
                "both ways: it folds over beyond the region the calibration covered; use the camera there only "
                "after a calibration whose views reach the corners"]
    return []


def _round_trip_fails(camera: Any, share: float) -> tuple[float, float] | None:
    """The first pixel of a grid over ``share`` of the image (around its centre) that does not come back to
    itself through unproject -> project (None: all do)."""
    w, h = camera.width, camera.height
    lo_u, hi_u = (w - 1) * (1 - share) / 2, (w - 1) * (1 + share) / 2
    lo_v, hi_v = (h - 1) * (1 - share) / 2, (h - 1) * (1 + share) / 2
    uu, vv = np.meshgrid(np.linspace(lo_u, hi_u, GRID), np.linspace(lo_v, hi_v, GRID))
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    with np.errstate(all="ignore"):
        back = camera.project(camera.unproject(uv))
    err = np.linalg.norm(back - uv, axis=1)
    bad = ~np.isfinite(err) | (err > ROUND_TRIP_PX)
    if not bad.any():
        return None
    u, v = uv[int(np.argmax(bad))]
    return float(u), float(v)


def check_covariance(value: Any, what: str) -> None:
    """Raise :class:`CheckFailed` unless ``value`` is a square, symmetric, positive semi-definite matrix."""
    try:
        C = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CheckFailed(f"{what} must be a square matrix of numbers") from None
    if C.size == 0:
        return
    if C.ndim != 2 or C.shape[0] != C.shape[1]:
        raise CheckFailed(f"{what} must be a square matrix, got shape {list(C.shape)}")
    if not np.isfinite(C).all():
        raise CheckFailed(f"{what} holds a number that is not finite")
    scale = float(np.abs(C).max())
    if scale == 0.0:
        return
    if float(np.abs(C - C.T).max()) > 1e-9 * scale:
        raise CheckFailed(f"{what} is not symmetric: a covariance is")
    eig = np.linalg.eigvalsh(C)
    if float(eig.min()) < -1e-9 * float(np.abs(eig).max()):
        raise CheckFailed(f"{what} is not positive semi-definite (an eigenvalue is {float(eig.min()):.3g}): a "
                          "variance cannot be negative; the file was edited or damaged")
