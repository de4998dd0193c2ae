"""A virtual cell with its PLC servers on: the true calibrations active, the bracket taught.

The store is prepared before the cell starts (the virtual cell's true camera and hand-eye
calibrations, activated; recipe 1 = the bracket taught from a rendered frame), so whoever drives
it measures the PLC front ends and the pick pipeline, not a calibration routine. Two ways to run
it, the same PLC servers (Modbus TCP, OPC UA) on free loopback ports either way:

- ``in_process_plc``: the app in this process (``tests.support.app``), its lifespan starting
  the PLC servers; the PLC tests use it (no interpreter to start, no imports or warm-up to pay again);
- ``start_plc_cell``: ``cellctl serve`` as a child process, for ``bench/plc.py`` and an
  integrator's own PLC check.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from calibration import geometry as g
from cellctl.config import default_config_text, parse_config
from cellctl.pick.flow import Recipe, SearchSettings
from cellctl.pick.model import teach
from cellctl.store import open_store
from drivers.sim.world import world_for
from tests.support.served import Served, free_port, start_served
from tests.support.truth import activate_truth

if TYPE_CHECKING:  # the app is imported when a cell starts, not when a test module is collected
    import httpx

    from tests.support.app import AppCell

SEED = 11
RECIPE = 1


@dataclass
class PlcFacts:
    """A cell's Modbus TCP and OPC UA loopback ports, and the facts the tests check against."""

    modbus_port: int
    opcua_port: int
    opcua_url: str
    part_x_mm: float
    part_y_mm: float
    camera_calibration_id: int
    handeye_calibration_id: int
    enip_port: int = field(default=0, kw_only=True)
    """The EtherNet/IP tag server's port (0: not enabled)."""
    robot_socket_port: int = field(default=0, kw_only=True)
    """The robot socket's port (0: not enabled)."""


@dataclass
class PlcCell(PlcFacts):
    """A served cell with Modbus TCP and OPC UA on loopback ports, and the facts the tests check against."""

    served: Served


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
        cam_id, he_id = activate_truth(store, truth, "eye-in-hand", plate["T_base_target"])
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
    return path, {"part_x_mm": part.x_mm, "part_y_mm": part.y_mm, "camera_calibration_id": cam_id,
                  "handeye_calibration_id": he_id}


def start_plc_cell(tmp: Path, opcua: dict[str, Any] | None = None, modbus: bool = True) -> PlcCell:
    """Prepare the store, then start ``cellctl serve`` with both PLC servers on free loopback ports."""
    modbus_port, opcua_port = free_port(), free_port()
    path, facts = prepare_cell(tmp, plc_section(modbus_port, opcua_port, opcua, modbus))
    served = start_served(tmp, config=path, timeout_s=120.0)
    return PlcCell(modbus_port, opcua_port, f"opc.tcp://127.0.0.1:{opcua_port}/cellctl/", served=served, **facts)


@dataclass
class PlcApp(PlcFacts):
    """The same cell as ``PlcCell``, its app in this process (``app``) instead of a served process."""

    app: AppCell

    def http(self) -> httpx.Client:
        """A REST client with the engineer's token, on the app's running lifespan."""
        return self.app.http()


def plc_section(modbus_port: int, opcua_port: int, opcua: dict[str, Any] | None = None, modbus: bool = True,
                allow_motion: bool = False, enip_port: int = 0, robot_socket: dict[str, Any] | None = None,
                ) -> dict[str, Any]:
    """cell.yaml's ``plc`` section: the servers on 127.0.0.1 at the given ports (unit id 1); EtherNet/IP when
    ``enip_port``, the robot socket when ``robot_socket`` (its settings, with ``port``) is given."""
    plc: dict[str, Any] = {"modbus": {"enabled": modbus, "host": "127.0.0.1", "port": modbus_port, "unit_id": 1},
                           "opcua": {"enabled": True, "host": "127.0.0.1", "port": opcua_port, **(opcua or {})}}
    if enip_port:
        plc["ethernet_ip"] = {"enabled": True, "host": "127.0.0.1", "port": enip_port}
    if robot_socket:
        plc["robot_socket"] = {"enabled": True, "host": "127.0.0.1", **robot_socket}
    if allow_motion:
        plc["allow_motion"] = True
    return plc


@contextmanager
def in_process_plc(tmp: Path, opcua: dict[str, Any] | None = None, modbus: bool = True,
                   allow_motion: bool = False, all_front_ends: bool = False,
                   robot_socket: dict[str, Any] | None = None) -> Iterator[PlcApp]:
    """Prepare the store, then run the app in this process with the PLC servers on free loopback ports
    (``allow_motion``: ``plc.allow_motion``, the PLC's picks with robot motion; ``all_front_ends``: EtherNet/IP
    and the robot socket too, the socket with ``robot_socket``'s settings)."""
    from tests.support.app import in_process_cell

    modbus_port, opcua_port = free_port(), free_port()
    enip_port = free_port() if all_front_ends else 0
    socket_cfg = {"port": free_port(), **(robot_socket or {})} if all_front_ends else None
    path, facts = prepare_cell(tmp, plc_section(modbus_port, opcua_port, opcua, modbus, allow_motion, enip_port,
                                                socket_cfg))
    with in_process_cell(tmp, config=path) as app:
        wait_ready(app)
        yield PlcApp(modbus_port, opcua_port, f"opc.tcp://127.0.0.1:{opcua_port}/cellctl/", app=app,
                     enip_port=enip_port, robot_socket_port=socket_cfg["port"] if socket_cfg else 0, **facts)


def start_all_front_ends(tmp: Path, robot_socket: dict[str, Any] | None = None,
                         allow_motion: bool = False) -> PlcCell:
    """``cellctl serve`` with every PLC front end (Modbus, OPC UA, EtherNet/IP, robot socket) on loopback."""
    modbus_port, opcua_port, enip_port = free_port(), free_port(), free_port()
    socket_cfg = {"port": free_port(), **(robot_socket or {})}
    path, facts = prepare_cell(tmp, plc_section(modbus_port, opcua_port, None, True, allow_motion, enip_port,
                                                socket_cfg))
    served = start_served(tmp, config=path, timeout_s=120.0)
    return PlcCell(modbus_port, opcua_port, f"opc.tcp://127.0.0.1:{opcua_port}/cellctl/", served=served,
                   enip_port=enip_port, robot_socket_port=socket_cfg["port"], **facts)


READY_TIMEOUT_S = 180.0
"""As long as the service itself lets a request wait for the warm-up (``cellctl.warmup.READY_WAIT_S``)."""


def wait_ready(app: AppCell, timeout_s: float = READY_TIMEOUT_S) -> None:
    """Wait until ``/health`` no longer says ``starting``: the app's warm-up (loading the renderer's,
    matcher's and solver's compiled loops on a background thread) is done, as ``start_served`` and
    ``served_in_thread`` wait for it. Until then a pick in this process competes with the warm-up for
    the CPU, and the tests that time a pick against a motion (a 5 s move, a 20 s search) would measure
    the warm-up, not the cell, on a loaded machine."""
    deadline = time.monotonic() + timeout_s
    while app.client.get("/health").json().get("status") == "starting":
        if time.monotonic() > deadline:
            raise TimeoutError(f"the in-process PLC cell was still starting after {timeout_s:.0f} s")
        time.sleep(0.1)
