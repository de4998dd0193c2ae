"""Run GigE Vision scenarios inside a private, loopback-only network namespace.

Aravis discovery broadcasts on every network interface, so no GigE test may run in the
machine's own namespace. :func:`run_scenario` re-executes this file under ``unshare -n`` (as root;
``unshare -rn`` otherwise): the child checks that ``lo`` is its only interface (and refuses to
run otherwise), brings ``lo`` up, starts ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` (a real GVCP/GVSP
peer) when the scenario needs it, drives the adapter and prints one JSON object on its last
stdout line.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
FAKE_CAMERA = "arv-fake-gv-camera-0.8"


def run_scenario(name: str, timeout_s: float = 90.0, *args: str) -> dict[str, Any]:
    """Run scenario ``name`` in a fresh network namespace and return its JSON result."""
    unshare = ["unshare", "-n"] if os.geteuid() == 0 else ["unshare", "-rn"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [*unshare, sys.executable, str(Path(__file__).resolve()), name, *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=env,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(
            f"netns scenario {name} failed (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        )
    result: dict[str, Any] = json.loads(lines[-1])
    return result


# -- inside the namespace ---------------------------------------------------------------------------


def _enter_loopback_only() -> None:
    names = [n for _, n in socket.if_nameindex()]
    if names != ["lo"]:
        raise SystemExit(f"refusing to run: this network namespace has interfaces {names}, not only lo")
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)


class FakeCamera:
    """``arv-fake-gv-camera-0.8`` on 127.0.0.1, stopped by its pid."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> FakeCamera:
        self.proc = subprocess.Popen(
            [FAKE_CAMERA, "-i", "127.0.0.1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        time.sleep(0.5)
        return self

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=5)
        self.proc = None


def _timed(fn: Callable[[], Any]) -> tuple[Any, float, str]:
    t0 = time.monotonic()
    try:
        return fn(), time.monotonic() - t0, ""
    except Exception as exc:
        return None, time.monotonic() - t0, f"{type(exc).__name__}: {exc}"


def scenario_gige() -> dict[str, Any]:
    from drivers.camera.aravis import AravisCamera

    out: dict[str, Any] = {}
    cam_peer = FakeCamera().start()
    try:
        for key in ("127.0.0.1", "Aravis-Fake-GV01", "GV01"):
            cam = AravisCamera("cam0", {"device_id": key, "interfaces": ["GigEVision"], "frame_rate_hz": 20})
            cam.open()
            f = cam.grab(5.0)
            out[f"open_{key}"] = {
                "shape": list(f.pixels.shape),
                "dtype": str(f.pixels.dtype),
                "serial": cam.settings()["serial"],
                "age_s": time.time() - f.timestamp_s,
                "camera_timestamp_ns": f.metadata["camera_timestamp_ns"],
            }
            cam.close()
        cam = AravisCamera(
            "cam0",
            {
                "device_id": "127.0.0.1",
                "interfaces": ["GigEVision"],
                "pixel_format": "Mono16",
                "roi": {"x_px": 16, "y_px": 8, "width_px": 256, "height_px": 128},
                "exposure_us": 5000,
                "gain_db": 3,
                "frame_rate_hz": 30,
            },
        )
        cam.open()
        frames = [cam.grab(5.0) for _ in range(10)]
        s = cam.settings()
        out["configured"] = {
            "shape": list(frames[-1].pixels.shape),
            "dtype": str(frames[-1].pixels.dtype),
            "settings": s,
            "ids": [f.frame_id for f in frames],
            "health": cam.health().as_dict(),
        }
        cam.set_trigger("software")
        time.sleep(0.3)
        before = cam.health().frames_received or 0
        time.sleep(0.5)
        idle = (cam.health().frames_received or 0) - before
        f, dt, err = _timed(lambda: cam.grab(3.0))
        out["software_trigger"] = {"frames_without_trigger": idle, "grab_s": dt, "error": err}
        _, _, err = _timed(lambda: cam.set_trigger("hardware"))
        out["hardware_trigger_error"] = err
        cam.close()
    finally:
        cam_peer.kill()
    return out


def scenario_faults() -> dict[str, Any]:
    from drivers.camera.aravis import AravisCamera

    out: dict[str, Any] = {}
    settings = {
        "device_id": "127.0.0.1",
        "interfaces": ["GigEVision"],
        "frame_rate_hz": 20,
        "stall_timeout_s": 0.5,
        "reconnect_initial_s": 0.2,
        "reconnect_max_s": 1.0,
    }
    cam = AravisCamera("cam0", settings)
    _, dt, err = _timed(cam.open)  # no camera yet: connect timeout
    out["connect_without_camera"] = {"s": dt, "error": err}
    # a peer on the GVCP port that answers every packet with bytes that follow no protocol
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 3956))
    stop = threading.Event()

    def garbage() -> None:
        udp.settimeout(0.05)
        while not stop.is_set():
            try:
                _, addr = udp.recvfrom(2048)
            except TimeoutError:
                continue
            udp.sendto(b"\x00\x00\x00\x03garbage-not-gvcp\xff" * 4, addr)

    th = threading.Thread(target=garbage, daemon=True)
    th.start()
    _, dt, err = _timed(AravisCamera("cam0", settings).open)
    out["garbage_peer"] = {"s": dt, "error": err}
    stop.set()
    th.join()
    udp.close()
    peer = FakeCamera().start()
    cam = AravisCamera("cam0", settings)
    try:
        cam.open()
        cam.grab(5.0)
        peer.kill()  # the camera dies mid-stream
        t0 = time.monotonic()
        _, dt, err = _timed(lambda: cam.grab(1.0))
        out["grab_after_kill"] = {"s": dt, "error": err}
        while cam.health().available and time.monotonic() - t0 < 10:
            time.sleep(0.05)
        out["unavailable_after_s"] = time.monotonic() - t0
        out["health_down"] = cam.health().as_dict()
        peer = FakeCamera().start()
        t1 = time.monotonic()
        f, dt, err = _timed(lambda: cam.grab(15.0))
        out["recovered"] = {"s": time.monotonic() - t1, "error": err, "health": cam.health().as_dict()}
    finally:
        cam.close()
        peer.kill()
    return out


