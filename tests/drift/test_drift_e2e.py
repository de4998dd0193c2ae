"""The drift loop end to end on the virtual production cell, in this process: a bump of the camera
raises the alarm on REST, /metrics and the Modbus STATUS bit; the re-solve stores a new hand-eye that
an engineer activates; the cell then maps within 0.1 mm of the truth again and a run places accurately."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np
import yaml
from pymodbus.client import ModbusTcpClient

from calibration import geometry as g
from calibration.io import camera_from_json
from cellctl.plc import modbus_map as mm
from tests.support.app import in_process_cell
from tests.support.ports import free_port
from tests.support.production_cell import production_config, slot_error, teach_recipe, wait_ended, wait_for

BASELINE = 5


def drift_cell(tmp: Path, modbus_port: int, opcua_port: int) -> Path:
    path = production_config(tmp, count=2)
    cfg = yaml.safe_load(path.read_text())
    cfg["drift"].update({"every_s": 0, "every_cycles": 1, "baseline_checks": BASELINE, "pause_on_alarm": True})
    cfg["plc"] = {"modbus": {"enabled": True, "host": "127.0.0.1", "port": modbus_port, "unit_id": 1},
                  "opcua": {"enabled": True, "host": "127.0.0.1", "port": opcua_port}}
    path.write_text(yaml.safe_dump(cfg))
    return path


def map_error_mm(http: object, truth: dict, xy_mm: tuple[float, float]) -> float:
    """How far the cell maps the pixel where the (bumped) camera truly sees base point ``xy_mm`` on the table."""
    cam = camera_from_json(truth["camera"], "truth")
    p = np.array([[xy_mm[0] * 1e-3, xy_mm[1] * 1e-3, 0.0]])
    uv = cam.project(g.transform_points(g.invert(np.array(truth["T_base_cam"])), p))[0]
    r = http.post("/map", json={"u_px": float(uv[0]), "v_px": float(uv[1]), "plane_z_mm": 0.0})  # type: ignore[attr-defined]
    assert r.status_code == 200, r.text
    return float(np.hypot(r.json()["x_mm"] - xy_mm[0], r.json()["y_mm"] - xy_mm[1]))


def status_bits(port: int) -> int:
    with ModbusTcpClient("127.0.0.1", port=port) as client:
        r = client.read_holding_registers(mm.address("STATUS"), count=1, device_id=1)
        assert not r.isError(), r
        return int(r.registers[0])


def opcua_drift(port: int) -> tuple[bool, float, str]:
    """(Cell/DriftAlarm, Cell/DriftMm, VisionSystem SystemState's description) read by an OPC UA client."""
    from asyncua import Client

    from cellctl.plc.opcua_mv.nodeset import NAMESPACE_MV
    from cellctl.plc.opcua_server import NAMESPACE

    async def run() -> tuple[bool, float, str]:
        async with Client(f"opc.tcp://127.0.0.1:{port}/cellctl/", timeout=30) as client:
            idx = await client.get_namespace_index(NAMESPACE)
            cell = await client.nodes.objects.get_child(f"{idx}:Cell")
            alarm = await (await cell.get_child(f"{idx}:DriftAlarm")).read_value()
            drift_mm = await (await cell.get_child(f"{idx}:DriftMm")).read_value()
            await client.load_data_type_definitions()
            ns = await client.get_namespace_index(NAMESPACE_MV)
            system = await (await client.nodes.objects.get_child([f"{ns}:VisionSystem", f"{ns}:SystemState"])
                            ).read_value()
            return bool(alarm), float(drift_mm), str(system.StateDescription)

    return asyncio.run(run())


def metric(http: object, name: str) -> float:
    text = http.get("/metrics").text  # type: ignore[attr-defined]
    line = next(ln for ln in text.splitlines() if ln.startswith(name + "{"))
    return float(line.rsplit(" ", 1)[1])


def test_bump_alarm_resolve_activate_accurate_again(tmp_path: Path) -> None:
    port, opcua_port = free_port(), free_port()
    with in_process_cell(tmp_path, drift_cell(tmp_path, port, opcua_port)) as app:
        http = app.http()
        recipe = teach_recipe(http)  # the arm out of the camera's view, the part taught, a recipe saved
        assert http.get("/drift").json()["limits"]["ucl_mm"] is None  # no limits before the baseline
        for _ in range(BASELINE):
            rec = http.post("/drift/check").json()
            assert rec["state"] == "baseline" and rec["drift_mm"] < 0.05 and rec["seen"] == 6, rec
        rec = http.post("/drift/check").json()
        assert rec["state"] == "ok" and rec["rule"] is None, rec
        body = http.get("/drift").json()
        assert body["state"] == "ok" and len(body["records"]) == BASELINE + 1
        assert set(body["limits"]) >= {"center_mm", "ucl_mm", "mr_ucl_mm"}
        assert set(body["records"][-1]) >= {"t", "drift_px", "drift_mm", "drift_deg", "state", "rule"}
        assert metric(http, "cellctl_drift_alarm") == 0.0
        assert not status_bits(port) & (1 << mm.STATUS_BITS["DRIFT_ALARM"])

        # The bracket is bumped: 0.3 mm along x and 0.05 deg about z.
        r = http.post("/sim/faults", json={"camera_shift_mm": [0.3, 0.0, 0.0], "camera_rot_deg": [0.0, 0.0, 0.05]})
        assert r.status_code == 200, r.text
        truth = http.get("/sim/truth").json()
        assert map_error_mm(http, truth, (450.0, 0.0)) > 0.25  # the cell now maps off
        rec = http.post("/drift/check").json()
        assert rec["state"] == "alarm" and rec["rule"] == "beyond_3sigma", rec
        assert rec["drift_mm"] > 0.2 and abs(rec["drift_deg"] - 0.05) < 0.01, rec
        assert http.get("/drift").json()["state"] == "alarm"
        assert metric(http, "cellctl_drift_alarm") == 1.0 and metric(http, "cellctl_drift_mm") > 0.2
        assert status_bits(port) & (1 << mm.STATUS_BITS["DRIFT_ALARM"])
        assert any(e["action"] == "drift.alarm" for e in http.get("/audit", params={"limit": 20}).json())
        deadline = time.monotonic() + 10  # the OPC UA variables follow within their poll (0.1 s, 1 s)
        while (seen := opcua_drift(opcua_port))[0] is not True or "drift alarm" not in seen[2]:
            assert time.monotonic() < deadline, seen
            time.sleep(0.3)
        assert seen[1] > 0.2, seen

        # The re-solve: a new inactive hand-eye; activating it is the engineer's audited act.
        out = http.post("/drift/resolve").json()
        assert out["verdict"]["ok"] is True and abs(out["shift_mm"] - 0.3) < 0.05, out
        assert abs(out["shift_deg"] - 0.05) < 0.01, out
        report = http.get(f"/calibrations/{out['calibration_id']}/report").text
        assert "Drift re-solve" in report and "beyond_3sigma" in report  # the history behind it
        active = http.get("/calibrations", params={"kind": "handeye"}).json()
        assert [c["id"] for c in active if c.get("active")] != [out["calibration_id"]]
        assert http.post(f"/calibrations/{out['calibration_id']}/activate").status_code == 200
        for point in ((300.0, -100.0), (450.0, 0.0), (600.0, 100.0)):
            assert map_error_mm(http, truth, point) < 0.1, point

        # A new calibration: a new chart (baseline), then ok; the alarm is gone from every front end.
        states = [http.post("/drift/check").json()["state"] for _ in range(BASELINE + 1)]
        assert states == ["baseline"] * BASELINE + ["ok"], states
        assert metric(http, "cellctl_drift_alarm") == 0.0
        assert not status_bits(port) & (1 << mm.STATUS_BITS["DRIFT_ALARM"])

        # Picks accurate again: a run places its parts in their slots (each production picture checked).
        r = http.post("/production/start", json={"recipe_id": 1, "count": 1})
        assert r.status_code == 202, r.text
        end = wait_ended(http)
        assert end["counters"]["placed"] == 1, end
        from cellctl.production.config import GridPlace

        part = next(p for p in http.get("/sim/truth").json()["parts"] if p["state"] == "placed")
        mm_err, deg_err = slot_error(part["T_base_part"], GridPlace.model_validate(recipe["place"]).T_slot(0))
        assert mm_err < 1.0 and deg_err < 1.0
        records = http.get("/drift").json()["records"]
        assert records[-1]["source"] == "production" and records[-1]["state"] == "ok", records[-1]

        # Bumped again during production: the run pauses after the cycle whose picture alarmed.
        http.post("/sim/faults", json={"camera_shift_mm": [0.6, 0.0, 0.0], "camera_rot_deg": [0.0, 0.0, 0.05]})
        assert http.post("/production/start", json={"recipe_id": 1, "count": 0}).status_code == 202
        paused = wait_for(http, lambda st: st["state"] == "paused")
        assert paused["counters"]["placed"] <= 1, paused
        last = http.get("/drift").json()["records"][-1]
        assert last["source"] == "production" and last["state"] == "alarm", last
        assert http.post("/production/stop").status_code == 200
        wait_ended(http)
