"""A served production cell for the tests and ``bench/production.py``: the built-in production scene
with a scatter of N parts, the camera's and the hand-eye's true calibrations stored and active, the
upright part taught from a live frame, a production recipe saved.

The calibrations are the scene's truth (stored and activated as any calibration would be), so what
is measured is the production run itself.
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
from tests.support.served import Served, start_served
from tests.support.truth import activate_truth

CLEAR_POSE_UR = [0.45, -0.30, 0.25, math.pi, 0.0, 0.0]
"""Out of the camera's view: where the robot waits and the first picture is taken from."""


def production_config(tmp: Path, scene: dict[str, Any] | None = None, time_scale: float = 0.2,
                      count: int = 4, seed: int = 3) -> Path:
    """cell.yaml of the production cell (``cellctl config default --scene production``), its scene
    written to ``tmp`` with ``scatter.count``/``seed`` and the ``production`` overrides in ``scene``."""
    text = run_cellctl("config", "default", "--scene", "production", check=True).stdout
    cfg = yaml.safe_load(text)
    data = yaml.safe_load(BUILTIN_SCENES["production"].read_text())
    data["production"]["scatter"].update({"count": count, "seed": seed})
    for key, value in (scene or {}).items():
        if isinstance(value, dict):
            data["production"].setdefault(key, {}).update(value)
        else:
            data["production"][key] = value
    scene_path = tmp / "scene.yaml"
    scene_path.write_text(yaml.safe_dump(data))
    for dev in (cfg["cameras"]["cam0"], cfg["robots"]["robot0"], cfg["io"]["gripper0"]):
        dev["settings"]["scene"] = str(scene_path)
    cfg["robots"]["robot0"]["settings"]["motion_time_scale"] = time_scale
    cfg["io"]["gripper0"]["settings"]["time_scale"] = time_scale
    cfg["store"]["path"] = str(tmp / "cell.db")
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(cfg))
    store_truth(path, scene_path)
    return path


def store_truth(config_path: Path, scene_path: Path) -> None:
    """Store and activate the scene's true camera and eye-to-hand hand-eye (before the service starts)."""
    config = parse_config(yaml.safe_load(config_path.read_text()))
    truth = SimWorld(load_scene(scene_path)).truth()
    with open_store(config) as store:
        activate_truth(store, truth, "eye-to-hand", truth["targets"]["plate"]["T_tool_target"])


def pick_area_roi(truth: dict[str, Any], margin_mm: float = 35.0) -> list[float]:
    """The pick area (grown by ``margin_mm``, at the parts' top face) as an image ROI ``[u, v, w, h]``."""
    from calibration import geometry as g
    from calibration.io import camera_from_json

    cam = camera_from_json(truth["camera"], "truth")
    area, z = truth["pick_area"], truth["part"]["thickness_mm"]
    corners = [[x, y, z] for x in (area["x_mm"][0] - margin_mm, area["x_mm"][1] + margin_mm)
               for y in (area["y_mm"][0] - margin_mm, area["y_mm"][1] + margin_mm)]
    uv = cam.project(g.transform_points(g.invert(np.array(truth["T_base_cam"])), np.array(corners) * 1e-3))
    lo = np.maximum(uv.min(axis=0), 0.0)
    hi = np.minimum(uv.max(axis=0), [cam.width - 1.0, cam.height - 1.0])
    return [float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])]


def teach_recipe(http: httpx.Client, recipe_id: int = 1, search_roi: bool = False, **overrides: Any) -> dict[str, Any]:
    """Move clear of the view, teach the clear part from a live frame, store the production recipe
    (``search_roi``: search the pick area's part of the image only, as a cell's recipe would)."""
    r = http.post("/robots/robot0/move", json={"pose_ur": dict(zip(("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"),
                                                                 CLEAR_POSE_UR, strict=True)), "speed_m_s": 0.5})
    if r.status_code != 200:
        raise RuntimeError(f"the move out of the camera's view failed: {r.text}")
    truth = http.get("/sim/truth").json()
    u, v, w, h = truth["parts"][0]["roi_px"]
    roi = [u - 12, v - 12, w + 24, h + 24]
    model = http.post("/pick/teach", json={"roi": roi, "name": "bracket"})
    if model.status_code != 200:
        raise RuntimeError(f"teaching the part failed: {model.text}")
    recipe: dict[str, Any] = {
        "name": "bracket", "models": [model.json()], "plane_z_mm": 6.0, "grasp_z_mm": 0.0,
        "approach_height_mm": 40.0, "speed_m_s": 0.5, "capture_pose_ur": CLEAR_POSE_UR,
        "search": {"max_count": 40, "min_score": 0.7, "timeout_s": 5.0},
        "gripper": {"grip_width_mm": 30.0, "settle_s": 0.05, "device": {"io_id": "gripper0", "kind": "robotiq_2f"}},
        "place": truth["place_grid"],
    }
    if search_roi:
        recipe["search"]["roi"] = pick_area_roi(truth)
    recipe.update(overrides)
    saved = http.post("/recipes", json={"recipe_id": recipe_id, "recipe": recipe})
    if saved.status_code != 201:
        raise RuntimeError(f"saving the recipe failed: {saved.text}")
    return recipe


def serve(tmp: Path, config: Path) -> Served:
    return start_served(tmp, config)


def wait_ended(http: httpx.Client, timeout_s: float = 120.0) -> dict[str, Any]:
    """Poll GET /production until the run has ended; the last answer."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st: dict[str, Any] = http.get("/production").json()
        if st["ended_because"] is not None:
            return st
        time.sleep(0.2)
    raise TimeoutError(f"the run did not end in {timeout_s} s: {http.get('/production').json()}")


def wait_for(http: httpx.Client, check: Any, timeout_s: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st: dict[str, Any] = http.get("/production").json()
        if check(st):
            return st
        time.sleep(0.05)
    raise TimeoutError(f"not reached in {timeout_s} s: {http.get('/production').json()}")


def slot_error(part_T: list[list[float]], slot_T: np.ndarray) -> tuple[float, float]:
    """(mm, deg) between a part's true pose and its slot's."""
    from calibration import geometry as g

    rot, trans = g.transform_error(np.asarray(part_T), slot_T)
    return trans * 1e3, math.degrees(rot)
