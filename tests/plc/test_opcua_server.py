"""The OPC UA server of the virtual cell (the app in this process), called by an asyncua client over loopback.

Security None (the lab) on the module's cell (``plc_app``); Basic256Sha256 SignAndEncrypt with
self-signed certificates made here (server certificate and a trusted client certificate) on a second one.
"""

from __future__ import annotations

import asyncio
import ipaddress
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua
from asyncua.crypto import cert_gen
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from asyncua.ua.status_codes import get_name_and_doc
from asyncua.ua.uaerrors import UaError, UaStatusCodeError
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import ExtendedKeyUsageOID

from cellctl.plc.opcua_method_io import POSE_STRIDE
from cellctl.plc.opcua_mv.nodeset import NAMESPACE_MV
from cellctl.plc.opcua_server import NAMESPACE
from cellctl.plc.requests import TEXT_NONE, TEXT_UNKNOWN_RECIPE
from tests.plc.conftest import RECIPE, PlcApp, PlcCell
from tests.support.served_plc import in_process_plc

CLIENT_URI = "urn:cellctl:test-plc"
NULL = ua.Variant(None, ua.VariantType.ExtensionObject)
# A Pick on the virtual cell renders a frame (~3 s on a loaded 2-core machine); asyncua's server
# answers one request per connection at a time, so the client's watchdog probe waits behind it.
CLIENT_OPTIONS: dict[str, Any] = {"timeout": 60, "watchdog_intervall": 60}


def make_cert(folder: Path, name: str, uri: str, server: bool, key_folder: Path | None = None) -> tuple[Path, Path]:
    """A self-signed OPC UA application certificate (PEM) and its key (PEM, in ``key_folder``) for ``uri``."""
    key = cert_gen.generate_private_key()
    alt: list[x509.GeneralName] = [x509.UniformResourceIdentifier(uri)]
    if server:
        alt += [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    usage = [ExtendedKeyUsageOID.SERVER_AUTH] if server else [ExtendedKeyUsageOID.CLIENT_AUTH]
    cert = cert_gen.generate_self_signed_app_certificate(key, name, {}, alt, usage, days=2)
    key_folder = key_folder or folder
    for f in (folder, key_folder):
        f.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = folder / f"{name}-cert.pem", key_folder / f"{name}-key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    return cert_path, key_path


async def cell_node(client: Client) -> tuple[Node, int]:
    idx = await client.get_namespace_index(NAMESPACE)
    return await client.nodes.objects.get_child(f"{idx}:Cell"), idx


async def read(cell: Node, idx: int, name: str) -> Any:
    return await (await cell.get_child(f"{idx}:{name}")).read_value()


def check_pick(result: list[Any], cell: PlcApp | PlcCell) -> int:
    count, poses, reachable = result
    assert count >= 1 and len(poses) == POSE_STRIDE * count and len(reachable) == count
    x_mm, y_mm, z_mm, rx, ry, rz, yaw_deg, score = poses[:POSE_STRIDE]
    assert math.hypot(x_mm - cell.part_x_mm, y_mm - cell.part_y_mm) < 0.5
    assert abs(z_mm - 5.0) < 1e-6 and abs(math.hypot(rx, ry, rz) - math.pi) < 0.1  # pointing down
    assert abs(yaw_deg) <= 90.0 and 0.6 <= score <= 1.0 and reachable[0] is True
    return int(count)


def test_pick_verify_and_status_with_security_none(plc_app: PlcApp) -> None:
    async def run() -> None:
        async with Client(plc_app.opcua_url, **CLIENT_OPTIONS) as client:
            cell, idx = await cell_node(client)
            assert await read(cell, idx, "CellId") == "virtual-cell"
            assert await read(cell, idx, "RobotAvailable") is True
            assert await read(cell, idx, "ActiveCameraCalibrationId") == plc_app.camera_calibration_id
            assert await read(cell, idx, "ActiveHandEyeCalibrationId") == plc_app.handeye_calibration_id

            count = check_pick(await cell.call_method(f"{idx}:Pick", ua.Variant(RECIPE, ua.VariantType.Int32)),
                               plc_app)
            assert await read(cell, idx, "LastPickCount") == count
            assert await read(cell, idx, "LastPickLatencyMs") > 0
            assert await read(cell, idx, "LastErrorCode") == TEXT_NONE and await read(cell, idx, "LastError") == ""
            assert await read(cell, idx, "Busy") is False

            passed, drift_px, drift_mm = await cell.call_method(f"{idx}:VerifyCalibration")
            assert passed is True and 0 <= drift_px < 1.0 and 0 <= drift_mm < 0.5

            # Bad calls: a status code, the message in LastError, and the server goes on.
            with pytest.raises(UaStatusCodeError) as e:
                await cell.call_method(f"{idx}:Pick", ua.Variant(65000, ua.VariantType.Int32))
            assert e.value.code == ua.StatusCodes.BadNotFound
            assert "65000" in await read(cell, idx, "LastError")
            assert await read(cell, idx, "LastErrorCode") == TEXT_UNKNOWN_RECIPE
            with pytest.raises(UaStatusCodeError) as e:
                await cell.call_method(f"{idx}:Pick", ua.Variant(-3, ua.VariantType.Int32))
            assert e.value.code == ua.StatusCodes.BadOutOfRange
            with pytest.raises(UaStatusCodeError) as e:
                await cell.call_method(f"{idx}:Pick", ua.Variant("one", ua.VariantType.String))
            assert e.value.code == ua.StatusCodes.BadInvalidArgument
            # The client is read-only: status variables refuse writes.
            with pytest.raises(UaStatusCodeError):
                await (await cell.get_child(f"{idx}:LastError")).write_value("forged")
            assert await read(cell, idx, "CellId") == "virtual-cell"

    before = plc_app.http().get("/plc/status").json()["front_ends"]["opcua"]["paced"]["frames"]
    asyncio.run(run())
    # Every message went through the front ends' work budget (cellctl.plc.opcua_pacing), as Modbus's frames do.
    status = plc_app.http().get("/plc/status").json()["front_ends"]
    assert status["opcua"]["paced"]["frames"] >= before + 15, status["opcua"]
    assert status["modbus"]["paced"] is not None


@pytest.fixture(scope="module")
def secure_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[PlcApp, Path]]:
    tmp = tmp_path_factory.mktemp("plc-secure")
    pki = tmp / "pki"
    server_cert, server_key = make_cert(pki / "server", "cellctl", "urn:cellctl:virtual-cell", server=True)
    make_cert(pki / "trusted", "plc", CLIENT_URI, server=False, key_folder=pki / "keys")
    with in_process_plc(tmp, modbus=False, opcua={
            "security": "basic256sha256", "cert": str(server_cert), "key": str(server_key),
            "trusted_client_certs": str(pki / "trusted")}) as cell:
        yield cell, pki


