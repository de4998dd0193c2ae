"""Benchmark: the driver adapters against their bare client libraries, same peer, same run.

Camera (named peer: a bare Aravis loop — pop buffer, copy to numpy, push back): frames/s, lost
and incomplete frames from ``arv-fake-gv-camera-0.8`` at 100 and 300 frames/s requested, inside
a loopback-only network namespace (drivers/peers/netns.py, bench/drivers_gige.py; no packet leaves it), and the
grab-to-numpy latency (host time when ``grab()`` returns minus the buffer's host timestamp).
Targets: adapter >= 95 % of the bare loop's rate; zero lost frames at 100 fps.

Robot (named peer: ``ur_rtde`` called directly in one process): against the UR emulator at
500 Hz, the age of the newest state when ``state()`` is read at random times, and the round trip
of a short ``move_linear`` (2 mm at 0.25 m/s) against a bare synchronous ``moveL``.

Run: ``.venv/bin/python bench/drivers.py [--seconds 10] [--out bench/results/drivers.md]`` (as root,
for the network namespace; the UR emulator needs 127.0.0.1's fixed UR ports).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# The adapter's worker processes are started with "spawn", which imports this script again in each
# worker (as __mp_main__): the heavy imports stay inside the functions so that a worker boots fast.

BARE_MOVES = r"""
import json, sys, time
import rtde_control, rtde_receive
n = int(sys.argv[1])
c = rtde_control.RTDEControlInterface("127.0.0.1")
r = rtde_receive.RTDEReceiveInterface("127.0.0.1")
p = r.getActualTCPPose()
times = []
for i in range(n):
    q = list(p); q[2] += 0.002 if i % 2 == 0 else 0.0
    t0 = time.perf_counter(); ok = c.moveL(q, 0.25, 1.2); times.append(time.perf_counter() - t0)
    assert ok
