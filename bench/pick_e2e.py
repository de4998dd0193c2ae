"""Pick on the virtual cell end to end: trigger-to-answer latency of ``POST /pick`` and the pick
error in mm against the scene's truth, with calibrations made by the cell's own routines.

Starts ``cellctl serve`` (virtual cell), runs intrinsics-capture and handeye-capture, activates
both, teaches the bracket from a live frame, stores recipe 1, then calls ``POST /pick`` ``--calls``
times. Prints a markdown table (saved to ``bench/results/pick_e2e.md``). Target (issue 8):
trigger-to-answer p50 <= 50 ms. The reference for time is the same run's ``GET /health``
round trip (the HTTP floor on this machine).

    .venv/bin/python bench/pick_e2e.py [--calls 40]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--calls", type=int, default=40)
    args = ap.parse_args()
    from calibration import geometry as g
    from tests.support.served import CELLCTL, run_job, start_served, stop_served

    truth = json.loads(subprocess.run([CELLCTL, "sim", "truth"], capture_output=True, check=True, text=True).stdout)
    bracket = next(p for p in truth["parts"] if p["name"] == "bracket")
    from calibration.camera_model import CameraModel

    cam = CameraModel.from_dict(truth["camera"])
    u, v = cam.project(g.transform_points(g.invert(np.array(truth["T_base_cam"])),
                                          [bracket["x_mm"] * 1e-3, bracket["y_mm"] * 1e-3, 0.0]))[0]
    served = start_served(Path(tempfile.mkdtemp(prefix="bench-pick-")))
    try:
        with served.client(timeout_s=120) as http:
            for name, params in (("intrinsics-capture", {"views": 14}), ("handeye-capture", {"stations": 10})):
                job = run_job(http, name, params)
                assert job["state"] == "succeeded", job["error"]
                http.post(f"/calibrations/{job['result']['calibration_id']}/activate").raise_for_status()
            model = http.post("/pick/teach", json={"roi": [u - 100, v - 100, 200, 200], "name": "bracket"})
            model.raise_for_status()
            recipe = {"name": "bracket", "models": [model.json()], "plane_z_mm": 0.0, "grasp_z_mm": 5.0}
            http.post("/recipes", json={"recipe_id": 1, "recipe": recipe}).raise_for_status()
            http.post("/pick", json={"recipe_id": 1}).raise_for_status()  # warm-up
            client_ms, server_ms, errors_mm, health_ms = [], [], [], []
            for _ in range(args.calls):
                t0 = time.perf_counter()
                http.get("/health").raise_for_status()
                health_ms.append((time.perf_counter() - t0) * 1e3)
                t0 = time.perf_counter()
                r = http.post("/pick", json={"recipe_id": 1})
                client_ms.append((time.perf_counter() - t0) * 1e3)
                r.raise_for_status()
                ans = r.json()
                server_ms.append(ans["latency_ms"]["total"])
                p = ans["picks"][0]["pick_pose"]
                errors_mm.append(float(np.hypot(p["x_mm"] - bracket["x_mm"], p["y_mm"] - bracket["y_mm"])))
    finally:
        stop_served(served)
    c, s_, e, h = (np.array(x) for x in (client_ms, server_ms, errors_mm, health_ms))
    met = "met" if np.median(c) <= 50 else "MISSED"
    table = "\n".join([
        "| measure | p50 | p99 | target |",
        "| --- | --- | --- | --- |",
        f"| POST /pick trigger-to-answer, client side (ms) | {np.median(c):.1f} | {np.percentile(c, 99):.1f} "
        f"| p50 <= 50 ms: {met} |",
        f"| same, inside the service (grab + find + convert, ms) | {np.median(s_):.1f} "
        f"| {np.percentile(s_, 99):.1f} | |",
        f"| GET /health round trip, same run (ms) | {np.median(h):.2f} | {np.percentile(h, 99):.2f} | reference |",
        f"| pick position error vs truth (mm) | {np.median(e):.3f} | {np.percentile(e, 99):.3f} | |",
    ])
    text = (f"# Pick end to end on the virtual cell ({args.calls} calls)\n\nCommand: `.venv/bin/python "
            "bench/pick_e2e.py`. Calibrations from the cell's own intrinsics-capture and handeye-capture "
            "routines; the bracket taught from a live frame; error = distance in the table plane between the "
            "pick pose and the part's true position.\n\n" + table + "\n")
    print(text)
    (REPO / "bench" / "results").mkdir(exist_ok=True)
    (REPO / "bench" / "results" / "pick_e2e.md").write_text(text)


if __name__ == "__main__":
    main()
