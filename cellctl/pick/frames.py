"""The last frames the pick flow used, kept to serve them annotated (``GET /frames/{id}.png``)."""

from __future__ import annotations

import itertools
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray


@dataclass
class StoredFrame:
    frame_id: int
    pixels: NDArray[Any]
    matches: list[dict[str, Any]] = field(default_factory=list)
    """Each with u_px, v_px, angle_deg, score, part, reachable."""


class FrameCache:
    """A bounded, thread-safe cache of recent frames with their matches."""

    def __init__(self, capacity: int = 20) -> None:
        self._frames: OrderedDict[int, StoredFrame] = OrderedDict()
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self.capacity = capacity

    def add(self, pixels: NDArray[Any], matches: list[dict[str, Any]]) -> int:
        with self._lock:
            fid = next(self._ids)
            self._frames[fid] = StoredFrame(fid, pixels, matches)
            while len(self._frames) > self.capacity:
                self._frames.popitem(last=False)
            return fid

    def get(self, frame_id: int) -> StoredFrame:
        with self._lock:
            f = self._frames.get(frame_id)
        if f is None:
            raise KeyError(f"frame {frame_id} is not kept any more (the last {self.capacity} are)")
        return f

    def latest(self) -> StoredFrame | None:
        with self._lock:
            return next(reversed(self._frames.values()), None)


def annotate(frame: StoredFrame) -> NDArray[np.uint8]:
    """The frame in colour with each match drawn: a cross at the reference point, the part's x axis,
    its rank, part name and score; green when reachable, red when not."""
    img = frame.pixels
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    for rank, m in enumerate(frame.matches, start=1):
        colour = (0, 200, 0) if m.get("reachable", True) else (0, 0, 230)
        u, v = float(m["u_px"]), float(m["v_px"])
        a = np.radians(float(m["angle_deg"]))
        p = (int(round(u)), int(round(v)))
        cv2.drawMarker(out, p, colour, cv2.MARKER_CROSS, 24, 2)
        q = (int(round(u + 40 * np.cos(a))), int(round(v - 40 * np.sin(a))))  # CCW on screen
        cv2.arrowedLine(out, p, q, colour, 2, tipLength=0.25)
        label = f"{rank} {m.get('part', '')} {float(m['score']):.2f}"
        cv2.putText(out, label, (p[0] + 10, p[1] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2)
    return out
