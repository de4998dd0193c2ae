"""The saddle refinement reaches a corner that OpenCV's sector detector left more than a pixel
off (blurred outer corners of defocused views), and says whether it converged."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.detect.chessboard import refine_saddle_converged


def _corner_image(centre: tuple[float, float], blur_px: float, size: int = 41) -> np.ndarray:
    """A blurred checker corner (four squares) at sub-pixel ``centre`` (u, v), 8-bit."""
    s = 8
    big = size * s
    u = (np.arange(big) + 0.5) / s - 0.5 - centre[0]
    v = (np.arange(big) + 0.5) / s - 0.5 - centre[1]
    uu, vv = np.meshgrid(u, v)
    hi = np.where(uu * vv > 0, 200.0, 40.0).astype(np.float32)
    img = cv2.resize(hi, (size, size), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), blur_px)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def test_a_corner_1_3_px_off_is_refined_and_converges() -> None:
    true_uv = np.array([20.3, 19.6])
    grey = _corner_image((true_uv[0], true_uv[1]), blur_px=1.6)
    start = true_uv + np.array([1.1, -0.7])          # 1.3 px off, as OpenCV left the blurred ones
    out, conv = refine_saddle_converged(grey, start[None, :])
    assert conv[0]
    assert np.hypot(*(out[0] - true_uv)) < 0.1


def test_a_window_without_a_saddle_does_not_converge() -> None:
    grey = np.full((41, 41), 120, dtype=np.uint8)
    grey[:, 20:] = 200                                  # a straight edge, no corner
    out, conv = refine_saddle_converged(grey, np.array([[20.0, 20.0]]))
    assert not conv[0]
