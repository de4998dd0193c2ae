"""Failure frames show the plant's parts and their records the cell's poses: files 0600, folders 0700
(whatever the umask), and a failures folder an older cellctl left 0755 is tightened (issue 34, item 6)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np

from cellctl.pick.frames import StoredFrame
from cellctl.production.frames import FailureFrames


def mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def frame() -> StoredFrame:
    return StoredFrame(7, np.full((24, 32), 90, np.uint8), [], [], "no match")


def test_failure_frames_are_written_0600_in_0700_folders(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        root = tmp_path / "data" / "production" / "failures"
        frames = FailureFrames(root, 5, 10_000_000)
        assert frames.keep(3, 1, frame(), {"n": 1, "result": "empty"})
    finally:
        os.umask(old)
    files = sorted(root.iterdir())
    assert [p.name for p in files] == ["run000000003-cycle000001.json", "run000000003-cycle000001.png"]
    assert all(mode(p) == 0o600 for p in files), {p.name: oct(mode(p)) for p in files}
    for folder in (root, root.parent, root.parent.parent):
        assert mode(folder) == 0o700, (folder, oct(mode(folder)))
    assert frames.load(3, 1).frame_id == 7


def test_an_open_failures_folder_of_ours_is_tightened(tmp_path: Path) -> None:
    root = tmp_path / "failures"
    root.mkdir(mode=0o755)
    os.chmod(root, 0o755)
    (root / "run000000001-cycle000001.png").write_bytes(b"old")
    frames = FailureFrames(root, 5, 10_000_000)
    assert frames.keep(1, 2, frame(), {"n": 2})
    assert mode(root) == 0o700
    assert mode(root / "run000000001-cycle000002.png") == 0o600
