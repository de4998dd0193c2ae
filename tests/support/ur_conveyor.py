"""The conveyor cell with a UR arm: ``robot0`` is the ``ur_rtde`` adapter (the real ``ur_rtde`` clients)
against the UR emulator on 127.0.0.1, for ``tests/conveyor/test_ur_conveyor.py`` and ``bench/conveyor.py``.

The belt, its parts, the camera and the gripper stay the virtual cell's; the virtual cell's tool follows
the emulated arm (``ArmMirror``: the world's tool is where an independent RTDE receive client says the
UR's TCP is), so the sim gripper grips and lets go where the UR really is and
the truth says where the parts went. The emulated arm is a UR5e with its TCP at the gripper's.

One emulator at a time (``ur_rtde`` dials fixed ports): ``ur_conveyor_cell`` holds ``fixed_port_lock``.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from calibration.geometry import ur_pose_to_transform
from drivers.base import MotionLimits
from drivers.peers.ur_emulator import fixed_port_lock
from drivers.robot.ur_rtde import URRTDERobot
from drivers.sim.world import SimWorld, world_for
from tests.drivers.peers import PeerProcess, fresh_state
from tests.support.conveyor_cell import conveyor_config

UR_SETTINGS = {
    "host": "127.0.0.1",
    "state_max_age_s": 0.3,  # the default 0.1 s, widened for a loaded 2-core test machine
    "watchdog_min_frequency_hz": 2.0,  # likewise (the watchdog itself is tested in tests/drivers)
    "stall_timeout_s": 1.0,
    "command_timeout_s": 5.0,
    "connect_timeout_s": 10.0,
    "acceleration_m_s2": 3.0,  # a pick-and-place cell's moveL acceleration (ur_rtde's default 1.2 is a teach value)
}

REALTIME_NICE = -10
"""The emulator's priority when the test may raise it (root, as CI runs): a UR controller is a real-time system;
on a 2-core machine at load 20 an ordinary-priority emulator stalls for tens of ms (mm of belt at 100 mm/s)."""


def ur_conveyor_config(tmp: Path, seed: int = 11) -> Path:
    """The conveyor cell's cell.yaml (``conveyor_config``) with ``robot0`` a UR on 127.0.0.1."""
    path = conveyor_config(tmp, seed=seed)
    cfg = yaml.safe_load(path.read_text())
    robot = cfg["robots"]["robot0"]
    robot["kind"] = "ur_rtde"
    robot["settings"] = dict(UR_SETTINGS)
    path.write_text(yaml.safe_dump(cfg))
    return path


class ArmMirror:
    """The virtual cell's tool is where the emulated UR says its TCP is now (``SimWorld.tool_source``): read from
    an independent RTDE receive client's newest sample when the world asks (a grip, a picture), carried on at the
    sample's TCP speed for its age (a process of its own fills the sample at 500 Hz, so no GIL in this one
    delays it)."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world
        self.observer = URRTDERobot("mirror", UR_SETTINGS, MotionLimits(
            x_mm=(-1000, 1000), y_mm=(-1000, 1000), z_mm=(-100, 1000), max_linear_speed_m_s=1.0,
            max_joint_speed_rad_s=1.0))
        self._last = np.eye(4)

    def start(self) -> ArmMirror:
        self.observer.connect()
        self._last = fresh_state(self.observer, 10.0).T_base_tool
        self.world.tool_source = self.T_base_tool
        return self

    def T_base_tool(self) -> NDArray[np.float64]:
        s = self.observer._link.buffer.snapshot()
        if s is None:
            return self._last.copy()
        T = ur_pose_to_transform(np.array(s.pose))
        T[:3, 3] += np.array(s.tcp_speed[:3]) * min(0.05, max(0.0, time.time() - s.host_time_s))
        self._last = T
        return T.copy()

    def close(self) -> None:
        self.world.tool_source = None
        self.observer.close()


def realtime_priority(pid: int) -> None:
    """Raise every thread of process ``pid`` to ``REALTIME_NICE`` where allowed (a controller runs in real time:
    not starved by a loaded test machine). Linux's nice is a thread's: ``setpriority(pid)`` alone raised the
    emulator's main thread, not its 500 Hz loop, which then stalled 20-240 ms a second at load 14 (the arm and
    its state stream standing meanwhile: mm of tracking error at 100 mm/s). Threads started later inherit it."""
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        tids = [pid]
    for tid in tids:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, tid, REALTIME_NICE)


@contextlib.contextmanager
def ur_emulator_with_mirror(scene_path: Path, seed: int | None = None) -> Iterator[ArmMirror]:
    """The UR emulator (holding the fixed ports) and the virtual cell's tool following it."""
    with fixed_port_lock():
        peer = PeerProcess("drivers.peers.ur_emulator", ready_port=30003).start()
        realtime_priority(peer.pid)
        try:
            mirror = ArmMirror(world_for(str(scene_path), seed)).start()
            try:
                yield mirror
            finally:
                mirror.close()
        finally:
            peer.stop()
