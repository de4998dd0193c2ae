"""The OPC UA server for PLCs (asyncua): the cell's status and its Pick / VerifyCalibration methods.

Endpoint ``opc.tcp://<plc.opcua.host>:<port>/cellctl/``, application URI ``urn:cellctl:<cell_id>``
(a production certificate's subjectAltName must carry that URI). Namespace ``urn:cellctl``;
under ``Objects`` one object ``Cell`` (full description: docs/plc-opcua.md):

Variables (read-only, refreshed every second and after every call)
    ``CellId`` String, ``RobotAvailable`` Boolean, ``CameraAvailable`` Boolean,
    ``ActiveCameraCalibrationId`` / ``ActiveHandEyeCalibrationId`` Int64 (0: none),
    ``Busy`` Boolean, ``LastPickCount`` Int32, ``LastPickLatencyMs`` Double,
    ``LastPickSigmaMm`` / ``LastPickSigmaDeg`` Double[] (the last Pick's picks in Poses' order: position
    1-sigma, largest axis, mm / yaw 1-sigma, degrees; NaN when not known; set before Pick returns),
    ``LastErrorCode`` Int32 (the error-text index of cellctl.plc.requests.ERROR_TEXTS, 0 = none),
    ``LastError`` String (the one-line message, empty when the last call succeeded).
    Live (checked every 0.1 s): ``RobotLatched`` Boolean (the cell's robot is stopped until an
    engineer resumes it), ``RobotMotionOwner`` String (who owns the robot's motion; empty: free),
    ``DriftAlarm`` Boolean (the last drift check alarmed: the camera moved, docs/drift.md) and
    ``DriftMm`` Double (its drift at the fiducials, mm; NaN before the first check).

Methods
    ``Pick(RecipeId: Int32) -> (Count: Int32, Poses: Double[], Reachable: Boolean[])``: grab,
    locate, convert (the robot does not move). ``Poses`` is flat, ``POSE_STRIDE`` = 8 doubles per
    pick, best first: x_mm, y_mm, z_mm, rx_rad, ry_rad, rz_rad (UR rotation vector of T_base_tool),
    gripper_yaw_deg, score. ``Reachable[k]`` says whether pick k is inside the robot's envelope.
    ``PickAndMove(RecipeId: Int32) -> (Count, Poses, Reachable, PickedIndex: Int32)``: the same,
    then the robot picks the best reachable part (approach, pick, retreat) and ``PickedIndex`` says
    which; only with ``plc.allow_motion: true`` (else BadNotExecutable). It obeys the motion owner
    (another mover: BadLocked) and the Stop latch (latched or stopped during the pick:
    BadRequestNotAllowed, "robot stopped: an engineer must resume it").
    ``VerifyCalibration() -> (Passed: Boolean, DriftPx: Double, DriftMm: Double)`` (DriftMm is NaN
    with no active hand-eye calibration). A drifted calibration is ``Passed = false``, not an error.
    Production (``cellctl.plc.opcua_production``): ``StartProduction(RecipeId, Count) -> RunId``,
    ``PauseProduction()``, ``ResumeProduction()``, ``StopProduction()`` and ``Production*`` variables.

Failures are OPC UA status codes (the message in ``LastError``): unknown recipe BadNotFound,
recipe number outside 0..65535 BadOutOfRange, a wrong argument type BadInvalidArgument, no
calibration or a recipe that cannot be used BadInvalidState, camera/robot or the store unavailable
BadResourceUnavailable, timeout BadTimeout, robot latched/stopped BadRequestNotAllowed, robot busy
BadLocked, motion off BadNotExecutable, anything else BadInternalError.

Security (``plc.opcua.security``): ``none`` — the lab, one endpoint without security;
``basic256sha256`` — one Basic256Sha256 SignAndEncrypt endpoint with the server certificate and key
from the config; only clients whose certificate is in ``trusted_client_certs`` may connect (the
server refuses to start without that directory or with an empty one).
Both run anonymous sessions: the secure channel authenticates the client application.
"""

from __future__ import annotations

import asyncio
import logging
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua

