"""Moving the robot from the service: one audited move, and ending a sequence safely.

The motion owner and the Stop latch are the driver contract's (``drivers.motion``, reached as
``robot.motion`` / ``robot.motion_session``); this module adds what the service owes the plant on
top: every commanded move is audited with its outcome (ok, refused, stopped, failed), and a
sequence that fails halts the robot without hiding the first error.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from cellctl.store import Store
from drivers.base import MotionRejected, MotionSession, RobotBase, RobotBusy, RobotStopped

log = logging.getLogger(__name__)


def pose_ur(T: NDArray[np.float64]) -> list[float]:
    return [float(v) for v in g.transform_to_ur_pose(T)]


def pose_json(T: NDArray[np.float64]) -> dict[str, float]:
    """A pose as the answers give it: ``x_mm``, ``y_mm``, ``z_mm`` and the rotation vector in radians."""
    x, y, z, rx, ry, rz = (float(v) for v in g.transform_to_ur_pose(T))
    return {"x_mm": x * 1e3, "y_mm": y * 1e3, "z_mm": z * 1e3, "rx_rad": rx, "ry_rad": ry, "rz_rad": rz}


def outcome(exc: BaseException) -> str:
    """The audit outcome of a failed move."""
    kind = ("refused" if isinstance(exc, MotionRejected | RobotBusy) else
            "stopped" if isinstance(exc, RobotStopped) else "failed")
    return f"{kind}: {exc}"


Write = Callable[[Callable[[], object]], object]
"""Runs a store write: at once (``_now``, the default) or later in order (a production run's writer thread)."""


def _now(write: Callable[[], object]) -> object:
    return write()


def audited_move(store: Store, who: str, robot: RobotBase, T: NDArray[np.float64], speed_m_s: float,
                 why: str, session: MotionSession | None = None, extra: dict[str, Any] | None = None,
                 write: Write = _now) -> None:
    """A checked linear move in ``session`` (or its own), audited under ``who`` whatever happens; the
    audit row goes through ``write`` (default: written before this returns)."""
    detail = {"pose_ur": pose_ur(T), "speed_m_s": speed_m_s, "why": why, **(extra or {})}
    try:
        robot.move_linear(T, speed_m_s, session=session, who=who)
    except Exception as exc:
        result = outcome(exc)
        write(lambda: store.audit(who, "robot.move", robot.robot_id, detail, result))
        raise
    write(lambda: store.audit(who, "robot.move", robot.robot_id, detail, "ok"))


def halt_after_failure(robot: RobotBase, error: BaseException) -> None:
    """Halt the robot after ``error`` ended its sequence; a failure to halt is logged and noted on ``error``."""
    if isinstance(error, RobotStopped | RobotBusy | MotionRejected):
        return  # stopped already, never moved by us, or refused before it was sent
    try:
        robot.halt()
    except Exception as exc:  # noqa: BLE001 - the original error stays the one raised
        log.error("robot %s: halting after '%s' failed: %s", robot.robot_id, error, exc)
        error.add_note(f"and halting robot {robot.robot_id} afterwards FAILED: {exc}; check the robot")
