"""OPC UA for Machine Vision (OPC 40100-1) on the production cell, driven by node-opcua as a PLC would
(tests/opcua_client/scenario.js, installed by deploy/install-opcua-client.sh): browse, prepare a
recipe, a single job and its ResultReady event and stored result, a continuous run with a result per
cycle until Stop, a wrong argument type refused, Halt latching the robot, Reset; then an engineer's
resume brings the vision system back to Operational.

The hostile-argument tests use asyncua's client on the PLC test cell (``plc_app``): cheaper, and
they reach the server's argument checks the same way.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from asyncua import Client, Node, ua
from asyncua.ua.status_codes import get_name_and_doc
from asyncua.ua.uaerrors import UaStatusCodeError

from cellctl.plc.opcua_mv.nodeset import NAMESPACE_MV, corrected_nodeset, nodeset_text
from tests.drivers.peers import free_port
from tests.plc.conftest import PlcApp
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
    served = start_served(tmp_path, path)
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
        placed = [c for c in cycles if c["result"] == "placed"]
        assert sum(e["result_state"] == 1 for e in run_done["events"]) == len(placed)
        assert sorted(run_done["listed"]) == sorted(e["result_id"] for e in run_done["events"])
        assert http.get("/production").json()["ended_because"] == "stopped"

        assert steps["bad_argument"] == {"step": "bad_argument", "status": "BadInvalidArgument", "auto_state": "Ready"}
        assert steps["halt"]["status"] == "Good" and steps["halt"]["vision_state"] == "Halted"
        assert http.get("/robots/robot0/motion").json()["latched"] is True  # Halt is the robot's Stop
        # Reset leaves Halted; the robot is still latched, so the vision system is in Error until an engineer resumes it.
        assert steps["reset"]["status"] == "Good" and steps["reset"]["vision_state"] == "Error"
        assert http.post("/robots/robot0/resume").status_code == 200
        assert asyncio.run(wait_state(url, "Operational")) == "Operational"
    finally:
        stop_served(served)


async def wait_state(url: str, want: str, timeout_s: float = 10.0) -> str:
    async with Client(url, timeout=30) as client:
        ns = await client.get_namespace_index(NAMESPACE_MV)
        node = await client.nodes.objects.get_child([f"{ns}:VisionSystem", f"{ns}:VisionStateMachine", "0:CurrentState"])
        deadline = time.monotonic() + timeout_s
        while True:
            text = (await node.read_value()).Text
            if text == want or time.monotonic() > deadline:
                return str(text)
            await asyncio.sleep(0.1)


async def _nodes(client: Client) -> tuple[int, Node, Node, Node, Node]:
    await client.load_data_type_definitions()
    ns = await client.get_namespace_index(NAMESPACE_MV)
    vs = await client.nodes.objects.get_child(f"{ns}:VisionSystem")
    vsm = await vs.get_child(f"{ns}:VisionStateMachine")
    auto = await vsm.get_child(f"{ns}:AutomaticModeStateMachine")
    return ns, vs, vsm, auto, await vs.get_child(f"{ns}:RecipeManagement")


def test_hostile_arguments_are_refused_with_a_status_and_never_move_the_robot(plc_app: PlcApp) -> None:
    http = plc_app.http()
    before = http.get("/robots/robot0/state").json()

    async def code(node: Node, name: str, *args: Any) -> str:
        try:
            await node.call_method(name, *args)
        except UaStatusCodeError as exc:
            return get_name_and_doc(exc.code)[0]
        return "Good"

    async def run() -> dict[str, Any]:
        async with Client(plc_app.opcua_url, timeout=60, watchdog_intervall=60) as client:
            ns, vs, vsm, auto, rm = await _nodes(client)
            idx = await client.get_namespace_index("urn:cellctl")
            cell = await client.nodes.objects.get_child(f"{idx}:Cell")
            got: dict[str, Any] = {}
            got["select"] = await code(vsm, f"{ns}:SelectModeAutomatic")
            ext = ua.RecipeIdExternalDataType  # type: ignore[attr-defined]
            got["prepare_int"] = await code(rm, f"{ns}:PrepareRecipe", ua.Variant(1, ua.VariantType.Int32), NULL)
            got["prepare_text"] = await code(rm, f"{ns}:PrepareRecipe", ext(Id="one"), NULL)
            got["prepare_range"] = await code(rm, f"{ns}:PrepareRecipe", ext(Id="70000"), NULL)
            got["prepare_unknown"] = await code(rm, f"{ns}:PrepareRecipe", ext(Id="4242"), NULL)
            got["prepare_too_many"] = await code(rm, f"{ns}:PrepareRecipe", ext(Id="1"), NULL, NULL)
            got["job_not_ready"] = await code(auto, f"{ns}:StartSingleJob", NULL, NULL, NULL, NULL,
                                              ua.Variant([], ua.VariantType.Variant))
            got["job_wrong_types"] = await code(auto, f"{ns}:StartSingleJob", ua.Variant("x", ua.VariantType.String),
                                                ua.Variant(3.5, ua.VariantType.Double), ext(Id="1"), NULL, NULL)
            got["job_bad_params"] = await code(auto, f"{ns}:StartSingleJob", NULL, NULL, ext(Id="1"), NULL,
                                               ua.Variant([ua.Variant(1, ua.VariantType.Int32)], ua.VariantType.Variant))
            count = ua.KeyValuePair(Key=ua.QualifiedName("Count", 0), Value=ua.Variant(2**31 - 1, ua.VariantType.Int32))
            got["continuous_count"] = await code(auto, f"{ns}:StartContinuous", NULL, NULL, ext(Id="1"), NULL,
                                                 ua.Variant([count], ua.VariantType.ExtensionObject))
            got["halt_too_few"] = await code(vsm, f"{ns}:Halt")
            got["result_wrong"] = await code(await vs.get_child(f"{ns}:ResultManagement"), f"{ns}:GetResultById",
                                             ua.Variant(5, ua.VariantType.Int32), ua.Variant(0, ua.VariantType.Int32))
            # The Cell object's methods (issue 34): arity, types and the production Count's limit.
            got["pick_two_args"] = await code(cell, f"{idx}:Pick", ua.Variant(1, ua.VariantType.Int32),
                                              ua.Variant(2, ua.VariantType.Int32))
            got["verify_arg"] = await code(cell, f"{idx}:VerifyCalibration", ua.Variant(1, ua.VariantType.Int32))
            got["production_count"] = await code(cell, f"{idx}:StartProduction", ua.Variant(1, ua.VariantType.Int32),
                                                 ua.Variant(2**31 - 1, ua.VariantType.Int32))
            got["production_types"] = await code(cell, f"{idx}:StartProduction", ua.Variant("1", ua.VariantType.String),
                                                 ua.Variant(1.5, ua.VariantType.Double))
            got["pause_arg"] = await code(cell, f"{idx}:PauseProduction", ua.Variant(1, ua.VariantType.Int32))
            got["state"] = (await (await vsm.get_child("0:CurrentState")).read_value()).Text
            return got

    got = asyncio.run(run())
    assert got == {
        "select": "Good", "prepare_int": "BadInvalidArgument", "prepare_text": "BadInvalidArgument",
        "prepare_range": "BadOutOfRange", "prepare_unknown": "BadNotFound", "prepare_too_many": "BadInvalidArgument",
        "job_not_ready": "BadInvalidState", "job_wrong_types": "BadInvalidArgument",
        "job_bad_params": "BadInvalidArgument", "continuous_count": "BadOutOfRange",
        "halt_too_few": "BadInvalidArgument", "result_wrong": "BadInvalidArgument",
        "pick_two_args": "BadInvalidArgument", "verify_arg": "BadInvalidArgument",
        "production_count": "BadOutOfRange", "production_types": "BadInvalidArgument",
        "pause_arg": "BadInvalidArgument", "state": "Operational"}
    after = http.get("/robots/robot0/state").json()
    assert after["pose_ur"] == before["pose_ur"] and after["latched"] is False  # the robot did not move
