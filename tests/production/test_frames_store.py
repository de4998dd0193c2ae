"""The failed cycles' frame folder: lossless round trip, bounded by count and by size (oldest first)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cellctl.pick.frames import StoredFrame
from cellctl.production.frames import FailureFrames, frame_name


def frame(seed: int) -> StoredFrame:
    pixels = np.random.default_rng(seed).integers(0, 256, (120, 160), dtype=np.uint8)  # noise: ~19 kB as PNG
    match = {"u_px": 40.5, "v_px": 60.25, "angle_deg": 12.0, "score": 0.9, "part": "bracket"}
    return StoredFrame(seed, pixels, [match], [np.array([[[1.0, 2.0], [3.5, 4.25]]])], None)


def test_a_kept_frame_reads_back_as_written(tmp_path: Path) -> None:
    frames = FailureFrames(tmp_path, max_count=10, max_bytes=10**9)
    f = frame(1)
    assert frames.keep(7, 3, f, {"n": 3, "result": "grip_failed"})
    back = frames.load(7, 3)
    assert np.array_equal(back.pixels, f.pixels) and back.matches == f.matches and back.frame_id == 1
    assert np.allclose(back.contours[0], f.contours[0])
    with pytest.raises(KeyError, match="no frame of run 7 cycle 4"):
        frames.load(7, 4)


def test_the_oldest_go_first_by_count_and_by_size(tmp_path: Path) -> None:
    frames = FailureFrames(tmp_path, max_count=3, max_bytes=10**9)
    for n in range(1, 6):
        assert frames.keep(1, n, frame(n), {"n": n})
    assert frames.names() == [frame_name(1, n) for n in (3, 4, 5)]
    # A later run's frames sort after every earlier run's (run ids are zero-padded).
    assert frames.keep(12, 1, frame(9), {"n": 1})
    assert frames.names() == [frame_name(1, 4), frame_name(1, 5), frame_name(12, 1)]
    one = sum(p.stat().st_size for p in tmp_path.glob(f"{frame_name(12, 1)}.*"))
    by_size = FailureFrames(tmp_path, max_count=100, max_bytes=int(2.5 * one))
    assert by_size.keep(13, 1, frame(10), {"n": 1})
    assert by_size.names() == [frame_name(12, 1), frame_name(13, 1)]
    assert not FailureFrames(tmp_path / "none", max_count=0, max_bytes=10**9).keep(1, 1, frame(1), {})
    assert not (tmp_path / "none").exists()
