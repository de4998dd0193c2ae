"""A served virtual cell with its PLC servers on: the true calibrations active, the bracket taught.

The store is prepared before ``cellctl serve`` starts (the virtual cell's true camera and hand-eye
calibrations, activated; recipe 1 = the bracket taught from a rendered frame), so whoever drives
it — the PLC tests, ``bench/plc.py``, an integrator's own PLC check — measures the PLC front ends
and the pick pipeline, not a calibration routine. Loopback only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration import geometry as g
from cellctl.config import default_config_text, parse_config
from cellctl.pick.flow import Recipe, SearchSettings
from cellctl.pick.model import teach
from cellctl.store import open_store
from drivers.sim.world import world_for
from tests.support.served import Served, free_port, start_served

SEED = 11
RECIPE = 1


@dataclass
class PlcCell:
    """A served cell with Modbus TCP and OPC UA on loopback ports, and the facts the tests check against."""

    served: Served
    modbus_port: int
    opcua_port: int
    opcua_url: str
    part_x_mm: float
    part_y_mm: float
    camera_calibration_id: int
    handeye_calibration_id: int


def prepare_cell(tmp: Path, plc: dict[str, Any]) -> tuple[Path, dict[str, Any]]:
    """Write cell.yaml (virtual cell + ``plc`` section) and its store; returns the config path and facts."""
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp / "cell.db")}
    data["cameras"]["cam0"]["settings"]["seed"] = SEED
    data["robots"]["robot0"]["settings"]["seed"] = SEED
    data["plc"] = plc
    config = parse_config(data)
    world = world_for(None, SEED)
    truth = world.truth()
    plate = next(t for t in truth["targets"].values() if t["attached_to"] == "base")
    store = open_store(config)
    try:
        cam = store.save_calibration("camera", "cam0", None, truth["camera"], {}, creator="test", note="truth")
        he = {"setup": "eye-in-hand", "T_tool_cam": truth["T_tool_cam"], "T_base_target": plate["T_base_target"],
              "uncertainty": {"covariance": (np.eye(6) * 1e-10).tolist()}, "pixel_sigma_px": 0.05,
              "robot_noise": {"sigma_mm": 0.02, "sigma_deg": 0.005}}
        h = store.save_calibration("handeye", "cam0", "robot0", he, {}, creator="test", note="truth")
        store.activate(cam.id, "test")
        store.activate(h.id, "test")
        part = world.scene.parts[0]
        T_cam_base = g.invert(world.T_base_cam())
        u, v = world.camera_model.project(g.transform_points(T_cam_base, [part.x_mm * 1e-3, part.y_mm * 1e-3, 0.0]))[0]
        model = teach(world.render(), (float(u) - 100, float(v) - 100, 200, 200), mode="shape", name="bracket")
        # A generous search timeout: on a loaded shared machine the default 1 s can cut the search short.
        recipe = Recipe(name="bracket", models=[model.to_dict()], plane_z_mm=0.0, grasp_z_mm=5.0,
                        approach_height_mm=40.0, search=SearchSettings(timeout_s=20.0))
        store.save_recipe(RECIPE, "bracket", recipe.model_dump(mode="json"), "test")
    finally:
        store.close()
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, {"part_x_mm": part.x_mm, "part_y_mm": part.y_mm, "camera_calibration_id": cam.id,
                  "handeye_calibration_id": h.id}


def start_plc_cell(tmp: Path, opcua: dict[str, Any] | None = None, modbus: bool = True) -> PlcCell:
    """Prepare the store, then start ``cellctl serve`` with both PLC servers on free loopback ports."""
    modbus_port, opcua_port = free_port(), free_port()
    plc = {"modbus": {"enabled": modbus, "host": "127.0.0.1", "port": modbus_port, "unit_id": 1},
           "opcua": {"enabled": True, "host": "127.0.0.1", "port": opcua_port, **(opcua or {})}}
    path, facts = prepare_cell(tmp, plc)
    served = start_served(tmp, config=path, timeout_s=120.0)
    return PlcCell(served, modbus_port, opcua_port, f"opc.tcp://127.0.0.1:{opcua_port}/cellctl/", **facts)
