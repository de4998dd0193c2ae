"""OPC UA for Machine Vision (OPC 40100-1) on the production cell, driven by node-opcua as a PLC would
(tests/opcua_client/scenario.js, installed by deploy/install-opcua-client.sh): browse, prepare a
recipe, a single job and its ResultReady event and stored result, a continuous run with a result per
cycle until Stop, a wrong argument type refused, Halt latching the robot, Reset; then an engineer's
resume brings the vision system back to Operational.

The hostile-argument test is in test_opcua_server.py (asyncua's client on the PLC test cell it shares).
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from asyncua import Client, ua

from cellctl.plc.opcua_mv.nodeset import NAMESPACE_MV, corrected_nodeset, nodeset_text
from tests.drivers.peers import free_port
from tests.support.production_cell import production_config, teach_recipe
from tests.support.served import start_served, stop_served

CLIENT_DIR = Path(__file__).resolve().parents[1] / "opcua_client"
NULL = ua.Variant(None, ua.VariantType.ExtensionObject)
CAUSE = (ua.Variant(0, ua.VariantType.Int32), ua.Variant(ua.LocalizedText("test"), ua.VariantType.LocalizedText))


def node_client() -> list[str]:
    node = shutil.which("node")
    if node is None or not (CLIENT_DIR / "node_modules" / "node-opcua-client").is_dir():
        pytest.fail("node-opcua is not installed: run deploy/setup.sh (deploy/install-opcua-client.sh)")
    return [node, str(CLIENT_DIR / "scenario.js")]


def test_the_nodeset_correction_gives_the_id_types_their_base_fields() -> None:
    text = corrected_nodeset(nodeset_text())
    for name in ("RecipeIdExternalDataType", "RecipeIdInternalDataType", "ConfigurationIdDataType"):
        assert f'<Definition Name="1:{name}" />' in nodeset_text()
        block = text.split(f'<Definition Name="1:{name}">', 1)[1].split("</Definition>", 1)[0]
        assert [f.split('"')[1] for f in block.split("<Field Name=")[1:]] == [
            "Id", "Version", "Hash", "HashAlgorithm", "Description"]


def test_a_plc_runs_jobs_and_production_over_opc_ua_machine_vision(tmp_path: Path) -> None:
    cmd = node_client()
    path = production_config(tmp_path, count=6)
    cfg = yaml.safe_load(path.read_text())
    port = free_port()
    cfg["plc"] = {"opcua": {"enabled": True, "host": "127.0.0.1", "port": port}, "allow_motion": True}
    path.write_text(yaml.safe_dump(cfg))
    served = start_served(tmp_path, path, timeout_s=180.0)  # the NodeSet import adds ~1 s of CPU to the start
    url = f"opc.tcp://127.0.0.1:{port}/cellctl/"
    try:
        http = served.client(timeout_s=60)
        teach_recipe(http)
        done = subprocess.run([*cmd, url], capture_output=True, text=True, timeout=600, cwd=CLIENT_DIR)
        steps = {s["step"]: s for s in (json.loads(line) for line in done.stdout.splitlines() if line.startswith("{"))}
        assert done.returncode == 0 and "error" not in steps, (done.stdout[-3000:], done.stderr[-3000:])

        browse = steps["browse"]
        assert {"VisionStateMachine", "RecipeManagement", "ResultManagement", "SystemState"} <= set(browse["children"])
        assert browse["vision_state"] == "Operational" and not browse["auto_state"]
        assert steps["select"]["status"] == "Good" and steps["select"]["auto_state"] == "Initialized"
        assert steps["recipes"]["ids"] == ["1"]
        assert steps["prepare"] == {"step": "prepare", "status": "Good", "internal_id": "1", "auto_state": "Ready"}

        single = steps["single"]
        assert single["status"] == "Good" and single["job_id"] and single["auto_state"] == "SingleExecution"
        ev = steps["single_event"]["event"]
        assert ev["job_id"] == single["job_id"] and ev["result_state"] == 1 and ev["is_partial"] is False
        assert ev["recipe"] == "1" and ev["configuration"].startswith("camera-") and ev["creation_time"]
        picks = json.loads(ev["content"][0])["picks"]
        assert picks and {"pick_pose", "score", "uncertainty"} <= set(picks[0])
        assert picks[0]["uncertainty"]["sigma_mm"] is not None
        assert steps["single_done"]["auto_state"] == "Ready"
        result = steps["result"]
        assert result["status"] == "Good" and result["result_id"] == ev["result_id"]
        assert result["job_id"] == single["job_id"] and result["content"] == ev["content"]

        cont, run_done = steps["continuous"], steps["continuous_done"]
        assert cont["status"] == "Good" and cont["auto_state"] == "ContinuousExecution"
        assert run_done["first"] and run_done["stop"] == "Good" and run_done["auto_state"] == "Ready"
        cycles = http.get(f"/production/runs/{cont['job_id'].removeprefix('run-')}/cycles").json()
        assert len(run_done["events"]) == len(cycles) >= 1  # one result per cycle
        assert [json.loads(e["content"][0])["cycle"]["result"] for e in run_done["events"]] == [
            c["result"] for c in cycles]
        assert [e["result_state"] for e in run_done["events"]] == [3 if c["result"] == "stopped" else 1 for c in cycles]
        assert cycles[0]["result"] == "placed" and json.loads(run_done["events"][0]["content"][0])["picks"]
        assert sorted(run_done["listed"]) == sorted(e["result_id"] for e in run_done["events"])
        assert http.get("/production").json()["ended_because"] == "stopped"

        assert steps["bad_argument"] == {"step": "bad_argument", "status": "BadInvalidArgument", "auto_state": "Ready"}
        assert steps["halt"]["status"] == "Good" and steps["halt"]["vision_state"] == "Halted"
        assert http.get("/robots/robot0/motion").json()["latched"] is True  # Halt is the robot's Stop
        # Reset leaves Halted; the robot is still latched: Error until an engineer resumes it.
        assert steps["reset"]["status"] == "Good" and steps["reset"]["vision_state"] == "Error"
        assert http.post("/robots/robot0/resume").status_code == 200
        assert asyncio.run(wait_state(url, "Operational")) == "Operational"
    finally:
        stop_served(served)


async def wait_state(url: str, want: str, timeout_s: float = 10.0) -> str:
    async with Client(url, timeout=30) as client:
        ns = await client.get_namespace_index(NAMESPACE_MV)
        path = [f"{ns}:VisionSystem", f"{ns}:VisionStateMachine", "0:CurrentState"]
        node = await client.nodes.objects.get_child(path)
        deadline = time.monotonic() + timeout_s
        while True:
            text = (await node.read_value()).Text
            if text == want or time.monotonic() > deadline:
                return str(text)
            await asyncio.sleep(0.1)
