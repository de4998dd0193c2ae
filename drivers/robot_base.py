"""The base of robot adapters (``RobotBase``): the public motion methods own the safety rules.

``move_linear`` / ``move_joint`` run the one envelope and speed check (``drivers.limits.MotionLimits``)
and only then call the adapter's ``_move_linear`` / ``_move_joint`` hooks, under the motion owner
(``drivers.motion``: one owner at a time, the Stop latch) and a deadline, so no adapter can bypass
them. Units: poses ``T_base_tool`` 4x4 in metres; joints in radians; speeds m/s and rad/s.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import math
import threading
from collections.abc import Callable, Iterator

import numpy as np
from numpy.typing import NDArray

from drivers.device_base import DeviceBase
from drivers.errors import DeviceTimeout, DeviceUnavailable, DriverError, MotionRejected
from drivers.limits import MotionLimits
from drivers.motion import MotionOwner, MotionSession, RobotBusy, RobotStopped, move_deadline_s
from drivers.values import RobotState

log = logging.getLogger(__name__)

DEFAULT_TURN_DEG_S = 90.0
"""The tool's turn rate a planner assumes for an adapter that does not say its own, deg/s."""
DEFAULT_ACCEL_M_S2 = 2.0
"""The tool's acceleration ``RobotBase.linear_move_s`` assumes by default, m/s^2."""