from cellctl.config import TRUST_HINT, OpcUaServerConfig
from cellctl.plc.engine import Engine, FrontEnd, Kind, Request, engine_for
from cellctl.plc.modbus_server import is_loopback
from cellctl.plc.opcua_args import guarded
from cellctl.plc.opcua_mv import VisionSystem, add_vision_system
from cellctl.plc.opcua_pacing import PacedClients, pace
from cellctl.plc.opcua_production import add_production, refresh_production
from cellctl.plc.requests import (
    TEXT_BAD_RECIPE,
    TEXT_BUSY,
    TEXT_CANNOT_PICK,
    TEXT_DEVICE,
    TEXT_MOTION_OFF,
    TEXT_NO_CALIBRATION,
    TEXT_RECIPE_RANGE,
    TEXT_ROBOT_BUSY,
    TEXT_ROBOT_STOPPED,
    TEXT_STORE,
    TEXT_TIMEOUT,
    TEXT_UNKNOWN_RECIPE,
    TEXT_VERIFY_FAILED_TO_RUN,
    Outcome,
    pick_sigma,
    robot_motion_status,
)
from cellctl.services import Services
from drivers.loop_thread import LoopNotRunning, LoopThread

log = logging.getLogger(__name__)

NAMESPACE = "urn:cellctl"
POSE_STRIDE = 8
REFRESH_S = 1.0
MOTION_POLL_S = 0.1
STATUS_OF_TEXT: dict[int, int] = {
    TEXT_UNKNOWN_RECIPE: ua.StatusCodes.BadNotFound,
    TEXT_RECIPE_RANGE: ua.StatusCodes.BadOutOfRange,
    TEXT_NO_CALIBRATION: ua.StatusCodes.BadInvalidState,
    TEXT_BAD_RECIPE: ua.StatusCodes.BadInvalidState,
    TEXT_CANNOT_PICK: ua.StatusCodes.BadInvalidState,
    TEXT_DEVICE: ua.StatusCodes.BadResourceUnavailable,
    TEXT_VERIFY_FAILED_TO_RUN: ua.StatusCodes.BadResourceUnavailable,
    TEXT_TIMEOUT: ua.StatusCodes.BadTimeout,
    TEXT_ROBOT_STOPPED: ua.StatusCodes.BadRequestNotAllowed,
    TEXT_ROBOT_BUSY: ua.StatusCodes.BadLocked,
    TEXT_BUSY: ua.StatusCodes.BadTooManyOperations,
    TEXT_MOTION_OFF: ua.StatusCodes.BadNotExecutable,
    TEXT_STORE: ua.StatusCodes.BadResourceUnavailable,
}

_VARIABLES: tuple[tuple[str, Any, ua.VariantType], ...] = (
    ("RobotAvailable", False, ua.VariantType.Boolean),
    ("CameraAvailable", False, ua.VariantType.Boolean),
    ("ActiveCameraCalibrationId", 0, ua.VariantType.Int64),
    ("ActiveHandEyeCalibrationId", 0, ua.VariantType.Int64),
    ("Busy", False, ua.VariantType.Boolean),
    ("LastPickCount", 0, ua.VariantType.Int32),
    ("LastPickLatencyMs", 0.0, ua.VariantType.Double),
    ("LastPickSigmaMm", [], ua.VariantType.Double),
    ("LastPickSigmaDeg", [], ua.VariantType.Double),
    ("LastErrorCode", 0, ua.VariantType.Int32),
    ("LastError", "", ua.VariantType.String),
    ("RobotLatched", False, ua.VariantType.Boolean),
    ("RobotMotionOwner", "", ua.VariantType.String),
    ("DriftAlarm", False, ua.VariantType.Boolean),
    ("DriftMm", float("nan"), ua.VariantType.Double),
)


def _arg(name: str, vtype: ua.VariantType, description: str, array: bool = False) -> ua.Argument:
    a = ua.Argument()
    a.Name = name
    a.DataType = ua.NodeId(ua.Int32(vtype.value))
    a.ValueRank = 1 if array else -1
    a.ArrayDimensions = [0] if array else []
    a.Description = ua.LocalizedText(description)
    return a


def _status_code(code: int) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(code))


