"""ChArUco corners through OpenCV's ``cv2.aruco.CharucoDetector`` (partial boards allowed).

Ids are OpenCV's ChArUco corner ids, which are the ids of ``calibration.targets.Charuco.points()``.
A detection needs at least ``MIN_CORNERS`` interpolated corners (enough for a homography);
fewer is reported not found with the number seen. Each corner carries its 1-sigma uncertainty
(``calibration.detect.precision``).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detect.precision import CORNER_WINDOW_SIGMA_PX, gradient_sigma_px
from calibration.observations import Detection
from calibration.targets import Charuco

MIN_CORNERS = 4


def _detector(target: Charuco) -> Any:
    board = target.cv_board()
    charuco_params = cv2.aruco.CharucoParameters()
    detector_params = cv2.aruco.DetectorParameters()
    detector_params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.CharucoDetector(board, charuco_params, detector_params)


def detect_charuco(grey: NDArray[np.uint8], target: Charuco, image_name: str = "") -> Detection:
    """Visible ChArUco corners of ``target`` with OpenCV's ids, or a reason why none were found."""
    corners, ids, _marker_corners, marker_ids = _detector(target).detectBoard(grey)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    n = 0 if ids is None else len(ids)
    if n < MIN_CORNERS:
        if n_markers == 0:
            why = f"no {target.dictionary} markers found"
        else:
            why = f"{n_markers} markers but only {n} ChArUco corners found (need {MIN_CORNERS})"
        return Detection(image_name, False, reason=f"{why}: board not visible, too small or blurred, "
                         "or a different dictionary/board size")
    ids_a = np.asarray(ids, dtype=np.int64).reshape(-1)
    uv = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    order = np.argsort(ids_a)
    uv = uv[order]
    return Detection(image_name, True, ids=ids_a[order], uv=uv,
                     uv_sigma_px=gradient_sigma_px(grey, uv, CORNER_WINDOW_SIGMA_PX))
