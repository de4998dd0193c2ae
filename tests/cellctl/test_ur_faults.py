"""Faults mid-move on a served UR cell (``deploy/examples/ur-sim.yaml`` against the UR emulator):

- the service is killed (SIGKILL) during a slow move: its workers die with it, the kicks of the
  controller's RTDE watchdog stop, and the controller halts the arm within the watchdog period;
- the controller (the emulator) is killed during a move and comes back: the robot is latched as a
  Stop latches it, and moves answer 409 ``robot_stopped`` until an engineer resumes.

The arm is watched through an independent ``ur_rtde`` receive client (not through the service).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml

from drivers.peers.ur_emulator import fixed_port_lock
from tests.conftest import REPO
from tests.drivers.peers import wait_port
from tests.support.served import Served, start_served, stop_served

WATCHDOG_HZ = 10.0
"""ur-sim.yaml's watchdog_min_frequency_hz: the arm stops within 1/f s of the last kick."""
STOP_MARGIN_S = 0.5
"""Added to the watchdog period for the stop: the emulator's 500 Hz loop and the test's polling, on a loaded machine."""
SPEED_M_S = 0.05
TRAVEL_M = 0.25


class Emulator:
    """The UR emulator in its own process, its log in a file (stopped by its pid only)."""

    def __init__(self, log_path: Path) -> None:
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> Emulator:
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "drivers.peers.ur_emulator"], cwd=REPO,
                                         stdout=subprocess.DEVNULL, stderr=log)
        wait_port(30003, 15.0)
        return self

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=5)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


def _config(tmp_path: Path) -> Path:
    cfg = yaml.safe_load((REPO / "deploy" / "examples" / "ur-sim.yaml").read_text())
    settings = cfg["robots"]["ur0"]["settings"]
    assert settings["watchdog_min_frequency_hz"] == WATCHDOG_HZ
    settings["state_max_age_s"] = 0.3  # the example's 0.1 s, widened for a loaded 2-core test machine
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.fixture
def ur_cell(tmp_path: Path) -> Iterator[tuple[Emulator, Served]]:
    with fixed_port_lock():
        emulator = Emulator(tmp_path / "emulator.log").start()
        try:
            served = start_served(tmp_path, config=_config(tmp_path))
            try:
                yield emulator, served
            finally:
                if served.process.poll() is None:
                    stop_served(served)
        finally:
            emulator.stop()


def wait_for(cond: Callable[[], Any], timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s} s")
        time.sleep(0.02)


def _state(http: httpx.Client) -> dict[str, Any] | None:
    r = http.get("/robots/ur0/state")
    return r.json() if r.status_code == 200 else None


def _moved(http: httpx.Client, box: dict[str, Any], emulator: Emulator, moved: Callable[[], bool]) -> bool:
    """True once ``moved()``; a move request that has already answered fails the test with its answer."""
    if moved():
        return True
    if "response" in box or "error" in box:
        answer = box.get("response")
        raise AssertionError(f"the move answered before it got under way: "
                             f"{answer.text if answer is not None else box['error']!r}\n{emulator.log()[-1500:]}")
    return False