CERT_SUFFIXES = (".der", ".pem", ".crt", ".cer")


def trusted_dir_problem(folder: str | None) -> str | None:
    """Why ``folder`` cannot serve as the trust list of client certificates (None: it can)."""
    if folder is None:
        return f"plc.opcua: {TRUST_HINT}"
    trusted = Path(folder)
    if not trusted.is_dir():
        return f"plc.opcua.trusted_client_certs {trusted} is not a directory; {TRUST_HINT}"
    if not any(f.suffix.lower() in CERT_SUFFIXES for f in trusted.iterdir() if f.is_file()):
        return (f"plc.opcua.trusted_client_certs {trusted} holds no certificate, so no client could connect; "
                f"{TRUST_HINT}")
    return None


def security_problem(config: OpcUaServerConfig) -> str | None:
    """What keeps the configured OPC UA security from starting (files missing, nobody trusted); None: fine."""
    if config.security == "none":
        return None
    for what, path in (("certificate", config.cert), ("key", config.key)):
        if path is None or not Path(path).is_file():
            return f"plc.opcua: the server {what} {path} is missing; create it (docs/plc-opcua.md)"
    return trusted_dir_problem(config.trusted_client_certs)


async def trusted_clients_validator(folder: str | None) -> Any:
    """A validator that lets only the client certificates in ``folder`` connect (asyncua's TrustStore)."""
    from asyncua.crypto.truststore import TrustStore
    from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions

    problem = trusted_dir_problem(folder)
    if problem or folder is None:
        raise OSError(problem)
    trusted = Path(folder)
    store = TrustStore([trusted], [])
    try:
        await store.load()
    except ValueError as exc:
        raise OSError(f"plc.opcua.trusted_client_certs {trusted}: a file there is not a certificate "
                      f"({exc}); keep only client certificates (.der/.pem) there") from None
    opts = (CertificateValidatorOptions.TIME_RANGE | CertificateValidatorOptions.TRUSTED
            | CertificateValidatorOptions.PEER_CLIENT)
    return CertificateValidator(opts, store)


def endpoint_url(host: str, port: int) -> str:
    return f"opc.tcp://{host}:{port}/cellctl/"


