"""The conveyor cell for the tests and ``bench/conveyor.py``: the built-in conveyor scene (its parts'
seed and the belt's speed set), the camera's, hand-eye's and belt's true calibrations stored and
active, a part taught from a still frame (the belt at 0), a belt recipe saved.

The calibrations are the scene's truth (stored and activated as any would be), so what is measured is
the tracking run itself; ``tests/conveyor/test_calibrate.py`` checks ``conveyor-calibrate`` against the
same truth.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import yaml

from cellctl.config import parse_config
from cellctl.store import open_store
from drivers.sim.scene import BUILTIN_SCENES, load_scene
from drivers.sim.world import SimWorld
from tests.support.forked import run_cellctl
from tests.support.truth import activate_truth

WAIT_POSE_UR = [0.55, -0.30, 0.25, math.pi, 0.0, 0.0]


def conveyor_config(tmp: Path, time_scale: float = 1.0, seed: int = 11, count: int = 60,
                    belt: dict[str, Any] | None = None, calibrate_belt: bool = True) -> Path:
    """cell.yaml of the conveyor cell (``cellctl config default --scene conveyor``) with its scene in ``tmp``
    (the parts' ``seed`` and ``count``, ``belt`` overrides of the scene's ``conveyor`` section), the belt
    at 0 mm/s (a test sets its speed), and the true calibrations stored and active."""
    text = run_cellctl("config", "default", "--scene", "conveyor", "--belt-speed-mm-s", "0", check=True).stdout
    cfg = yaml.safe_load(text)
    data = yaml.safe_load(BUILTIN_SCENES["conveyor"].read_text())
    data["conveyor"]["parts"].update({"seed": seed, "count": count})
    data["conveyor"]["speed_mm_s"] = 0.0
    data["conveyor"].update(belt or {})
    scene_path = tmp / "scene.yaml"
    scene_path.write_text(yaml.safe_dump(data))
    for dev in (cfg["cameras"]["cam0"], cfg["robots"]["robot0"], cfg["io"]["gripper0"], cfg["conveyors"]["belt0"]):
        dev["settings"]["scene"] = str(scene_path)
    cfg["robots"]["robot0"]["settings"]["motion_time_scale"] = time_scale
    cfg["io"]["gripper0"]["settings"]["time_scale"] = time_scale
    cfg["store"]["path"] = str(tmp / "cell.db")
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    store_truth(path, scene_path, calibrate_belt)
    return path


def store_truth(config_path: Path, scene_path: Path, calibrate_belt: bool = True) -> None:
    """Store and activate the scene's true camera, eye-to-hand hand-eye and (``calibrate_belt``) belt."""
    config = parse_config(yaml.safe_load(config_path.read_text()))
    scene = load_scene(scene_path)
    truth = SimWorld(scene).truth()
    with open_store(config) as store:
        activate_truth(store, truth, "eye-to-hand", truth["targets"]["plate"]["T_tool_target"])
        if calibrate_belt:
            assert scene.conveyor is not None
            b = store.save_calibration("conveyor", "belt0", "robot0",
                                       {"direction_base": [1.0, 0.0, 0.0], "ticks_per_m": scene.conveyor.ticks_per_m,
                                        "sigma_ticks_per_m": 0.0, "sigma_direction_deg": 0.0,
                                        "verdict": {"ok": True, "problems": []}}, {}, creator="test", note="truth")
            store.activate(b.id, "test")