def scenario_bench(seconds: str = "10", rates: str = "100,300", rounds: str = "2") -> dict[str, Any]:
    """Frames/s and lost frames: the adapter vs a bare Aravis loop, same camera, same run.

    Per rate, ``rounds`` alternating runs of each client share ``seconds`` (so a change of the
    machine's load hits both alike); counts are summed over the rounds.
    """
    import gi
    import numpy as np

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    from drivers.camera.aravis import AravisCamera

    def bare(rate: float, secs: float) -> dict[str, float]:
        """Pop a buffer, copy it to numpy, push it back: the least a client can do."""
        Aravis.disable_interface("USB3Vision")
        Aravis.disable_interface("Fake")
        Aravis.enable_interface("GigEVision")
        cam = Aravis.Camera.new("127.0.0.1")
        cam.set_frame_rate(rate)
        stream = cam.create_stream(None, None)
        for _ in range(8):
            stream.push_buffer(Aravis.Buffer.new_allocate(cam.get_payload()))
        cam.start_acquisition()
        n_ok = n_bad = lost = 0
        last_id: int | None = None
        cpu0 = time.process_time()
        t0 = time.monotonic()
        while time.monotonic() - t0 < secs:
            buf = stream.timeout_pop_buffer(100_000)
            if buf is None:
                continue
            fid = int(buf.get_frame_id())
            if last_id is not None and 0 < fid - last_id - 1 < 1000:
                lost += fid - last_id - 1
            last_id = fid
            if buf.get_status() == Aravis.BufferStatus.SUCCESS:
                np.frombuffer(buf.get_data(), np.uint8).copy()
                n_ok += 1
            else:
                n_bad += 1
            stream.push_buffer(buf)
        elapsed = time.monotonic() - t0
        cpu = time.process_time() - cpu0
        cam.stop_acquisition()
        return {"frames": n_ok, "incomplete": n_bad, "lost": lost, "elapsed_s": elapsed, "cpu_s": cpu}

    def adapter(rate: float, secs: float, latencies: list[float]) -> dict[str, float]:
        """The adapter, with the application grabbing every frame it can."""
        cam = AravisCamera(
            "cam0", {"device_id": "127.0.0.1", "interfaces": ["GigEVision"], "frame_rate_hz": rate, "buffer_count": 8}
        )
        cam.open()
        cam.grab(5.0)
        h0 = cam.health().as_dict()
        n = 0
        cpu0 = time.process_time()
        t0 = time.monotonic()
        while time.monotonic() - t0 < secs:
            try:
                f = cam.grab(1.0)
            except Exception:
                continue
            n += 1
            latencies.append(time.time() - f.timestamp_s)
        elapsed = time.monotonic() - t0
        cpu = time.process_time() - cpu0
        h1 = cam.health().as_dict()
        cam.close()
        return {
            "frames": h1["frames_received"] - h0["frames_received"],
            "grabbed": n,
            "incomplete": h1["frames_incomplete"] - h0["frames_incomplete"],
            "lost": h1["frames_lost"] - h0["frames_lost"],
            "elapsed_s": elapsed,
            "cpu_s": cpu,
        }

    def total(runs: list[dict[str, float]]) -> dict[str, float]:
        return {k: sum(r[k] for r in runs) for k in runs[0]}

    n_rounds = int(rounds)
    secs = float(seconds) / n_rounds
    out: dict[str, Any] = {"duration_s": float(seconds), "rounds": n_rounds, "rates": {}}
    peer = FakeCamera().start()
    try:
        for rate in (float(r) for r in rates.split(",")):
            b_runs: list[dict[str, float]] = []
            a_runs: list[dict[str, float]] = []
            latencies: list[float] = []
            for _ in range(n_rounds):
                b_runs.append(bare(rate, secs))
                a_runs.append(adapter(rate, secs, latencies))
            b, a = total(b_runs), total(a_runs)
            out["rates"][str(int(rate))] = {
                "bare": {
                    "fps": b["frames"] / b["elapsed_s"],
                    "frames": b["frames"],
                    "incomplete": b["incomplete"],
                    "lost": b["lost"],
                    "cpu_ms_per_frame": 1000 * b["cpu_s"] / max(1.0, b["frames"]),
                },
                "adapter": {
                    "fps_received": a["frames"] / a["elapsed_s"],
                    "fps_grabbed": a["grabbed"] / a["elapsed_s"],
                    "incomplete": a["incomplete"],
                    "lost": a["lost"],
                    "cpu_ms_per_frame": 1000 * a["cpu_s"] / max(1.0, a["frames"]),
                    "latency_ms_median": 1000 * float(np.median(latencies)) if latencies else None,
                    "latency_ms_p99": 1000 * float(np.percentile(latencies, 99)) if latencies else None,
                },
                "per_round_fps": {
                    "bare": [r["frames"] / r["elapsed_s"] for r in b_runs],
                    "adapter": [r["frames"] / r["elapsed_s"] for r in a_runs],
                },
            }
    finally:
        peer.kill()
    return out


def scenario_contract() -> dict[str, Any]:
    """The camera contract checks (``camera_contract.py``) over GigE Vision against the fake camera."""
    from drivers.camera.aravis import AravisCamera
    from tests.drivers.camera_contract import run_all

    peer = FakeCamera().start()
    try:
        return run_all(lambda: AravisCamera("cam0", {"device_id": "127.0.0.1", "interfaces": ["GigEVision"],
                                                    "frame_rate_hz": 20}))
    finally:
        peer.kill()


SCENARIOS: dict[str, Callable[..., dict[str, Any]]] = {
    "gige": scenario_gige,
    "contract": scenario_contract,
    "faults": scenario_faults,
    "bench": scenario_bench,
}


def main() -> None:
    _enter_loopback_only()
    name, args = sys.argv[1], sys.argv[2:]
    result = SCENARIOS[name](*args)
    print(json.dumps(result, default=str), flush=True)


if __name__ == "__main__":
    main()