def _move_in_thread(http: httpx.Client, pose_ur: dict[str, float], speed_m_s: float) -> dict[str, Any]:
    """POST the move in a thread; the box gets its response (or the exception) when it returns."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["response"] = http.post("/robots/ur0/move", json={"pose_ur": pose_ur, "speed_m_s": speed_m_s})
        except httpx.HTTPError as exc:  # the service was killed under the request
            box["error"] = exc

    box["thread"] = threading.Thread(target=run, daemon=True)
    box["thread"].start()
    return box


def test_the_arm_halts_within_the_watchdog_period_when_the_service_is_killed(
        ur_cell: tuple[Emulator, Served]) -> None:
    import rtde_receive

    emulator, served = ur_cell
    with served.client(timeout_s=60) as http:
        start = wait_for(lambda: _state(http), 20.0, "the robot's state")["pose_ur"]
        target = {**start, "x_m": start["x_m"] + TRAVEL_M}  # 250 mm at 0.05 m/s: 5 s
        receiver = rtde_receive.RTDEReceiveInterface("127.0.0.1")
        try:
            def x_m() -> float:
                return float(receiver.getActualTCPPose()[0])

            x0 = x_m()
            box = _move_in_thread(http, target, SPEED_M_S)
            wait_for(lambda: _moved(http, box, emulator, lambda: x_m() - x0 > 0.06), 30.0,
                     "the arm 60 mm (1.2 s) into the move")
            x_kill = x_m()
            t_kill = time.monotonic()
            os.kill(served.process.pid, signal.SIGKILL)
            track: list[tuple[float, float]] = []  # (s after the kill, x in m)
            while time.monotonic() - t_kill < 2.0:
                track.append((time.monotonic() - t_kill, x_m()))
                time.sleep(0.002)
            served.process.wait(timeout=10)
            x_end = track[-1][1]
            last_motion_s = max((t for t, x in track if abs(x - x_end) > 1e-7), default=0.0)
            print(f"\nkill -9 at x = {1000 * (x_kill - x0):.1f} mm; arm halted {last_motion_s * 1000:.0f} ms "
                  f"after, {1000 * (x_end - x_kill):.1f} mm further; {1000 * (x0 + TRAVEL_M - x_end):.0f} mm "
                  "short of the target")
            assert last_motion_s < 1.0 / WATCHDOG_HZ + STOP_MARGIN_S, track[-50:]
            assert x_end - x_kill < SPEED_M_S * (1.0 / WATCHDOG_HZ + STOP_MARGIN_S)
            assert x0 + TRAVEL_M - x_end > 0.1  # far from the target: the move did not go on unsupervised
            # frozen: nothing moves it any more, and the controller says its program was stopped
            assert all(abs(x - x_end) < 1e-7 for t, x in track if t > last_motion_s)
            time.sleep(0.5)
            assert abs(x_m() - x_end) < 1e-7
            assert receiver.getRuntimeState() != 2  # not "playing": the control script was stopped
        finally:
            receiver.disconnect()
    log = wait_for(lambda: "RTDE watchdog" in emulator.log() and emulator.log(), 5.0, "the emulator's report")
    assert "program stopped, the arm halted mid-move" in log, log[-2000:]


def test_a_controller_that_drops_out_mid_move_latches_the_robot_until_resumed(
        ur_cell: tuple[Emulator, Served]) -> None:
    emulator, served = ur_cell
    with served.client(timeout_s=60) as http:
        start = wait_for(lambda: _state(http), 20.0, "the robot's state")["pose_ur"]
        box = _move_in_thread(http, {**start, "x_m": start["x_m"] + 0.1}, SPEED_M_S)

        def under_way() -> bool:
            s = _state(http)
            return s is not None and s["pose_ur"]["x_m"] - start["x_m"] > 0.01

        wait_for(lambda: _moved(http, box, emulator, under_way), 30.0, "the move")
        emulator.kill()
        box["thread"].join(timeout=30)
        r = box["response"]
        assert r.status_code == 503 and r.json()["error"]["code"] == "device_unavailable", r.text
        motion = http.get("/robots/ur0/motion").json()
        print(f"\nafter the controller dropped out: {motion}")
        assert motion["latched"] and motion["latched_by"] == "controller", motion
        assert "controller dropped out" in motion["latched_reason"]
        emulator.start()  # the controller is back (at its home pose); the adapter reconnects by itself
        back = wait_for(lambda: _state(http), 30.0, "the reconnected robot's state")
        assert back["latched"] is True
        small = {**back["pose_ur"], "z_m": back["pose_ur"]["z_m"] + 0.01}
        r = http.post("/robots/ur0/move", json={"pose_ur": small, "speed_m_s": 0.1})
        assert r.status_code == 409 and r.json()["error"]["code"] == "robot_stopped", r.text
        assert "resume" in r.json()["error"]["message"]
        time.sleep(0.3)
        here = _state(http)
        assert here is not None and abs(here["pose_ur"]["z_m"] - back["pose_ur"]["z_m"]) < 1e-4  # nothing moved
        r = http.post("/robots/ur0/resume")
        assert r.status_code == 200 and r.json()["resumed"] is True, r.text
        r = http.post("/robots/ur0/move", json={"pose_ur": small, "speed_m_s": 0.1})
        assert r.status_code == 200, r.text
        assert np.isclose(r.json()["pose_ur"]["z_m"], small["z_m"], atol=2e-4)
