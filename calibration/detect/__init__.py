"""Target detection: image in, target points with ids and sub-pixel ``(u, v)`` out.

``detect(image, target)`` dispatches on the target type:

- chessboard: OpenCV's ``findChessboardCornersSB`` (``calibration.detect.chessboard``),
- charuco: OpenCV's ``CharucoDetector``, partial boards allowed (``.charuco``),
- circle_grid: OpenCV's ``findCirclesGrid`` (``.circle_grid``),
- circle_plate: our own HALCON-style plate detector (``.circle_plate``).

Beside them: ``conic`` (the perspective bias of a circular mark's imaged centre, which the
solvers correct for) and ``tool_spot`` (``find_spot``: the tool's saturated spot that the
tool-centre step looks for).

Errors: bad *input* (an empty or non-image array, an unreadable or corrupt file, a target type
that cannot be seen in an image) raises ``DetectionError`` (a ``ValueError``) with one clear
line; a valid image in which the target is not found returns ``Detection(found=False,
reason=...)``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration import CalibrationError
from calibration.detect.conic import circle_centre_bias_px, conic_centres_normalized
from calibration.detect.quality import image_quality
from calibration.detect.tool_spot import Spot, SpotNotFound, find_spot
from calibration.observations import Detection
from calibration.targets import Charuco, Chessboard, CircleGrid, CirclePlate, Points3D, Target

__all__ = [
    "Detection", "DetectionError", "Spot", "SpotNotFound", "circle_centre_bias_px", "conic_centres_normalized",
    "detect", "detect_file", "find_spot", "read_image", "to_grey",
]


class DetectionError(CalibrationError):
    """The input to detection is unusable: empty/corrupt image, or a target that has no image pattern."""


def to_grey(image: NDArray[np.generic], image_name: str = "image") -> NDArray[np.uint8]:
    """A 2D uint8 grey image from a grey, BGR or BGRA array (8 or 16 bit, or float in [0, 1] / [0, 255])."""
    a = np.asarray(image)
    if a.size == 0 or a.ndim not in (2, 3) or min(a.shape[:2]) < 8:
        raise DetectionError(f"{image_name}: empty or too small image (shape {a.shape}); give a 2D grey or "
                             "colour image of at least 8x8 pixels")
    if a.ndim == 3:
        if a.shape[2] == 1:
            a = a[:, :, 0]
        elif a.shape[2] in (3, 4):
            a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        else:
            raise DetectionError(f"{image_name}: image has {a.shape[2]} channels; give grey, BGR or BGRA")
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if a.dtype == np.uint16:
        return (a.astype(np.float64) / 257.0 + 0.5).astype(np.uint8)
    if np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer):
        f = a.astype(np.float64)
        if not np.all(np.isfinite(f)):
            raise DetectionError(f"{image_name}: image contains NaN or infinity")
        scale = 255.0 if np.issubdtype(a.dtype, np.floating) and f.max() <= 1.0 else 1.0
        return np.clip(np.rint(f * scale), 0, 255).astype(np.uint8)
    raise DetectionError(f"{image_name}: unsupported pixel type {a.dtype}")


def detect(image: NDArray[np.generic], target: Target, image_name: str = "") -> Detection:
    """Find ``target`` in ``image``; ``found=False`` with a reason when it is not there."""
    name = image_name or "image"
    if isinstance(target, Points3D):
        raise DetectionError("points3d targets have no printed pattern to detect; give their image points "
                             "as obs.csv (id,u_px,v_px) instead")
    grey = to_grey(image, name)
    det: Detection
    if isinstance(target, Chessboard):
        from calibration.detect.chessboard import detect_chessboard

        det = detect_chessboard(grey, target, image_name)
    elif isinstance(target, Charuco):
        from calibration.detect.charuco import detect_charuco

        det = detect_charuco(grey, target, image_name)
    elif isinstance(target, CircleGrid):
        from calibration.detect.circle_grid import detect_circle_grid

        det = detect_circle_grid(grey, target, image_name)
    elif isinstance(target, CirclePlate):
        from calibration.detect.circle_plate import detect_circle_plate

        det = detect_circle_plate(grey, target, image_name)
    else:  # pragma: no cover - the Target union is exhaustive
        raise DetectionError(f"cannot detect targets of type {type(target).__name__}")
    det.image_size = (int(grey.shape[1]), int(grey.shape[0]))
    if det.found:
        det.quality = image_quality(grey, det.uv)
    return det


def read_image(path: str | Path) -> NDArray[np.uint8]:
    """Read an image file as grey uint8; ``DetectionError`` if it is missing, empty or corrupt."""
    p = Path(path)
    if not p.is_file():
        raise DetectionError(f"{p}: no such image file")
    if p.stat().st_size == 0:
        raise DetectionError(f"{p}: image file is empty (0 bytes)")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # our one-line error says it all
    try:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None or img.size == 0:
        raise DetectionError(f"{p}: cannot decode image (corrupt or not a PNG/JPEG/BMP/TIFF file)")
    return to_grey(img, str(p))


def detect_file(path: str | Path, target: Target) -> Detection:
    """``detect`` on an image file; the Detection's ``image`` is the file name."""
    return detect(read_image(path), target, Path(path).name)
