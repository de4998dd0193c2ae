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
BadLocked, motion off BadNotExecutable, anything else BadInternalError. The methods' arguments and
how an answer becomes their outputs: :mod:`cellctl.plc.opcua_method_io`.

Security (``plc.opcua.security``, :mod:`cellctl.plc.opcua_security`): ``none`` — the lab, one
endpoint without security; ``basic256sha256`` — one Basic256Sha256 SignAndEncrypt endpoint with the
server certificate and key from the config; only clients whose certificate is in
``trusted_client_certs`` may connect (the server refuses to start without that directory or with an
empty one).
Both run anonymous sessions: the secure channel authenticates the client application.
"""

from __future__ import annotations

import asyncio
import logging
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from asyncua import Node, Server, ua

from cellctl.config_listeners import OpcUaServerConfig
from cellctl.plc.engine import Engine, FrontEnd, Kind, Request, engine_for
from cellctl.plc.modbus_server import is_loopback
from cellctl.plc.opcua_args import guarded
from cellctl.plc.opcua_method_io import (
    failed_status,
    pick_outputs,
    pick_signature,
    sigma_arrays,
    status_code,
    verify_outputs,
    verify_signature,
)
from cellctl.plc.opcua_mv import VisionSystem, add_vision_system
from cellctl.plc.opcua_pacing import PacedClients, pace
from cellctl.plc.opcua_production import add_production, refresh_production
from cellctl.plc.opcua_security import secure
from cellctl.plc.requests import TEXT_RECIPE_RANGE, Outcome, robot_motion_status
from cellctl.services import Services
from drivers.loop_thread import LoopNotRunning, LoopThread

log = logging.getLogger(__name__)

NAMESPACE = "urn:cellctl"
REFRESH_S = 1.0
MOTION_POLL_S = 0.1

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
            await secure(server, cfg)
        server.set_identity_tokens([ua.AnonymousIdentityToken])
        idx = await server.register_namespace(NAMESPACE)
        cell = await server.nodes.objects.add_object(idx, "Cell")
        self._vars["CellId"] = await cell.add_variable(idx, "CellId", self.services.config.cell_id,
                                                       ua.VariantType.String)
        for name, value, vtype in _VARIABLES:
            self._vars[name] = await cell.add_variable(idx, name, value, vtype)
        await cell.add_method(
            idx, "Pick", guarded("Pick", self._pick, 1, self._refused), *pick_signature(move=False))
        await cell.add_method(
            idx, "PickAndMove", guarded("PickAndMove", self._pick_and_move, 1, self._refused),
            *pick_signature(move=True))
        self._production_vars = await add_production(cell, idx, self.services, self._call, failed_status,
                                                     self._refused)
        await cell.add_method(
            idx, "VerifyCalibration", guarded("VerifyCalibration", self._verify, 0, self._refused), [],
            verify_signature())
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
            return status_code(ua.StatusCodes.BadInvalidArgument)
        out = await self._call(Request(Kind.PICK_MOVE if move else Kind.PICK, value))
        if not out.ok:
            return failed_status(out)
        await self._set("LastPickCount", len(out.picks))
        await self._set("LastPickLatencyMs", out.latency_ms)
        sigma_mm, sigma_deg = sigma_arrays(out)
        await self._set("LastPickSigmaMm", sigma_mm)
        await self._set("LastPickSigmaDeg", sigma_deg)
        return pick_outputs(out, move)

    async def _verify(self, parent: ua.NodeId) -> Any:
        out = await self._call(Request(Kind.VERIFY))
        if out.verify is None:
            return failed_status(out)
        return verify_outputs(out.verify)
