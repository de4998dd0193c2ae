"""Chessboard corner refinement by point symmetry (issue 26 item 2): corners of boards whose lines
run along the pixel axes are found to < 0.03 px, the window follows the local square and stays in
the image, an edge is not taken for a corner; the image-noise estimate is not quantised."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.camera_model import CameraModel
from calibration.detect import detect
from calibration.detect.chessboard import refine_saddle_converged
from calibration.detect.corner_symmetry import (
    MIN_HALF_WINDOW_PX,
    SYMMETRY_WINDOW_SQUARES,
    half_windows_px,
    local_square_px,
    refine_symmetric,
)
from calibration.detect.precision import image_noise_grey
from calibration.targets import Chessboard
from drivers.sim.imaging import Imaging, PlanarObject, render
from tests.calibration.conftest import plate_pose, truth_uv


def _square_wave_integral(x: np.ndarray, origin: float, square_px: float) -> np.ndarray:
    """Antiderivative of the +-1 square wave that is +1 on [origin, origin + square_px)."""
    t = (x - origin) / square_px
    k = np.floor(t)
    f = t - k
    return square_px * np.where(k % 2 == 0, f, 1.0 - f)


def _axis_aligned_board(origin: tuple[float, float], square_px: float, size: int = 160, blur_px: float = 0.8,
                        noise: float = 2.0, seed: int = 0) -> np.ndarray:
    """An axis-aligned checkerboard filling the image, its corners at ``origin + k * square_px``
    (u, v, pixel-centre convention), each pixel the exact mean over its area (the pattern is
    separable), then blurred, noisy, 8-bit."""
    c = np.arange(size, dtype=np.float64)
    a = [_square_wave_integral(c + 0.5, o, square_px) - _square_wave_integral(c - 0.5, o, square_px)
         for o in origin]
    img = (120.0 + 80.0 * np.outer(a[1], a[0])).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def test_axis_aligned_corners_are_found_to_three_hundredths_of_a_pixel() -> None:
    origin, square = (30.3, 29.6), 20.0
    grey = _axis_aligned_board(origin, square)
    k = np.arange(5, dtype=np.float64)
    truth = np.array([[origin[0] + a * square, origin[1] + b * square] for b in k for a in k])
    start = truth + np.random.default_rng(1).uniform(-0.6, 0.6, truth.shape)
    hw = half_windows_px(grey.shape, start, np.full(len(start), square))
    out, ok = refine_symmetric(grey, start, hw)
    assert ok.all()
    err = np.hypot(*(out - truth).T)
    assert np.sqrt(np.mean(err**2)) < 0.03, err
    # the small-window saddle fit these corners were refined with before is worse here
    saddle, _ = refine_saddle_converged(grey, start, 3)
    assert np.sqrt(np.mean(np.sum((saddle - truth) ** 2, axis=1))) > np.sqrt(np.mean(err**2))


def test_detector_on_a_rendered_board_with_lines_along_the_pixel_axes(camera: CameraModel) -> None:
    board = Chessboard(9, 6, 20.0)
    T = plate_pose(board, 0.45, 0.0, roll_deg=0.0)            # frontal, lines on the pixel axes
    # 32 x 32 samples per edge pixel: the renderer's box supersampling puts an edge that runs along
    # the pixel axes up to 1 / (2 n) px off (RMS corner error 0.03 px at its default n = 8 here)
    grey = render(camera, [PlanarObject(T, board.reflectance)], Imaging(noise_sigma=2.0, blur_sigma_px=0.8),
                  np.random.default_rng(3), supersample=32)
    det = detect(grey, board)
    assert det.found, det.reason
    err = np.hypot(*(det.uv - truth_uv(camera, board, T)[det.ids]).T)
    assert np.sqrt(np.mean(err**2)) < 0.03
    assert err.max() < 0.1


def test_window_follows_the_local_square_and_stays_inside_the_image() -> None:
    G = np.stack(np.meshgrid(np.arange(4) * 30.0 + 40, np.arange(3) * 10.0 + 40), axis=2)   # 30 x 10 px cells
    sq = local_square_px(G)
    assert np.allclose(sq, 10.0)
    hw = half_windows_px((100, 200), G.reshape(-1, 2), sq)
    assert np.all(hw == int(SYMMETRY_WINDOW_SQUARES * 10))
    near = half_windows_px((100, 200), np.array([[3.0, 50.0], [100.0, 50.0]]), np.array([50.0, 50.0]))
    assert near[0] == MIN_HALF_WINDOW_PX and near[1] == int(SYMMETRY_WINDOW_SQUARES * 50)


def test_a_straight_edge_is_not_a_corner() -> None:
    grey = np.full((61, 61), 120, dtype=np.uint8)
    grey[:, 30:] = 200
    _, ok = refine_symmetric(grey, np.array([[30.0, 30.0]]), 8)
    assert not ok[0]


def test_noise_estimate_is_not_quantised() -> None:
    """Noise sigma and 1.1 sigma on the same board: the estimates differ by about 10 %, and each
    is close to the truth (a median of 8-bit responses moved in steps of 0.25 grey)."""
    rng = np.random.default_rng(4)
    base = _axis_aligned_board((30.0, 30.0), 20.0, noise=0.0, blur_px=1.0).astype(np.float64)
    box = np.array([[20.0, 20.0], [140.0, 140.0]])
    est = []
    for sigma in (2.0, 2.2):
        img = np.clip(np.round(base + rng.normal(0.0, sigma, base.shape)), 0, 255).astype(np.uint8)
        est.append(image_noise_grey(img, box))
        assert abs(est[-1] / sigma - 1.0) < 0.1, est
    assert 1.05 < est[1] / est[0] < 1.15, est
