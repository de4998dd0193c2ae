"""A device that is unreachable never hangs a route: 503 quickly, and the service reconnects by
itself when the device comes back. The device is a Modbus TCP robot (the pymodbus simulator of
``drivers/peers/modbus_robot.py``, a real protocol peer) on a loopback port."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import yaml

from tests.conftest import REPO, free_port, start_served, stop_served


def test_unreachable_robot_is_503_then_recovers(tmp_path: Path) -> None:
    port = free_port()
    cfg = yaml.safe_load((REPO / "deploy" / "examples" / "modbus-sim.yaml").read_text())
    robot_id = next(iter(cfg["robots"]))
    cfg["robots"][robot_id]["settings"]["port"] = port
    for dev in cfg.get("io", {}).values():
        dev["settings"]["port"] = port
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    served = start_served(tmp_path, config=path)
    peer = None
    try:
        with served.client(timeout_s=30) as http:
            for _ in range(3):
                t0 = time.monotonic()
                r = http.get(f"/robots/{robot_id}/state")
                assert time.monotonic() - t0 < 5.0
                assert r.status_code == 503, r.text
                body = r.json()
                assert body["available"] is False and body["reason"]
            peer = subprocess.Popen([sys.executable, "-m", "drivers.peers.modbus_robot", "--host", "127.0.0.1",
                                     "--port", str(port)], cwd=REPO)
            deadline = time.monotonic() + 30
            while True:
                r = http.get(f"/robots/{robot_id}/state")
                if r.status_code == 200:
                    break
                assert r.status_code == 503
                assert time.monotonic() < deadline, "the service did not reconnect within 30 s"
                time.sleep(0.5)
            assert r.json()["age_s"] < 1.0
            # The peer dies: the next reads answer 503 quickly again, never a stale pose.
            peer.kill()
            peer.wait()
            deadline = time.monotonic() + 15
            while (r := http.get(f"/robots/{robot_id}/state")).status_code == 200:
                assert time.monotonic() < deadline
                time.sleep(0.2)
            assert r.status_code == 503 and r.json()["available"] is False
    finally:
        if peer is not None and peer.poll() is None:
            peer.kill()
        stop_served(served)
