"""GigE Vision test scenarios, run inside a private, loopback-only network namespace.

:func:`run_scenario` re-executes this file there (``drivers.peers.netns``); the child drives the
adapter against ``arv-fake-gv-camera`` when the scenario needs it and prints one JSON object on
its last stdout line.
"""

from __future__ import annotations

import json
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from drivers.peers.netns import REPO, FakeCamera, enter_loopback_only, run_in_loopback_namespace

__all__ = ["REPO", "run_scenario"]


def run_scenario(name: str, timeout_s: float = 90.0, *args: str) -> dict[str, Any]:
    """Run scenario ``name`` in a fresh network namespace and return its JSON result."""
    return run_in_loopback_namespace(Path(__file__).resolve(), name, *args, timeout_s=timeout_s)


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


def scenario_controls(tmp: str) -> dict[str, Any]:
    """``GET``/``PUT /cameras/cam0/controls`` of the service (in process) on arv-fake-gv-camera over GigE Vision."""
    import yaml

    from cellctl.config import default_config_text
    from tests.support.app import in_process_cell

    cfg = yaml.safe_load(default_config_text())
    cfg["cameras"]["cam0"] = {"kind": "aravis", "settings": {"device_id": "127.0.0.1", "interfaces": ["GigEVision"],
                                                             "frame_rate_hz": 20}}
    cfg["store"]["path"] = str(Path(tmp) / "cell.db")
    path = Path(tmp) / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out: dict[str, Any] = {}
    peer = FakeCamera().start()
    try:
        with in_process_cell(Path(tmp), path) as a, a.http() as http:
            out["get"] = http.get("/cameras/cam0/controls").json()
            r = http.put("/cameras/cam0/controls", json={"exposure_us": 4000, "gain_db": 2, "trigger": "software"})
            out["put"] = {"status": r.status_code, "body": r.json()}
            out["settings"] = http.get("/cameras/cam0/settings").json()
            t0 = time.monotonic()
            out["image_status"] = http.get("/cameras/cam0/image", params={"format": "png"}).status_code
            out["image_s"] = time.monotonic() - t0
            r = http.put("/cameras/cam0/controls", json={"exposure_us": 50_000_000})
            out["too_long"] = {"status": r.status_code, "body": r.json()}
            r = http.put("/cameras/cam0/controls", json={"trigger": "free_run"})
            out["free_run"] = {"status": r.status_code, "trigger": r.json()["controls"]["trigger"]["value"]}
            audit = http.get("/audit", params={"limit": 20}).json()
            out["audit"] = [e for e in audit if e["action"] == "camera.controls"]
    finally:
        peer.kill()
    return out


SCENARIOS: dict[str, Callable[..., dict[str, Any]]] = {
    "controls": scenario_controls,
    "gige": scenario_gige,
    "contract": scenario_contract,
    "faults": scenario_faults,
}


def main() -> None:
    enter_loopback_only()
    name, args = sys.argv[1], sys.argv[2:]
    result = SCENARIOS[name](*args)
    print(json.dumps(result, default=str), flush=True)


if __name__ == "__main__":
    main()
