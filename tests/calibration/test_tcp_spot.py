"""The tool's spot: a saturated disk ringed by dark, found sub-pixel; everything else refused clearly."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.detect import SpotNotFound, find_spot


def _disk_image(centres: list[tuple[float, float]], r_px: float = 9.0, ring: bool = True,
                size: tuple[int, int] = (320, 240), background: float = 200.0) -> np.ndarray:
    """Disks drawn by area coverage (8x8 sub-samples per pixel), on a ring of grey 20 when ``ring``."""
    s = 8
    img = np.full((size[1], size[0]), background)
    for cu, cv in centres:
        x0, x1 = max(int(cu - 2 * r_px) - 2, 0), min(int(cu + 2 * r_px) + 3, size[0])
        y0, y1 = max(int(cv - 2 * r_px) - 2, 0), min(int(cv + 2 * r_px) + 3, size[1])
        yy, xx = np.mgrid[0:(y1 - y0) * s, 0:(x1 - x0) * s]
        d = np.hypot(x0 + (xx + 0.5) / s - 0.5 - cu, y0 + (yy + 0.5) / s - 0.5 - cv)
        sub = np.repeat(np.repeat(img[y0:y1, x0:x1], s, axis=0), s, axis=1)
        if ring:
            sub[d <= 2 * r_px] = 20.0
        sub[d <= r_px] = 255.0
        img[y0:y1, x0:x1] = sub.reshape(y1 - y0, s, x1 - x0, s).mean(axis=(1, 3))
    return np.round(img).astype(np.uint8)


@pytest.mark.parametrize("centre", [(100.0, 80.0), (160.37, 120.81), (201.5, 99.25)])
def test_the_centre_is_sub_pixel(centre: tuple[float, float]) -> None:
    spot = find_spot(_disk_image([centre]))
    assert abs(spot.u_px - centre[0]) < 0.02 and abs(spot.v_px - centre[1]) < 0.02
    assert spot.radius_px == pytest.approx(9.0, abs=0.1)
    assert spot.ring_dn == pytest.approx(20.0, abs=1.0)


def test_a_colour_image_works_the_same() -> None:
    img = _disk_image([(120.4, 90.6)])
    spot = find_spot(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    assert abs(spot.u_px - 120.4) < 0.02 and abs(spot.v_px - 90.6) < 0.02


def test_nothing_saturated_is_refused_with_the_reason() -> None:
    for img in (np.zeros((240, 320), np.uint8), np.full((240, 320), 128, np.uint8)):
        with pytest.raises(SpotNotFound, match="no region at or above 250 DN"):
            find_spot(img)


def test_a_saturated_area_without_a_dark_ring_is_not_the_spot() -> None:
    img = _disk_image([(160.0, 120.0)], ring=False, background=200.0)
    with pytest.raises(SpotNotFound, match="none ringed by dark"):
        find_spot(img)


def test_two_spots_are_refused_naming_both() -> None:
    with pytest.raises(SpotNotFound, match=r"2 spots ringed by dark at \(80, 60\), \(240, 180\)"):
        find_spot(_disk_image([(80.0, 60.0), (240.0, 180.0)]))


def test_a_spot_cut_by_the_border_is_skipped() -> None:
    with pytest.raises(SpotNotFound):
        find_spot(_disk_image([(3.0, 120.0)]))
    spot = find_spot(_disk_image([(3.0, 120.0), (200.0, 100.0)]))  # the whole one is found
    assert abs(spot.u_px - 200.0) < 0.02


def test_not_an_image_is_refused() -> None:
    with pytest.raises(SpotNotFound, match="grey or BGR"):
        find_spot(np.zeros((4, 4, 4, 4), np.uint8))