class RobotBase(DeviceBase):
    """Base of robot adapters: the public motion methods own the rules, the adapter fills hooks.

    ``move_linear`` / ``move_joint`` check the envelope, orientation, speed and duration, take the
    robot's motion (``self.motion``: one owner at a time, refused while latched), run the adapter's
    hook under a deadline, and raise ``RobotStopped`` when a Stop halted the move — whatever the
    hook returned. ``stop`` halts and latches; ``resume`` clears the latch; ``halt`` stops motion
    without latching (cleanup after a failed sequence). Adapters implement ``_move_linear``,
    ``_stop`` and may poll ``_motion_aborted()`` while they wait for arrival.
    A controller lost while a move runs or a sequence owns the robot latches it (``_controller_dropped``).
    """

    def __init__(self, robot_id: str, limits: MotionLimits) -> None:
        self.robot_id = robot_id
        self.limits = limits
        self.motion = MotionOwner(robot_id)
        self._move_lock = threading.Lock()
        self._moving_session: MotionSession | None = None

    def _open_device(self) -> None:
        self.connect()

    @abc.abstractmethod
    def connect(self) -> None:
        """Connect to the robot controller."""

    @abc.abstractmethod
    def state(self) -> RobotState:
        """The current state; DeviceUnavailable when it is not fresh."""

    # -- motion sessions -----------------------------------------------------------------------------
    @contextlib.contextmanager
    def motion_session(self, who: str, what: str) -> Iterator[MotionSession]:
        """Own the robot's motion for a sequence of moves (``RobotBusy`` / ``RobotStopped`` if not free)."""
        session = self.motion.begin(who, what)
        try:
            yield session
        finally:
            self.motion.end(session)

    def move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float,
                    session: MotionSession | None = None, who: str = "direct") -> None:
        """Move the tool in a straight line to ``T_base_tool`` (metres) at ``speed_m_s``.

        Without ``session`` the move is a sequence of its own (refused while another one runs), owned
        by ``who`` (the motion owner ``GET /robots/{id}/motion`` shows: a token's name).
        """
        target = np.asarray(T_base_tool, dtype=np.float64)
        self.limits.check_pose(target)
        self.limits.check_linear_speed(speed_m_s)
        distance_m = self._distance_to(target)
        nominal_s = self.limits.check_duration(distance_m, speed_m_s, "m")
        self._supervised(session, f"linear move to {_xyz_mm(target)}", nominal_s,
                         lambda: self._move_linear(target, speed_m_s), who)

    def move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float,
                   session: MotionSession | None = None) -> None:
        """Move in joint space to ``joints_rad``; the resulting tool pose is checked too."""
        q = np.asarray(joints_rad, dtype=np.float64)
        self.limits.check_joints(q)
        self.limits.check_joint_speed(speed_rad_s)
        T = self.forward_kinematics(q)
        if T is not None:
            self.limits.check_pose(T)
        span_rad = self._joint_span_to(q)
        nominal_s = self.limits.check_duration(span_rad, speed_rad_s, "rad")
        self._supervised(session, "joint move", nominal_s, lambda: self._move_joint(q, speed_rad_s))

    def move_deadline_s(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> float:
        """How long a linear move to ``T_base_tool`` may take before it is stopped (s)."""
        distance_m = self._distance_to(np.asarray(T_base_tool, dtype=np.float64))
        return move_deadline_s(distance_m / speed_m_s if speed_m_s > 0 else math.inf,
                               self.limits.move_deadline_slack_s)

    def _supervised(self, session: MotionSession | None, what: str, nominal_s: float,
                    hook: Callable[[], None], who: str = "direct") -> None:
        if session is None:
            with self.motion_session(who, what) as own:
                self._run_move(own, nominal_s, hook, in_sequence=False)
        else:
            if not self.motion.is_current(session):
                session.check()
                raise RobotBusy(f"robot {self.robot_id}: {session.what} does not own the robot's motion")
            self._run_move(session, nominal_s, hook, in_sequence=True)

    def _run_move(self, session: MotionSession, nominal_s: float, hook: Callable[[], None], in_sequence: bool) -> None:
        session.check()
        deadline_s = move_deadline_s(nominal_s, self.limits.move_deadline_slack_s)
        timed_out = threading.Event()
        stop_failures: list[BaseException] = []

        def on_deadline() -> None:
            timed_out.set()
            try:
                self._stop()
            except Exception as exc:  # noqa: BLE001 - reported with the timeout below
                stop_failures.append(exc)
                log.error("robot %s: stopping a move past its deadline failed: %s", self.robot_id, exc)

        timer = threading.Timer(deadline_s, on_deadline)
        timer.daemon = True
        dropout_if_lost = in_sequence or self.health().available  # gone before a lone move: an outage only
        with self._move_lock:
            self._moving_session = session
        timer.start()
        try:
            hook()
        except Exception as exc:
            if isinstance(exc, DeviceUnavailable) and dropout_if_lost:
                self._controller_dropped(str(exc))  # latched; the move answers why it failed
                raise
            if session.aborted:
                raise RobotStopped(f"robot {self.robot_id}: the move was stopped ({session.abort_reason})") from exc
            if timed_out.is_set():
                raise self._deadline_error(deadline_s, nominal_s, stop_failures) from exc
            raise
        finally:
            timer.cancel()
            with self._move_lock:
                self._moving_session = None
        if session.aborted:
            # A Stop came while the adapter moved: whatever the adapter says, the move did not happen as asked.
            raise RobotStopped(f"robot {self.robot_id}: the move was stopped ({session.abort_reason})")
        if timed_out.is_set():
            raise self._deadline_error(deadline_s, nominal_s, stop_failures)

    def _deadline_error(self, deadline_s: float, nominal_s: float, stop_failures: list[BaseException]
                        ) -> DeviceTimeout:
        msg = (f"robot {self.robot_id}: the move did not finish within {deadline_s:.1f} s (nominal "
               f"{nominal_s:.1f} s) and was stopped")
        if stop_failures:
            msg += f"; STOPPING IT FAILED: {stop_failures[0]} — check the robot now"
        return DeviceTimeout(msg)

    def _controller_dropped(self, reason: str) -> None:
        """The controller was lost: latch the robot (the Stop's latch) if a move runs or a sequence owns it."""
        session = self.motion.latch_if_owned("controller", f"controller dropped out: {reason}")
        if session is not None:
            log.warning("robot %s: the controller dropped out during %s; latched until an engineer resumes: %s",
                        self.robot_id, session.what, reason)

    def _motion_aborted(self) -> bool:
        """True while the move in progress belongs to a session a Stop has aborted (adapters poll it)."""
        with self._move_lock:
            s = self._moving_session
        return s is not None and s.aborted

    def _distance_to(self, target: NDArray[np.float64]) -> float:
        """Straight-line distance (m) from the current tool position to ``target`` (for the deadline)."""
        try:
            current = self.state().T_base_tool
        except DriverError:
            # Where the tool is now is unknown: the longest move the envelope allows bounds the deadline.
            lim = self.limits
            return 1e-3 * math.dist((lim.x_mm[0], lim.y_mm[0], lim.z_mm[0]), (lim.x_mm[1], lim.y_mm[1], lim.z_mm[1]))
        return float(np.linalg.norm(target[:3, 3] - current[:3, 3]))

    def _joint_span_to(self, q: NDArray[np.float64]) -> float:
        try:
            current = self.state().joints_rad
        except DriverError:
            return 0.0
        if current.shape != q.shape:
            return 0.0
        return float(np.max(np.abs(q - current))) if q.size else 0.0

    # -- the robot's own motion: what a planner needs to know -------------------------------------------
    def tool_turn_speed_deg_s(self) -> float:
        """How fast a linear move turns the tool, deg/s (the robot's orientation speed; a planner's estimate
        of a turn). Default ``DEFAULT_TURN_DEG_S``; an adapter that knows its controller's says its own."""
        return DEFAULT_TURN_DEG_S

    def linear_move_s(self, T_from: NDArray[np.float64], T_to: NDArray[np.float64], speed_m_s: float,
                      accel_m_s2: float = DEFAULT_ACCEL_M_S2) -> float:
        """How long a linear move from ``T_from`` to ``T_to`` (4x4, metres) at ``speed_m_s`` takes on this
        robot until its arrival is seen, s: the adapter times its moves with the same function, so a planner
        using it is never optimistic about the motion itself (the host's delays are the planner's to add).
        Default (an adapter that does not know its controller's profile): the distance at ``speed_m_s``
        with ``accel_m_s2`` ramps, or the turn at ``tool_turn_speed_deg_s`` when that is longer."""
        d = float(np.linalg.norm(np.asarray(T_to)[:3, 3] - np.asarray(T_from)[:3, 3]))
        ramp = speed_m_s / accel_m_s2 if accel_m_s2 > 0 else 0.0
        return max(d / speed_m_s + ramp, turn_deg(T_from, T_to) / self.tool_turn_speed_deg_s())

    def tracking_report(self) -> dict[str, float | int] | None:
        """The last conveyor tracking's measured error (an adapter that tracks from the host and measures it:
        ``rms_mm``, ``max_mm``, ``samples``, ``servo_steps``); None when the adapter does not measure it
        (a controller tracking with the encoder wired to it)."""
        return None

    # -- conveyor tracking ---------------------------------------------------------------------------
    def start_tracking(self, direction_base: NDArray[np.float64], ticks_per_m: float, most_m: float,
                       session: MotionSession, count: Callable[[], int] | None = None) -> int:
        """Follow a conveyor from now, as the robot controller does with the belt's encoder wired to it (UR:
        ``conveyor_pulse_decode`` + ``track_conveyor_linear``): every pose commanded from now on is carried
        along ``direction_base`` (unit vector, base frame) by the travel the encoder counts
        (``ticks_per_m``), at most ``most_m`` metres. The count tracking starts at. Needs the motion
        (``session``); a Stop ends tracking at once (the tool stays where it is). ``MotionRejected`` when
        the adapter cannot track. ``count``: the belt's encoder count as the host reads it (cellctl's
        conveyor), for an adapter that tracks from the host (the UR over RTDE); a controller with the encoder
        wired to it (the sim arm) counts itself."""
        if not self.motion.is_current(session):
            session.check()
            raise RobotBusy(f"robot {self.robot_id}: {session.what} does not own the robot's motion")
        session.check()
        return self._start_tracking(np.asarray(direction_base, dtype=np.float64), float(ticks_per_m), float(most_m),
                                    count)

    def tracks_conveyor(self) -> bool:
        """Whether this adapter can track a conveyor (``start_tracking``); a belt run is refused before the
        robot moves when it cannot."""
        return False

    def stop_tracking(self) -> None:
        """Stop following the conveyor: the tool stays where it is."""
        self._stop_tracking()

    def _start_tracking(self, direction_base: NDArray[np.float64], ticks_per_m: float, most_m: float,
                        count: Callable[[], int] | None) -> int:
        raise MotionRejected(f"robot {self.robot_id}: this adapter cannot track a conveyor (docs/conveyor.md)")

    def _stop_tracking(self) -> None:
        """Tell the controller to stop tracking (nothing when it cannot track)."""

    # -- stop, resume ------------------------------------------------------------------------------
    def stop(self, by: str = "") -> None:
        """Halt now, abort the sequence that owns the robot, and latch until ``resume``.

        The latch holds even when the adapter's stop fails; that failure is raised, never swallowed.
        """
        self.motion.latch(by, "Stop")
        self._stop()

    def resume(self, by: str = "") -> bool:
        """Clear the Stop latch (an engineer's act, ``by`` names them); True when the robot was latched."""
        return self.motion.resume(by)

    def halt(self) -> None:
        """Stop any motion without latching (cleanup after a failed or cancelled sequence)."""
        self._stop()

    def forward_kinematics(self, joints_rad: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """``T_base_tool`` for ``joints_rad`` if the adapter knows it (for the envelope check)."""
        return None

    @abc.abstractmethod
    def _move_linear(self, T_base_tool: NDArray[np.float64], speed_m_s: float) -> None:
        """Send a checked linear move to the controller and wait until it arrives."""

    def _move_joint(self, joints_rad: NDArray[np.float64], speed_rad_s: float) -> None:
        raise MotionRejected(f"robot {self.robot_id}: joint moves are not supported by this adapter")

    @abc.abstractmethod
    def _stop(self) -> None:
        """Tell the controller to stop any motion now."""


def turn_deg(T0: NDArray[np.float64], T1: NDArray[np.float64]) -> float:
    """The angle (deg) the tool turns from ``T0`` to ``T1`` (4x4 poses)."""
    c = (float(np.trace(np.asarray(T0)[:3, :3].T @ np.asarray(T1)[:3, :3])) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _xyz_mm(T: NDArray[np.float64]) -> str:
    x, y, z = (float(v) * 1000.0 for v in T[:3, 3])
    return f"({x:.1f}, {y:.1f}, {z:.1f}) mm"
