"""Moving the robot from the service: one audited move, and ending a sequence safely.

The motion owner and the Stop latch are the driver contract's (``drivers.motion``, reached as
``robot.motion`` / ``robot.motion_session``); this module adds what the service owes the plant on
top: every commanded move is audited with its outcome (ok, refused, stopped, failed), and a
sequence that fails halts the robot without hiding the first error.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from cellctl.store import Store
from drivers.base import MotionRejected, MotionSession, RobotBase, RobotBusy, RobotStopped

log = logging.getLogger(__name__)


def pose_ur(T: NDArray[np.float64]) -> list[float]:
    return [float(v) for v in g.transform_to_ur_pose(T)]


def outcome(exc: BaseException) -> str:
    """The audit outcome of a failed move."""
    kind = ("refused" if isinstance(exc, MotionRejected | RobotBusy) else
            "stopped" if isinstance(exc, RobotStopped) else "failed")
    return f"{kind}: {exc}"


def audited_move(store: Store, who: str, robot: RobotBase, T: NDArray[np.float64], speed_m_s: float,
                 why: str, session: MotionSession | None = None, extra: dict[str, Any] | None = None) -> None:
    """A checked linear move in ``session`` (or its own), audited under ``who`` whatever happens."""
    detail = {"pose_ur": pose_ur(T), "speed_m_s": speed_m_s, "why": why, **(extra or {})}
    try:
        robot.move_linear(T, speed_m_s, session=session, who=who)
    except Exception as exc:
        store.audit(who, "robot.move", robot.robot_id, detail, outcome(exc))
        raise
    store.audit(who, "robot.move", robot.robot_id, detail, "ok")


def halt_after_failure(robot: RobotBase, error: BaseException) -> None:
    """Halt the robot after ``error`` ended its sequence; a failure to halt is logged and noted on ``error``."""
    if isinstance(error, RobotStopped | RobotBusy | MotionRejected):
        return  # stopped already, never moved by us, or refused before it was sent
    try:
        robot.halt()
    except Exception as exc:  # noqa: BLE001 - the original error stays the one raised
        log.error("robot %s: halting after '%s' failed: %s", robot.robot_id, error, exc)
        error.add_note(f"and halting robot {robot.robot_id} afterwards FAILED: {exc}; check the robot")
