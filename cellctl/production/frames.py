"""The frames of failed production cycles, kept on disk beside their records.

The service keeps only its last frames in memory (``cellctl.pick.frames.FrameCache``); a failed
cycle's frame must outlive that, so the run writes it here: the picture as a lossless PNG (the
camera's pixels as grabbed) and a JSON file with what was found on it (the matches, their model
contours in image pixels, the reason when nothing was found) and the cycle's record. Files are
named ``run<run_id>-cycle<n>`` (zero-padded: their names sort oldest first). The folder is
bounded (``cell.yaml`` ``production:``): when a new frame takes it over the count or the size, the
oldest frames are deleted first, so the newest failures are the ones kept.

A frame shows the plant's parts and its record the cell's poses: files are written 0600 in folders
0700 (``cellctl.store.files``), whatever the process umask; a failures folder of ours found more open
(an older cellctl made it 0755) is tightened to 0700 when the next frame is written.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cellctl.config import CellConfig
from cellctl.paths import data_dir
from cellctl.pick.frames import StoredFrame
from cellctl.store.files import open_private, private_dir

log = logging.getLogger(__name__)

KEPT_RESULTS = frozenset({"grip_failed", "skipped", "empty", "none_pickable", "vision_failed", "not_recognized"})
"""Cycle results whose frame is kept on disk: the failures, and ``empty`` (an area called empty
while parts lie there is a vision failure only its frame shows)."""


def frame_name(run_id: int, n: int) -> str:
    return f"run{run_id:09d}-cycle{n:06d}"


class FailureFrames:
    """A bounded folder of failed cycles' frames (thread-safe)."""

    def __init__(self, root: Path, max_count: int, max_bytes: int) -> None:
        self.root = root
        self.max_count = max_count
        self.max_bytes = max_bytes
        self._lock = threading.Lock()

    @classmethod
    def for_config(cls, config: CellConfig) -> FailureFrames:
        p = config.production
        root = (Path(p.failure_frames_dir) if p.failure_frames_dir
                else data_dir() / "production" / config.cell_id / "failures")
        return cls(root, p.failure_frames_max_count, int(p.failure_frames_max_mb * 1e6))

    def keep(self, run_id: int, n: int, frame: StoredFrame, record: dict[str, Any]) -> bool:
        """Write the cycle's frame and record, then prune; False when nothing is kept (a bound of 0, or
        the write failed: logged)."""
        if self.max_count == 0 or self.max_bytes == 0:
            return False
        name = frame_name(run_id, n)
        ok, png = cv2.imencode(".png", frame.pixels)
        if not ok:
            log.error("production: frame %s of run %s cycle %s could not be encoded", frame.frame_id, run_id, n)
            return False
        meta = {"run_id": run_id, "n": n, "frame_id": frame.frame_id, "reason": frame.reason,
                "matches": frame.matches,
                "contours_px": [np.round(np.asarray(c, dtype=np.float64), 2).tolist() for c in frame.contours],
                "record": record}
        try:
            with self._lock:
                _private_folder(self.root)
                _write_atomic(self.root / f"{name}.json", json.dumps(meta, allow_nan=False).encode())
                _write_atomic(self.root / f"{name}.png", png.tobytes())
                self._prune()
        except OSError as exc:
            log.error("production: the frame of run %s cycle %s could not be kept in %s: %s", run_id, n, self.root,
                      exc)
            return False
        return True

    def load(self, run_id: int, n: int) -> StoredFrame:
        """The kept frame of the cycle (``KeyError`` when none is kept, or it was pruned)."""
        name = frame_name(run_id, n)
        png, meta_path = self.root / f"{name}.png", self.root / f"{name}.json"
        with self._lock:
            try:
                raw = np.frombuffer(png.read_bytes(), dtype=np.uint8)
                meta = json.loads(meta_path.read_text())
            except FileNotFoundError:
                raise KeyError(f"no frame of run {run_id} cycle {n} is kept in {self.root} (failed cycles' "
                               f"frames are kept, the newest {self.max_count} at most)") from None
        pixels = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
        if pixels is None:
            raise KeyError(f"the kept frame {png} cannot be read (damaged)")
        contours = [np.asarray(c, dtype=np.float64).reshape(-1, 2, 2) for c in meta["contours_px"]]
        return StoredFrame(int(meta["frame_id"]), pixels, list(meta["matches"]), contours, meta["reason"])

    def names(self) -> list[str]:
        """The kept frames' names, oldest first."""
        with self._lock:
            return self._names()

    def _names(self) -> list[str]:
        if not self.root.is_dir():
            return []
        return sorted(p.stem for p in self.root.glob("run*-cycle*.png"))

    def _prune(self) -> None:
        """Delete the oldest frames until the folder is within both bounds (called under the lock)."""
        names = self._names()
        sizes = {n: sum(_size(self.root / f"{n}{ext}") for ext in (".png", ".json")) for n in names}
        total = sum(sizes.values())
        while names and (len(names) > self.max_count or total > self.max_bytes):
            oldest = names.pop(0)
            for ext in (".png", ".json"):
                (self.root / f"{oldest}{ext}").unlink(missing_ok=True)
            total -= sizes[oldest]


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def _private_folder(root: Path) -> None:
    """``root`` and its missing parents made 0700; ``root`` itself tightened to 0700 when this user owns it."""
    private_dir(root)
    st = root.stat()
    if st.st_uid == os.geteuid() and st.st_mode & 0o077:
        os.chmod(root, 0o700)


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to a new 0600 file and rename it over ``path`` (a reader never sees half a frame)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.unlink(missing_ok=True)
    with os.fdopen(open_private(tmp), "wb") as f:
        f.write(data)
    os.replace(tmp, path)
