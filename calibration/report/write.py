"""``write_report``: the HTML report of an intrinsics calibration, as the CLI writes it.

The page is the one the service serves for a stored calibration (:mod:`calibration.report.html`);
here it is built from the solver's result directly, with thumbnails of the images when their files
are given.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from calibration.intrinsics import IntrinsicsResult
from calibration.report import camera as rc
from calibration.report.html import camera_html
from calibration.report.page import page

THUMB_WIDTH_PX = 340  # twice the drawn width (sharp on high-DPI screens)


def thumbnail_jpeg(path: str | Path, width_px: int = THUMB_WIDTH_PX) -> bytes | None:
    """A small JPEG of an image file (None when it cannot be read)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        return None
    h, w = img.shape[:2]
    small = cv2.resize(img, (width_px, max(1, int(round(h * width_px / w)))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 70])
    return bytes(buf) if ok else None


def from_result(res: IntrinsicsResult, images: dict[str, bytes] | None = None) -> rc.CameraReport:
    """The report's data from a fresh calibration (its own residuals, coverage and uncertainty map)."""
    views = [rc.ViewData(v.image, v.used, float(v.rms_px) if np.isfinite(v.rms_px) else None, v.reason, v.outlier,
                         np.asarray(v.uv, dtype=np.float64).reshape(-1, 2),
                         np.asarray(v.residuals_px, dtype=np.float64).reshape(-1, 2), (images or {}).get(v.image))
             for v in res.views]
    return rc.CameraReport(res.camera, res.to_json(), views, res.coverage, res.uncertainty_map_px)


def write_report(res: IntrinsicsResult, path: str | Path, cross_validation: dict[str, Any] | None = None,
                 image_files: Sequence[str | Path] | None = None) -> None:
    """Write the report; ``image_files``: the calibration images (for the per-view thumbnails)."""
    images: dict[str, bytes] = {}
    names = {v.image for v in res.views}
    for f in image_files or []:
        if Path(f).name in names:
            thumb = thumbnail_jpeg(f)
            if thumb is not None:
                images[Path(f).name] = thumb
    cam = res.camera
    title = f"Camera calibration: {cam.model}, {cam.width} x {cam.height} px"
    Path(path).write_text(page(title, camera_html(from_result(res, images), cross_validation)))