def teach_belt_recipe(http: httpx.Client, recipe_id: int = 1, **overrides: Any) -> dict[str, Any]:
    """With the belt still: the arm out of view, the part in view taught, the belt recipe stored."""
    r = http.post("/robots/robot0/move", json={"pose_ur": dict(zip(("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"),
                                                                 WAIT_POSE_UR, strict=True)), "speed_m_s": 1.0})
    if r.status_code != 200:
        raise RuntimeError(f"the move out of the camera's view failed: {r.text}")
    truth = http.get("/sim/truth").json()
    seen = [p for p in truth["parts"] if p["roi_px"] is not None and p["roi_px"][2] > 40 and p["roi_px"][3] > 40]
    u, v, w, h = seen[0]["roi_px"]
    model = http.post("/pick/teach", json={"roi": [u - 12, v - 12, w + 24, h + 24], "name": "bracket"})
    if model.status_code != 200:
        raise RuntimeError(f"teaching the part failed: {model.text}")
    recipe: dict[str, Any] = {
        "name": "bracket on the belt", "models": [model.json()], "plane_z_mm": 6.0, "grasp_z_mm": 0.0,
        "approach_height_mm": 30.0, "speed_m_s": 1.0,
        "search": {"max_count": 10, "min_score": 0.7, "timeout_s": 2.0, "roi": lane_roi(truth)},
        "gripper": {"grip_width_mm": 30.0, "settle_s": 0.02, "device": {"io_id": "gripper0", "kind": "robotiq_2f"}},
        "place": truth["place_grid"], "source": {"kind": "conveyor", "conveyor_id": "belt0"},
    }
    recipe.update(overrides)
    saved = http.post("/recipes", json={"recipe_id": recipe_id, "recipe": recipe})
    if saved.status_code != 201:
        raise RuntimeError(f"saving the recipe failed: {saved.text}")
    return recipe


def lane_roi(truth: dict[str, Any], margin_px: float = 50.0) -> list[float]:
    """The parts' lane of the belt in the image (not the chessboard beside it), clear of the image's left and
    right edges by ``margin_px`` (a part cut by the edge is seen in the next picture whole)."""
    from calibration import geometry as g
    from calibration.io import camera_from_json

    cam = camera_from_json(truth["camera"], "truth")
    lane = (-78.0, 78.0)
    corners = np.array([[x, y, 6.0] for x in (-200.0, 400.0) for y in lane]) * 1e-3
    uv = cam.project(g.transform_points(g.invert(np.array(truth["T_base_cam"])), corners))
    v0, v1 = max(0.0, float(uv[:, 1].min())), min(cam.height - 1.0, float(uv[:, 1].max()))
    return [margin_px, v0, cam.width - 2 * margin_px, v1 - v0]


def set_speed(http: httpx.Client, speed_mm_s: float) -> None:
    r = http.put("/sim/conveyors/belt0/speed", json={"speed_mm_s": speed_mm_s})
    if r.status_code != 200:
        raise RuntimeError(f"setting the belt's speed failed: {r.text}")


def wait_ended(http: httpx.Client, timeout_s: float = 120.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st: dict[str, Any] = http.get("/production").json()
        if st["ended_because"] is not None:
            return st
        time.sleep(0.1)
    raise TimeoutError(f"the run did not end in {timeout_s} s: {http.get('/production').json()}")


def placement_errors(truth: dict[str, Any]) -> list[tuple[float, float]]:
    """(mm, deg) of every placed part against the slot nearest it (the grid of the truth), xy and yaw."""
    from calibration import geometry as g

    grid = truth["place_grid"]
    origin = g.ur_pose_to_transform(grid["origin_ur"])
    slots = [origin @ g.make_transform(np.eye(3), [c * grid["pitch_mm"][0] * 1e-3, r * grid["pitch_mm"][1] * 1e-3, 0.0])
             for r in range(grid["rows"]) for c in range(grid["cols"])]
    out = []
    for p in truth["parts"]:
        if p["state"] != "placed":
            continue
        T = np.asarray(p["T_base_part"])
        slot = min(slots, key=lambda S: float(np.linalg.norm(S[:2, 3] - T[:2, 3])))
        d_mm = float(np.linalg.norm(slot[:2, 3] - T[:2, 3])) * 1e3
        yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]) - math.atan2(slot[1, 0], slot[0, 0]))
        out.append((d_mm, abs((yaw + 180.0) % 360.0 - 180.0)))
    return out