c.stopScript(); c.disconnect(); r.disconnect()
print(json.dumps(times))
"""


def camera(seconds: float) -> dict[str, Any]:
    from drivers.peers.netns import run_in_loopback_namespace

    return run_in_loopback_namespace(ROOT / "bench" / "drivers_gige.py", str(seconds), "100,300", "2",
                                     timeout_s=120 + 6 * seconds)


def wait_port(port: int, timeout_s: float = 10.0) -> None:
    """Wait until something accepts TCP connections on 127.0.0.1:``port``."""
    import socket

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")


def robot(n_moves: int, state_reads: int) -> dict[str, Any]:
    from drivers.base import MotionLimits
    from drivers.peers.ur_emulator import fixed_port_lock
    from drivers.robot.ur_rtde import URRTDERobot

    out: dict[str, Any] = {}
    with fixed_port_lock():
        emu = subprocess.Popen([sys.executable, "-m", "drivers.peers.ur_emulator"], cwd=ROOT,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            wait_port(30003)
            bare = subprocess.run([sys.executable, "-c", BARE_MOVES, str(n_moves)], capture_output=True, text=True,
                                  timeout=120)
            out["bare_move_s"] = json.loads(bare.stdout.strip().splitlines()[-1])
            limits = MotionLimits((-900, 900), (-900, 900), (0, 900), 0.5)
            # a sample older than the limit is never served; 0.5 s (not the default 0.1 s) so that a read on
            # this shared, overloaded machine is measured rather than refused (the ages are in the table)
            r = URRTDERobot("ur0", {"host": "127.0.0.1", "state_max_age_s": 0.5, "connect_timeout_s": 20.0}, limits)
            r.connect()
            try:
                ages = []
                for _ in range(state_reads):
                    time.sleep(random.uniform(0.0, 0.004))
                    ages.append(r.state().age_s())
                out["state_age_s"] = ages
                start = r.state().T_base_tool
                r.move_linear(start, 0.25)  # starts the control worker (not timed)
                times = []
                for i in range(n_moves):
                    T = start.copy()
                    T[2, 3] += 0.002 if i % 2 == 0 else 0.0
                    t0 = time.perf_counter()
                    r.move_linear(T, 0.25)
                    times.append(time.perf_counter() - t0)
                out["adapter_move_s"] = times
            finally:
                r.close()
        finally:
            emu.send_signal(signal.SIGTERM)
            emu.wait(timeout=10)
    return out


def _ms(values: list[float], q: float) -> float:
    import numpy as np

    return 1000.0 * float(np.percentile(values, q))


def _camera_note(cam: dict[str, Any]) -> str:
    spread = max(max(r["per_round_fps"]["bare"]) / min(r["per_round_fps"]["bare"]) - 1.0
                 for r in cam["rates"].values())
    missed = [rate for rate, r in cam["rates"].items() if r["adapter"]["fps_received"] < 0.95 * r["bare"]["fps"]]
    note = (f"The fake camera is CPU-bound on this shared machine (well under 300 fps even for the bare loop), and "
            f"the bare loop's own rounds differ by up to {100 * spread:.0f} %: ratios within that spread are noise. ")
    if missed:
        note += (f"Missed at {', '.join(missed)} fps: the camera process and the client share 2 cores, so the "
                 "adapter's extra CPU per frame (its reader thread + the application's grab thread) costs the "
                 "camera frames; reported, not tuned away.")
    return note


def report(cam: dict[str, Any], rob: dict[str, Any], seconds: float) -> str:
    import numpy as np

    lines = ["# Driver benchmark", "",
             f"Machine: {os.cpu_count()} cores (shared; load average {os.getloadavg()[0]:.1f} at the end). "
             f"Camera runs: {seconds:g} s per rate and client, as {cam['rounds']} alternating rounds (the issue "
             "asks 30 s; shortened for the shared 2-core machine). Peer of the camera adapter: a bare "
             "Aravis loop on the same fake camera in the same run; peer of the robot adapter: ur_rtde called "
             "directly, same emulator, same run.", "",
             "## Camera: arv-fake-gv-camera-0.8 (512x512 Mono8) over GigE Vision on loopback, in a network namespace",
             "", "| requested fps | bare Aravis fps | adapter fps | ratio | target >= 95 % | bare lost / incomplete "
             "| adapter lost / incomplete | zero lost at 100 fps | grab-to-numpy latency median / p99 (ms) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for rate, row in cam["rates"].items():
        b, a = row["bare"], row["adapter"]
        ratio = a["fps_received"] / b["fps"] if b["fps"] else float("nan")
        met = "met" if ratio >= 0.95 else "**missed**"
        zero = ("met" if a["lost"] == 0 and a["incomplete"] == 0 else "**missed**") if rate == "100" else "-"
        lat = (f"{a['latency_ms_median']:.2f} / {a['latency_ms_p99']:.2f}" if a["latency_ms_median"] is not None
               else "-")
        lines.append(f"| {rate} | {b['fps']:.1f} | {a['fps_received']:.1f} (grabbed {a['fps_grabbed']:.1f}) | "
                     f"{ratio:.3f} | {met} | {b['lost']} / {b['incomplete']} | {a['lost']} / {a['incomplete']} | "
                     f"{zero} | {lat} |")
    lines += ["", "Client CPU per frame (ms, bare / adapter) and per-round frames/s (bare | adapter): " + "; ".join(
        f"{rate} fps: {row['bare']['cpu_ms_per_frame']:.2f} / {row['adapter']['cpu_ms_per_frame']:.2f} ms, "
        f"{', '.join(f'{v:.1f}' for v in row['per_round_fps']['bare'])} | "
        f"{', '.join(f'{v:.1f}' for v in row['per_round_fps']['adapter'])}"
        for rate, row in cam["rates"].items()) + ".",
              "", _camera_note(cam)]
    ages = rob["state_age_s"]
    bare, ad = rob["bare_move_s"], rob["adapter_move_s"]
    lines += ["", "## Robot: UR emulator (RTDE 500 Hz) on 127.0.0.1", "",
              "| measure | ur_rtde directly | cellctl adapter | ratio |", "| --- | --- | --- | --- |",
              f"| newest state age when read, median / p99 / max (ms) | - (ur_rtde has no host timestamp) | "
              f"{_ms(ages, 50):.2f} / {_ms(ages, 99):.2f} / {1000 * max(ages):.2f} | - |",
              f"| move_linear 2 mm at 0.25 m/s round trip, median (ms) | {_ms(bare, 50):.1f} | {_ms(ad, 50):.1f} | "
              f"{np.median(ad) / np.median(bare):.2f} |",
              f"| same, p95 (ms) | {_ms(bare, 95):.1f} | {_ms(ad, 95):.1f} | "
              f"{np.percentile(ad, 95) / np.percentile(bare, 95):.2f} |",
              "", f"State reads: {len(ages)} at random times; moves: {len(ad)} each. The adapter sends moves "
              "asynchronously from a worker process and watches arrival in the state stream (so stop() can "
              "interrupt a move), which adds the state period and inter-process hops to the round trip."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--moves", type=int, default=30)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "drivers.md"))
    a = ap.parse_args()
    rob = robot(a.moves, 2000)
    cam = camera(a.seconds)
    text = report(cam, rob, a.seconds)
    print(text)
    Path(a.out).write_text(text)


if __name__ == "__main__":
    main()
