"""Every failed cycle's frame is kept on disk with its record, within the cell's bounds (the oldest
deleted first), and served by the records route, also after a restart; the other cycles' frames
are served while the service's frame cache holds them."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from tests.support.app import in_process_cell
from tests.support.production_cell import production_config, teach_recipe, wait_ended

KEEP = 2


def png(content: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(content, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


@pytest.mark.slow  # an in-process production cell (motion at 0.2 x real time) and its restart: ~15 s
def test_failed_cycles_keep_their_frames_on_disk_bounded_and_served(tmp_path: Path) -> None:
    config = production_config(tmp_path, count=3, scene={"gripper": {"fail_probability": 0.5}})
    cfg = yaml.safe_load(config.read_text())
    frames_dir = tmp_path / "failures"
    cfg["production"] = {"failure_frames_dir": str(frames_dir), "failure_frames_max_count": KEEP}
    config.write_text(yaml.safe_dump(cfg))
    with in_process_cell(tmp_path, config) as cell:
        http = cell.http()
        teach_recipe(http, gripper={"grip_width_mm": 30.0, "settle_s": 0.05,
                                    "device": {"io_id": "gripper0", "kind": "robotiq_2f", "retries": 8}})
        run_id = http.post("/production/start", json={"recipe_id": 1}).json()["run_id"]
        end = wait_ended(http)
        assert end["ended_because"] == "area_empty" and end["counters"]["placed"] == 3, end
        cycles = http.get(f"/production/runs/{run_id}/cycles").json()
        failed = [c["n"] for c in cycles if c["result"] != "placed"]
        placed = [c["n"] for c in cycles if c["result"] == "placed"]
        assert len(failed) >= 1 + 2, [c["result"] for c in cycles]  # grip failures and the final 'empty'
        assert all(c["frame_kept"] == (c["result"] != "placed") for c in cycles), cycles
        assert cycles[0]["frame_url"] == f"/production/runs/{run_id}/cycles/1/frame.png"
        # On disk: the newest KEEP failures, each a PNG and its JSON (record and matches).
        kept = sorted(p.stem for p in frames_dir.glob("*.png"))
        assert kept == [f"run{run_id:09d}-cycle{n:06d}" for n in failed[-KEEP:]], kept
        assert sorted(p.stem for p in frames_dir.glob("*.json")) == kept
        url = f"/production/runs/{run_id}/cycles/{{}}/frame.png"
        newest = http.get(url.format(failed[-1]))
        assert newest.status_code == 200 and newest.headers["content-type"] == "image/png"
        raw = http.get(url.format(failed[-1]), params={"annotated": "false"})
        assert raw.status_code == 200
        shown, pixels = png(newest.content), png(raw.content)
        assert pixels.ndim == 2 and shown.shape[:2] == pixels.shape and shown.ndim == 3
        pruned = http.get(url.format(failed[0]))
        assert pruned.status_code == 404 and pruned.json()["error"]["code"] == "unknown_frame", pruned.text
        # A placed cycle's frame is served from the last frames, while the cache holds it.
        assert http.get(url.format(placed[-1])).status_code == 200
        assert http.get(url.format(999)).json()["error"]["code"] == "unknown_cycle"
    with in_process_cell(tmp_path, config) as cell:
        http = cell.http()
        again = http.get(url.format(failed[-1]), params={"annotated": "false"})
        assert again.status_code == 200 and np.array_equal(png(again.content), pixels)  # lossless, from disk
        gone = http.get(url.format(placed[-1]))  # the new service's frame cache is empty
        assert gone.status_code == 404 and gone.json()["error"]["code"] == "unknown_frame"