def test_pick_and_verify_with_basic256sha256(secure_cell: tuple[PlcApp, Path]) -> None:
    cell_info, pki = secure_cell

    async def run() -> None:
        client = Client(cell_info.opcua_url, **CLIENT_OPTIONS)
        client.application_uri = CLIENT_URI
        await client.set_security(SecurityPolicyBasic256Sha256, str(pki / "trusted" / "plc-cert.pem"),
                                  str(pki / "keys" / "plc-key.pem"),
                                  server_certificate=str(pki / "server" / "cellctl-cert.pem"),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        async with client:
            endpoints = await client.get_endpoints()
            assert {e.SecurityPolicyUri for e in endpoints} == {SecurityPolicyBasic256Sha256.URI}
            assert {e.SecurityMode for e in endpoints} == {ua.MessageSecurityMode.SignAndEncrypt}
            cell, idx = await cell_node(client)
            assert await read(cell, idx, "CellId") == "virtual-cell"
            check_pick(await cell.call_method(f"{idx}:Pick", ua.Variant(RECIPE, ua.VariantType.Int32)), cell_info)
            passed, drift_px, _ = await cell.call_method(f"{idx}:VerifyCalibration")
            assert passed is True and drift_px < 1.0

    asyncio.run(run())


def test_basic256sha256_refuses_plain_and_untrusted_clients(secure_cell: tuple[PlcApp, Path]) -> None:
    cell_info, pki = secure_cell
    stranger_cert, stranger_key = make_cert(pki / "untrusted", "stranger", "urn:cellctl:stranger", server=False)

    async def plain() -> None:
        async with Client(cell_info.opcua_url, timeout=10) as client:
            await client.nodes.objects.get_children()

    async def untrusted() -> None:
        client = Client(cell_info.opcua_url, timeout=10)
        client.application_uri = "urn:cellctl:stranger"
        await client.set_security(SecurityPolicyBasic256Sha256, str(stranger_cert), str(stranger_key),
                                  server_certificate=str(pki / "server" / "cellctl-cert.pem"))
        async with client:
            await client.nodes.objects.get_children()

    # The server checks the client's certificate against the trusted folder.
    with pytest.raises(UaStatusCodeError) as e:
        asyncio.run(untrusted())
    assert e.value.code == ua.StatusCodes.BadCertificateUntrusted
    # No endpoint without security is offered, so a plain client finds none to open a session on.
    with pytest.raises(UaError, match="No matching endpoints"):
        asyncio.run(plain())


async def _nodes(client: Client) -> tuple[int, Node, Node, Node, Node]:
    """VisionSystem and its parts (it is added once the server listens: waited for up to 60 s)."""
    deadline = time.monotonic() + 60
    while True:
        try:
            ns = await client.get_namespace_index(NAMESPACE_MV)
            vs = await client.nodes.objects.get_child(f"{ns}:VisionSystem")
            state = await vs.get_child([f"{ns}:VisionStateMachine", "0:CurrentState"])
            value = await state.read_value()
            if value is not None and value.Text:  # shown once the VisionSystem is built
                break
        except (ValueError, UaError):
            pass
        if time.monotonic() > deadline:
            raise TimeoutError("no VisionSystem within 60 s")
        await asyncio.sleep(0.2)
    await client.load_data_type_definitions()
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
            not_pairs = ua.Variant([ua.Variant(1, ua.VariantType.Int32)], ua.VariantType.Variant)
            got["job_bad_params"] = await code(auto, f"{ns}:StartSingleJob", NULL, NULL, ext(Id="1"), NULL, not_pairs)
            count = ua.KeyValuePair(Key=ua.QualifiedName("Count", 0), Value=ua.Variant(2**31 - 1, ua.VariantType.Int32))
            got["continuous_count"] = await code(auto, f"{ns}:StartContinuous", NULL, NULL, ext(Id="1"), NULL,
                                                 ua.Variant([count], ua.VariantType.ExtensionObject))
            count = ua.KeyValuePair(Key=ua.QualifiedName("Count", 0), Value=ua.Variant(2, ua.VariantType.Int32))
            # A good Count passes the argument checks; this cell's plc.allow_motion is off.
            got["continuous_motion_off"] = await code(auto, f"{ns}:StartContinuous", NULL, NULL, ext(Id="1"), NULL,
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
        "continuous_motion_off": "BadNotExecutable",
        "halt_too_few": "BadInvalidArgument", "result_wrong": "BadInvalidArgument",
        "pick_two_args": "BadInvalidArgument", "verify_arg": "BadInvalidArgument",
        "production_count": "BadOutOfRange", "production_types": "BadInvalidArgument",
        "pause_arg": "BadInvalidArgument", "state": "Operational"}
    after = http.get("/robots/robot0/state").json()
    assert after["pose_ur"] == before["pose_ur"] and after["latched"] is False  # the robot did not move


def test_abort_is_the_robots_stop_and_the_vision_system_recovers_after_resume(plc_app: PlcApp) -> None:
    http = plc_app.http()

    async def state(vsm: Node) -> str:
        return str((await (await vsm.get_child("0:CurrentState")).read_value()).Text)

    async def until(vsm: Node, want: str) -> str:
        for _ in range(100):
            if (now := await state(vsm)) == want:
                return now
            await asyncio.sleep(0.05)
        return await state(vsm)

    async def run() -> None:
        async with Client(plc_app.opcua_url, timeout=60, watchdog_intervall=60) as client:
            ns, vs, vsm, auto, _ = await _nodes(client)
            cause = (ua.Variant(0, ua.VariantType.Int32),
                     ua.Variant(ua.LocalizedText("test"), ua.VariantType.LocalizedText))
            assert await until(vsm, "Operational") == "Operational"
            assert await auto.call_method(f"{ns}:Abort", *cause) == 0
            assert http.get("/robots/robot0/motion").json()["latched"] is True
            assert await until(vsm, "Error") == "Error"
            system = await (await vs.get_child(f"{ns}:SystemState")).read_value()
            assert system.State == 5 and "latched" in system.StateDescription
            with pytest.raises(UaStatusCodeError) as e:  # no new work while the robot is latched
                await vsm.call_method(f"{ns}:SelectModeAutomatic")
            assert e.value.code == ua.StatusCodes.BadInvalidState
            assert http.post("/robots/robot0/resume").status_code == 200
            assert await until(vsm, "Operational") == "Operational"

    try:
        asyncio.run(run())
    finally:
        http.post("/robots/robot0/resume")