class OpcUaPlcServer:
    """The PLC's OPC UA server for one cell; ``start()`` listens, ``stop()`` ends it."""

    def __init__(self, services: Services, config: OpcUaServerConfig) -> None:
        self.services, self.config = services, config
        self.url = endpoint_url(config.host, config.port)
        self.application_uri = f"urn:cellctl:{services.config.cell_id}"
        self._thread = LoopThread(f"plc-opcua-{config.port}")
        self._executor = ThreadPoolExecutor(max_workers=2, thread_name_prefix="plc-opcua-request")
        self._server: Server | None = None
        self._vars: dict[str, Node] = {}
        self._refresher: asyncio.Task[None] | None = None
        self._motion_watch: asyncio.Task[None] | None = None
        self._call_lock = asyncio.Lock()
        self._pending_refresh: asyncio.Task[None] | None = None
        self._production_vars: dict[str, Node] = {}
        self._front: FrontEnd | None = None
        self._engine: Engine = engine_for(services)
        self._production_shown: dict[str, Any] = {}
        self._vision: VisionSystem | None = None
        self._vision_task: asyncio.Task[None] | None = None
        self.paced: PacedClients | None = None
        """The connections whose messages are paced (``cellctl.plc.opcua_pacing``), once listening."""

    # -- life cycle ---------------------------------------------------------------------------------
    def start(self) -> OpcUaPlcServer:
        # asyncua logs every standard node it adds at INFO: thousands of lines per start.
        logging.getLogger("asyncua").setLevel(max(logging.WARNING, logging.getLogger("asyncua").level))
        # With security, clients are authenticated by certificate: no zone decision needed beyond loopback.
        self._engine = engine_for(self.services)
        self._front = self._engine.register("opcua", self.config.host, self.config.port,
                                            motion=self.config.security == "none")
        self._thread.start(self._serve, timeout_s=60.0)
        log.info("PLC OPC UA server at %s (security %s)", self.url, self.config.security)
        if self.services.config.plc.allow_motion:
            log.warning("plc.allow_motion is on: an OPC UA client at %s may move the robot (PickAndMove)", self.url)
        if self.config.security == "none" and not is_loopback(self.config.host):
            log.warning("PLC OPC UA server on %s without security (plc.insecure_plc_network: true, the "
                        "integrator's IEC 62443 zone decision): anyone on that network can call Pick",
                        self.config.host)
        return self

    def stop(self) -> None:
        async def shutdown() -> None:
            for task in (self._refresher, self._motion_watch):
                if task is not None:
                    task.cancel()
            if self._vision_task is not None:
                self._vision_task.cancel()
                await asyncio.gather(self._vision_task, return_exceptions=True)
            if self._vision is not None:
                await self._vision.stop()
            if self._server is not None:
                await self._server.stop()

        self._thread.stop(shutdown, timeout_s=15.0)
        self._executor.shutdown(wait=True, cancel_futures=True)
        self._engine.unregister("opcua")

    async def _serve(self) -> None:
        cfg = self.config
        server = Server()
        await server.init()
        server.set_endpoint(self.url)
        server.set_server_name(f"cellctl {self.services.config.cell_id}")
        await server.set_application_uri(self.application_uri)
        if cfg.security == "none":
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        else:
            await self._secure(server)
        server.set_identity_tokens([ua.AnonymousIdentityToken])
        idx = await server.register_namespace(NAMESPACE)
        cell = await server.nodes.objects.add_object(idx, "Cell")
        self._vars["CellId"] = await cell.add_variable(idx, "CellId", self.services.config.cell_id,
                                                       ua.VariantType.String)
        for name, value, vtype in _VARIABLES:
            self._vars[name] = await cell.add_variable(idx, name, value, vtype)
        pick_outputs = [
            _arg("Count", ua.VariantType.Int32, "number of picks, best first"),
            _arg("Poses", ua.VariantType.Double, "8 per pick: x_mm, y_mm, z_mm, rx_rad, ry_rad, rz_rad, "
                                                 "gripper_yaw_deg, score", array=True),
            _arg("Reachable", ua.VariantType.Boolean, "per pick: inside the robot's envelope", array=True)]
        await cell.add_method(
            idx, "Pick", guarded("Pick", self._pick, 1, self._refused),
            [_arg("RecipeId", ua.VariantType.Int32, "recipe number 0..65535")],
            pick_outputs)
        await cell.add_method(
            idx, "PickAndMove", guarded("PickAndMove", self._pick_and_move, 1, self._refused),
            [_arg("RecipeId", ua.VariantType.Int32, "recipe number 0..65535")],
            [*pick_outputs,
             _arg("PickedIndex", ua.VariantType.Int32, "index in Poses of the pick the robot made")])
        self._production_vars = await add_production(cell, idx, self.services, self._call, self._failed,
                                                     self._refused)
        await cell.add_method(
            idx, "VerifyCalibration", guarded("VerifyCalibration", self._verify, 0, self._refused), [],
            [_arg("Passed", ua.VariantType.Boolean, "the active calibration is within tolerance"),
             _arg("DriftPx", ua.VariantType.Double, "RMS drift of the plate's points, pixels"),
             _arg("DriftMm", ua.VariantType.Double, "RMS drift in 3D, mm (NaN: no hand-eye calibration)")])
        try:
            await server.start()
        except OSError as exc:
            raise OSError(f"PLC OPC UA server cannot listen on {cfg.host}:{cfg.port} ({exc.strerror or exc}); "
                          "free the port or change plc.opcua.port") from None
        self._server = server
        self.paced = pace(server)  # its messages share the interpreter budget of every front end
        if self._front is not None:  # connected clients for GET /plc/status (asyncua keeps the list)
            self._front.clients_of = lambda: len(server.bserver.clients) if server.bserver is not None else 0
            self._front.pacer = None if self.paced is None else self.paced.pacer
        # OPC UA for Machine Vision is added once the server listens (the NodeSet's import costs ~2 s of
        # CPU, more on a loaded machine): the service's start does not wait for it.
        self._vision_task = asyncio.get_running_loop().create_task(self._add_vision(server))
        await self._refresh()
        self._refresher = asyncio.get_running_loop().create_task(self._refresh_forever())
        self._motion_watch = asyncio.get_running_loop().create_task(self._watch_motion())

    async def _add_vision(self, server: Server) -> None:
        """Build ``Objects/VisionSystem`` (docs/plc-opcua.md) on the running server, then let it follow the cell."""
        try:
            vision = await add_vision_system(server, self.services, self._call, self._executor)
        except Exception:  # noqa: BLE001 - the Cell object keeps serving without the Machine Vision model
            log.exception("OPC UA for Machine Vision could not be added; the Cell object serves on")
            return
        self._vision = vision
        await vision.started()
        log.info("OPC UA for Machine Vision: Objects/VisionSystem at %s", self.url)

    async def _secure(self, server: Server) -> None:
        """Basic256Sha256 SignAndEncrypt, and only clients whose certificate is in the trusted directory.

        Refuses to start (``OSError`` with how to fix it) without a trusted directory or with one
        that holds no certificate: without a trust list asyncua accepts any self-signed client.
        """
        cfg = self.config
        problem = security_problem(cfg)
        if problem or cfg.cert is None or cfg.key is None:
            raise OSError(problem or "plc.opcua: security basic256sha256 needs the server certificate and key")
        await server.load_certificate(cfg.cert)
        await server.load_private_key(cfg.key)
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
        server.set_certificate_validator(await trusted_clients_validator(cfg.trusted_client_certs))

    # -- status -------------------------------------------------------------------------------------
    def _status(self) -> dict[str, Any]:
        """Device and calibration status (blocking: the store is a database)."""
        svc = self.services
        d = svc.config.calibration
        cam = svc.store.active("camera", d.camera, None)
        he = svc.store.active("handeye", d.camera, d.robot)
        robot = svc.cell.robots.get(d.robot)
        camera = svc.cell.cameras.get(d.camera)
        return {"RobotAvailable": bool(robot is not None and robot.is_open),
                "CameraAvailable": bool(camera is not None and camera.is_open),
                "ActiveCameraCalibrationId": int(cam.id) if cam is not None else 0,
                "ActiveHandEyeCalibrationId": int(he.id) if he is not None else 0}

    async def _set(self, name: str, value: Any) -> None:
        node = self._vars[name]
        vtype = {n: t for n, _, t in _VARIABLES}.get(name, ua.VariantType.String)
        await node.write_value(ua.DataValue(ua.Variant(value, vtype)))

    async def _refresh(self) -> None:
        try:
            status = await asyncio.get_running_loop().run_in_executor(self._executor, self._status)
        except Exception as exc:  # noqa: BLE001 - status is best effort; the server keeps serving
            log.warning("OPC UA status refresh failed: %s", exc)
            return
        for name, value in status.items():
            await self._set(name, value)

    async def _refresh_forever(self) -> None:
        while True:
            await asyncio.sleep(REFRESH_S)
            await self._refresh()

    async def _watch_motion(self) -> None:
        """Keep RobotLatched / RobotMotionOwner (and DriftAlarm / DriftMm) live: a Stop shows within MOTION_POLL_S."""
        shown: tuple[bool, str] | None = None
        drift_shown: tuple[bool, float | None] | None = None
        while True:
            try:
                status = robot_motion_status(self.services)
                owner = status["owner"]
                now = (bool(status["latched"]), "" if not owner else f"{owner['what']} (by {owner['who']})")
                if now != shown:
                    await self._set("RobotLatched", now[0])
                    await self._set("RobotMotionOwner", now[1])
                    shown = now
                drift = self.services.drift_if_made  # from memory: a lock, no I/O
                last = None if drift is None else drift.last()
                drift_now = (drift is not None and drift.alarm, None if last is None else float(last["drift_mm"]))
                if drift_now != drift_shown:
                    await self._set("DriftAlarm", drift_now[0])
                    await self._set("DriftMm", float("nan") if drift_now[1] is None else drift_now[1])
                    drift_shown = drift_now
                await refresh_production(self._production_vars, self.services, self._production_shown)
            except Exception:  # noqa: BLE001 - the watch keeps running; the variables stay as they were
                log.exception("OPC UA robot motion status failed")
            await asyncio.sleep(MOTION_POLL_S)

    # -- methods ------------------------------------------------------------------------------------
    async def _call(self, request: Request) -> Outcome:
        """Run ``request`` through the cell's request engine (one at a time for every front end)."""
        async with self._call_lock:
            await self._set("Busy", True)
            try:
                if self._front is None:
                    raise LoopNotRunning("the OPC UA server is not started: start() registers its front end")
                out = await asyncio.wrap_future(self._engine.submit(self._front, request, "plc:opcua"))
            finally:
                await self._set("Busy", False)
        await self._set("LastErrorCode", out.text_index)
        await self._set("LastError", "" if out.ok else out.message)
        # Device and calibration status are refreshed after the answer, not before it.
        self._pending_refresh = asyncio.get_running_loop().create_task(self._refresh())
        return out

    async def _refused(self, message: str) -> None:
        """A call refused for its arguments: its message in ``LastError`` (code: the request is wrong)."""
        await self._set("LastErrorCode", TEXT_RECIPE_RANGE)
        await self._set("LastError", message)

    def _failed(self, out: Outcome) -> ua.StatusCode:
        return _status_code(STATUS_OF_TEXT.get(out.text_index, ua.StatusCodes.BadInternalError))

    async def _pick(self, parent: ua.NodeId, recipe: ua.Variant | None = None) -> Any:
        return await self._pick_request(recipe, move=False)

    async def _pick_and_move(self, parent: ua.NodeId, recipe: ua.Variant | None = None) -> Any:
        return await self._pick_request(recipe, move=True)

    async def _pick_request(self, recipe: ua.Variant | None, move: bool) -> Any:
        value = recipe.Value if isinstance(recipe, ua.Variant) else None
        method = "PickAndMove" if move else "Pick"
        if not isinstance(value, int) or isinstance(value, bool):
            await self._set("LastErrorCode", TEXT_RECIPE_RANGE)
            await self._set("LastError", f"{method} needs one Int32 recipe number, got {value!r}")
            return _status_code(ua.StatusCodes.BadInvalidArgument)
        out = await self._call(Request(Kind.PICK_MOVE if move else Kind.PICK, value))
        if not out.ok:
            return _status_code(STATUS_OF_TEXT.get(out.text_index, ua.StatusCodes.BadInternalError))
        poses: list[float] = []
        reachable: list[bool] = []
        for p in out.picks:
            q = p["pick_pose"]
            poses += [q["x_mm"], q["y_mm"], q["z_mm"], q["rx_rad"], q["ry_rad"], q["rz_rad"],
                      float(p["gripper_yaw_deg"]), float(p["score"])]
            reachable.append(bool(p["reachable"]))
        await self._set("LastPickCount", len(out.picks))
        await self._set("LastPickLatencyMs", out.latency_ms)
        sigmas = [pick_sigma(p) for p in out.picks]
        await self._set("LastPickSigmaMm", [math.nan if mm is None else mm for mm, _ in sigmas])
        await self._set("LastPickSigmaDeg", [math.nan if deg is None else deg for _, deg in sigmas])
        answer = [ua.Variant(len(out.picks), ua.VariantType.Int32),
                  ua.Variant([float(x) for x in poses], ua.VariantType.Double),
                  ua.Variant(reachable, ua.VariantType.Boolean)]
        if move:
            picked = -1 if out.picked_index is None else out.picked_index
            answer.append(ua.Variant(picked, ua.VariantType.Int32))
        return answer

    async def _verify(self, parent: ua.NodeId) -> Any:
        out = await self._call(Request(Kind.VERIFY))
        if out.verify is None:
            return _status_code(STATUS_OF_TEXT.get(out.text_index, ua.StatusCodes.BadInternalError))
        v = out.verify
        drift_mm = v.get("drift_mm")
        return [ua.Variant(bool(v.get("passed")), ua.VariantType.Boolean),
                ua.Variant(float(v.get("drift_px", math.nan)), ua.VariantType.Double),
                ua.Variant(float(drift_mm) if drift_mm is not None else math.nan, ua.VariantType.Double)]

