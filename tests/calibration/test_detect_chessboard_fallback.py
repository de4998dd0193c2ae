"""The chessboard finder's upsampled fallback pass, on OpenCV's real stereo sample views it is for."""

from __future__ import annotations

import numpy as np

from calibration.detect import detect, read_image
from calibration.detect.chessboard import FIND_PASSES, find_corners_opencv
from calibration.intrinsics import calibrate
from calibration.targets import Chessboard
from tests.calibration.conftest import DATA

STEREO = DATA / "opencv_stereo_9x6"
RECOVERED = ("left04.jpg", "left05.jpg")
"""Views that neither the plain nor the exhaustive pass finds, the upsampled one does."""


def test_the_fallback_finds_views_the_first_passes_miss_and_their_corners_fit_like_the_rest() -> None:
    board = Chessboard(9, 6, 1000.0)
    greys = {f.name: read_image(f) for f in sorted(STEREO.glob("left*.jpg"))}
    for name in RECOVERED:
        # the first two passes alone miss it (the reason for the third)
        assert find_corners_opencv(greys[name], 9, 6, passes=FIND_PASSES[:2]) is None
    dets = [detect(g, board, name) for name, g in greys.items()]
    assert all(d.found for d in dets), [d.reason for d in dets if not d.found]
    res = calibrate(dets, board, "opencv5", jackknife=False)
    rms = {v.image: v.rms_px for v in res.views}
    median = float(np.median(list(rms.values())))
    for name in RECOVERED:
        assert rms[name] < 1.5 * median, (name, rms[name], median)   # refined as well as the others
