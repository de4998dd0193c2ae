"""The control worker's half of host-side conveyor tracking (``drivers/robot/ur_tracking.py`` is the other).

The stream runs in the control worker, a process of its own, so that nothing in the service's process (a
vision search holding the GIL) can delay a servo step. The service writes into ``TrackShared`` (shared
memory): the belt's newest count sample and speed, the tool's move in the belt's frame, the envelope; the
worker, every ``period_s``, carries the belt-frame position along the belt by the count extrapolated to
``lead_s`` ahead, checks it against the envelope box and sends it as ``servoL``. A pose outside the box is
never sent: the stream ends, the arm is stopped, the pose is reported (``failed``).

Kept free of numpy (the worker starts fast). Positions in metres, base frame; times ``time.monotonic``.
"""

from __future__ import annotations

import ctypes
import time
from multiprocessing.context import SpawnContext
from typing import Any

# layout (doubles)
ACTIVE, FAILED, T_COUNT, TICKS, SPEED, LAG, TICKS0, TPM, MOST, PERIOD, LEAD, SEG_T0, SEG_DUR, SENT = range(14)
DIR, P0, P1, ROT, BOX, BAD = 14, 17, 20, 23, 26, 32
LAST, MAXGAP = 35, 36
"""When the worker last sent a step (``time.monotonic``), and the longest interval between two sends (s): a
stall of the worker shows there."""
SIZE = 37


class TrackShared:
    """The tracking's shared state: written by the service, read by the control worker's stream."""

    def __init__(self, ctx: SpawnContext) -> None:
        self._a: Any = ctx.Array(ctypes.c_double, SIZE)

    def read(self) -> list[float]:
        with self._a.get_lock():
            return list(self._a[:])

    def write(self, **fields: float | list[float]) -> None:
        """Set fields by name (``active``, ``ticks``, ``p0`` ...), all at once."""
        with self._a.get_lock():
            for name, value in fields.items():
                i = globals()[name.upper()]
                if isinstance(value, list):
                    self._a[i:i + len(value)] = [float(v) for v in value]
                else:
                    self._a[i] = float(value)

    @property
    def active(self) -> bool:
        return bool(self._a[ACTIVE])

    def end(self) -> None:
        """No pose is streamed after this (the worker reads it before every send)."""
        self._a[ACTIVE] = 0.0


def stream_pose(v: list[float], now: float) -> list[float]:
    """The position (m) to stream at ``now``: the belt-frame move at ``now + lead`` carried by the belt's travel
    (the count extrapolated at its speed, the service's lag term), 0 to ``most`` metres."""
    lead = v[LEAD]
    ticks = v[TICKS] + v[SPEED] * (now - v[T_COUNT] + lead)
    travel = min(max((ticks - v[TICKS0]) / v[TPM] + v[LAG], 0.0), v[MOST])
    s = 1.0 if v[SEG_DUR] <= 0 else min(1.0, max(0.0, (now + lead - v[SEG_T0]) / v[SEG_DUR]))
    return [v[P0 + i] + s * (v[P1 + i] - v[P0 + i]) + v[DIR + i] * travel for i in range(3)]


def outside_box(p: list[float], v: list[float]) -> bool:
    return any(not v[BOX + 2 * i] <= p[i] <= v[BOX + 2 * i + 1] for i in range(3))


def stream_step(ctrl: Any, shared: TrackShared) -> bool:
    """One servo step; False when the stream has ended (ended by the service, or a pose left the box)."""
    v = shared.read()
    if not v[ACTIVE]:
        return False
    p = stream_pose(v, time.monotonic())
    if outside_box(p, v):
        shared.write(active=0.0, failed=1.0, bad=p)
        ctrl.stopL(5.0, False)
        return False
    if not shared.active:
        return False
    ctrl.servoL([*p, *v[ROT:ROT + 3]], 0.5, 0.5, v[LEAD], 0.1, 300.0)
    now = time.monotonic()
    gap = now - v[LAST] if v[SENT] > 0 else 0.0
    shared.write(sent=v[SENT] + 1, last=now, maxgap=max(v[MAXGAP], gap))
    return True
