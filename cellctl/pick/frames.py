"""The last frames the pick flow used, kept to serve them annotated (``GET /frames/{id}.png``).

Each frame keeps its matches (as the pick answer gives them), the model contour of each match at
its pose (``match_contours``), and the reason when nothing was found; ``annotate`` draws them.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from cellctl.pick.model import PartModel


@dataclass
class StoredFrame:
    frame_id: int
    pixels: NDArray[Any]
    matches: list[dict[str, Any]] = field(default_factory=list)
    """Each with u_px, v_px, angle_deg, score, part, reachable."""
    contours: list[NDArray[np.float64]] = field(default_factory=list)
    """Per match (same order), the model's edge segments ``(N, 2, 2)`` at its pose, image pixels."""
    reason: str | None = None
    """Why nothing was found (``FindResult.reason()``), shown on the frame."""


class FrameCache:
    """A bounded, thread-safe cache of recent frames with their matches."""

    def __init__(self, capacity: int = 20) -> None:
        self._frames: OrderedDict[int, StoredFrame] = OrderedDict()
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self.capacity = capacity

    def add(self, pixels: NDArray[Any], matches: list[dict[str, Any]],
            contours: list[NDArray[np.float64]] | None = None, reason: str | None = None) -> int:
        with self._lock:
            fid = next(self._ids)
            self._frames[fid] = StoredFrame(fid, pixels, matches, list(contours or []), reason)
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


def match_contours(models: Sequence[PartModel], matches: Sequence[dict[str, Any]]) -> list[NDArray[np.float64]]:
    """Each match's model contour at its pose (the model named by the match's ``part``, else the first)."""
    by_name = {m.name: m for m in models}
    out = []
    for mt in matches:
        model = by_name.get(str(mt.get("part")), models[0] if models else None)
        if model is None:
            out.append(np.zeros((0, 2, 2)))
            continue
        out.append(model.contour(float(mt["u_px"]), float(mt["v_px"]), float(mt["angle_deg"]),
                                 float(mt.get("scale", 1.0)), bool(mt.get("mirrored", False))))
    return out


def _draw_contour(out: NDArray[np.uint8], seg: NDArray[np.float64], colour: tuple[int, int, int]) -> None:
    if len(seg) == 0:
        return
    shift = 4  # sub-pixel line ends (cv2 fixed point)
    pts = np.rint(seg * (1 << shift)).astype(np.int32).reshape(-1, 2, 1, 2)
    cv2.polylines(out, list(pts), False, colour, 1, cv2.LINE_AA, shift)


def annotate(frame: StoredFrame) -> NDArray[np.uint8]:
    """The frame in colour with each match drawn: its model contour at its pose, a cross at the
    reference point, the part's x axis, the recipe's grasp (the open fingers and their closing line, in
    blue), its rank, part name and score; green when reachable, red when not. With no match, the reason in
    the top-left corner."""
    img = frame.pixels
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    for rank, m in enumerate(frame.matches, start=1):
        colour = (0, 200, 0) if m.get("reachable", True) else (0, 0, 230)
        if rank - 1 < len(frame.contours):
            _draw_contour(out, frame.contours[rank - 1], (0, 255, 255))
        u, v = float(m["u_px"]), float(m["v_px"])
        a = math.radians(float(m["angle_deg"]))
        p = (int(round(u)), int(round(v)))
        cv2.drawMarker(out, p, colour, cv2.MARKER_CROSS, 24, 2)
        q = (int(round(u + 40 * math.cos(a))), int(round(v - 40 * math.sin(a))))  # CCW on screen
        cv2.arrowedLine(out, p, q, colour, 2, tipLength=0.25)
        if isinstance(m.get("grasp_px"), dict):
            draw_grasp(out, m["grasp_px"], (255, 120, 0))
        label = f"{rank} {m.get('part', '')} {float(m['score']):.2f}"
        cv2.putText(out, label, (p[0] + 10, p[1] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2)
    if not frame.matches and frame.reason:
        _banner(out, frame.reason)
    return out


def draw_grasp(out: NDArray[np.uint8], grasp_px: dict[str, Any], colour: tuple[int, int, int]) -> None:
    """A parallel gripper's grasp (``GraspImage.as_json``): the closing line between the open fingers (dashed
    look: thin), each finger a short bar across it, the gripper centre a small circle."""
    (u0, v0), (u1, v1) = grasp_px["fingers_px"]
    du, dv = u1 - u0, v1 - v0
    n = math.hypot(du, dv) or 1.0
    pu, pv = -dv / n * 9.0, du / n * 9.0  # half a finger's width across the closing line, px
    cv2.line(out, _pt(u0, v0), _pt(u1, v1), colour, 1, cv2.LINE_AA)
    for fu, fv in ((u0, v0), (u1, v1)):
        cv2.line(out, _pt(fu - pu, fv - pv), _pt(fu + pu, fv + pv), colour, 4, cv2.LINE_AA)
    cu, cv_ = grasp_px["centre_px"]
    cv2.circle(out, _pt(cu, cv_), 5, colour, 2, cv2.LINE_AA)
    for c in grasp_px.get("contacts_px") or []:
        cv2.circle(out, _pt(*c), 3, (0, 0, 255) if grasp_px.get("problem") else colour, -1, cv2.LINE_AA)


def _pt(u: float, v: float) -> tuple[int, int]:
    return int(round(u)), int(round(v))


def _banner(out: NDArray[np.uint8], text: str) -> None:
    """``text`` on a dark band across the top, wrapped to the frame's width."""
    scale, thick = 0.55, 1
    (cw, ch), _ = cv2.getTextSize("M", cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    per_line = max(int(out.shape[1] / max(cw * 0.62, 1)), 10)
    words, lines, cur = text.split(), [], ""
    for w in words:
        if cur and len(cur) + 1 + len(w) > per_line:
            lines.append(cur)
            cur = w
        else:
            cur = f"{cur} {w}".strip()
    lines.append(cur)
    h = (ch + 8) * len(lines) + 8
    out[:h] = (out[:h] * 0.35).astype(np.uint8)
    for k, line in enumerate(lines):
        cv2.putText(out, line, (8, 8 + (k + 1) * (ch + 8) - 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 200, 255),
                    thick, cv2.LINE_AA)
