"""Detection entry points: dispatch and bad input (calibration.detect)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.detect import DetectionError, detect, detect_file, to_grey
from calibration.targets import CirclePlate, Points3D


def test_empty_image_is_a_clear_error() -> None:
    with pytest.raises(DetectionError, match="empty"):
        detect(np.zeros((0, 0), dtype=np.uint8), CirclePlate(7, 7, 12.5, 6.25), "x.png")


def test_points3d_cannot_be_detected() -> None:
    t = Points3D({i: (float(i), 0.0, float(i % 2)) for i in range(6)})
    with pytest.raises(DetectionError, match="points3d"):
        detect(np.full((50, 50), 128, dtype=np.uint8), t)


@pytest.mark.parametrize("content, word", [(b"", "empty"), (b"not a png at all" * 10, "cannot decode")])
def test_corrupt_files_are_clear_errors(tmp_path: Path, content: bytes, word: str) -> None:
    p = tmp_path / "bad.png"
    p.write_bytes(content)
    with pytest.raises(DetectionError, match=word):
        detect_file(p, CirclePlate(7, 7, 12.5, 6.25))
    with pytest.raises(DetectionError, match="no such"):
        detect_file(tmp_path / "missing.png", CirclePlate(7, 7, 12.5, 6.25))


def test_blank_image_is_not_found_with_a_reason() -> None:
    det = detect(np.full((120, 160, 3), 200, dtype=np.uint8), CirclePlate(7, 7, 12.5, 6.25), "blank")
    assert not det.found
    assert "no frame" in det.reason
    assert det.image_size == (160, 120)


def test_to_grey_accepts_colour_and_16_bit() -> None:
    assert to_grey(np.full((10, 10, 3), 255, dtype=np.uint8)).max() == 255
    assert to_grey(np.full((10, 10), 65535, dtype=np.uint16)).max() == 255
    with pytest.raises(DetectionError, match="channels"):
        to_grey(np.zeros((10, 10, 5), dtype=np.uint8))
