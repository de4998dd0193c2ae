"""The camera half of ``bench/drivers.py``, run inside a loopback-only network namespace.

``python bench/drivers_gige.py SECONDS RATES ROUNDS`` (started by ``bench/drivers.py`` through
``drivers.peers.netns.run_in_loopback_namespace``) prints one JSON object: frames/s, lost and
incomplete frames of the adapter and of a bare Aravis loop on the same fake camera.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

# this folder holds bench/drivers.py, which would shadow the drivers package
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.peers.netns import FakeCamera, enter_loopback_only  # noqa: E402


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


if __name__ == "__main__":
    enter_loopback_only()
    print(json.dumps(scenario_bench(*sys.argv[1:]), default=str), flush=True)
