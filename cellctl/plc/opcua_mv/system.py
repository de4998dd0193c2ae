"""``Objects/VisionSystem``: an instance of OPC 40100-1's ``VisionSystemType`` driven by the cell
(docs/plc-opcua.md, "OPC UA for Machine Vision").

The state machines (:mod:`.states`) follow the cell, polled every ``POLL_S``; the methods are
linked to the instance's method nodes (:mod:`.methods`); each job or production cycle becomes a
:class:`~.results.Result`, kept and emitted as a ``ResultReadyEventType`` event from this object.
The cell's requests run in the server's executor through the server's ``call`` (one PLC request at
a time, ``Busy`` and ``LastError`` of ``Cell`` as for every call).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from collections.abc import Awaitable, Callable
from concurrent.futures import Executor
from datetime import UTC, datetime
from typing import Any, TypeVar

from asyncua import Node, Server, ua
from asyncua.common.instantiate_util import instantiate

from cellctl.plc.opcua_mv import cell
from cellctl.plc.opcua_mv.cell import Outcome, Request
from cellctl.plc.opcua_mv.nodeset import import_machine_vision
from cellctl.plc.opcua_mv.results import (
    STATE_ABORTED,
    STATE_COMPLETED,
    STATE_FAILED,
    Result,
    ResultStore,
    mv_type,
)
from cellctl.plc.opcua_mv.states import AUTO_STATE_IDS, VISION_STATE_IDS, Job, VisionModel
from cellctl.services import Services

log = logging.getLogger(__name__)

POLL_S = 0.1
_EVENT_TYPES = {"CreationTime": ua.VariantType.DateTime, "IsPartial": ua.VariantType.Boolean,
                "IsSimulated": ua.VariantType.Boolean, "ResultState": ua.VariantType.Int32,
                "ResultContent": ua.VariantType.Variant}
T = TypeVar("T")
Call = Callable[[Request], Awaitable[Outcome]]
"""The OPC UA server's call: a request through the cell's request engine (``Busy``/``LastError`` of ``Cell``)."""


class VisionSystem:
    """The VisionSystem object of one OPC UA server."""

    def __init__(self, server: Server, services: Services, call: Call, executor: Executor) -> None:
        self.server, self.services, self.call, self.executor = server, services, call, executor
        self.model = VisionModel()
        self.results = ResultStore()
        self.ns = 0
        self.node: Node | None = None
        self._nodes: dict[str, Node] = {}
        self._shown: dict[str, Any] = {}
        self._event: Any = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._poller: asyncio.Task[None] | None = None
        self._jobs = 0
        self._run_id: int | None = None
        self._run_seen = 0
        self.problem: str | None = None

    # -- building -----------------------------------------------------------------------------------
    async def build(self) -> None:
        from cellctl.plc.opcua_mv.methods import link_methods

        self.ns = ns = await import_machine_vision(self.server)
        vs_type = self.server.get_node(_node_id(1003, ns))
        self.node = (await instantiate(self.server.nodes.objects, vs_type, bname=ua.QualifiedName("VisionSystem", ns),
                                       dname=ua.LocalizedText("VisionSystem")))[0]
        vsm = await self.node.get_child(f"{ns}:VisionStateMachine")
        auto = await vsm.get_child(f"{ns}:AutomaticModeStateMachine")
        self._nodes = {"vision": await vsm.get_child("0:CurrentState"),
                       "vision_id": await vsm.get_child(["0:CurrentState", "0:Id"]),
                       "auto": await auto.get_child("0:CurrentState"),
                       "auto_id": await auto.get_child(["0:CurrentState", "0:Id"]),
                       "system": await self.node.get_child(f"{ns}:SystemState")}
        await link_methods(self, self.node)
        event_type = self.server.get_node(_node_id(1024, ns))
        generator = await self.server.get_event_generator(event_type, self.node.nodeid)
        self._event = generator
        await self.show()

    async def started(self) -> None:
        """The server listens: poll the cell from now on."""
        self._poller = asyncio.get_running_loop().create_task(self._poll_forever())

    async def stop(self) -> None:
        tasks = [t for t in (self._poller, *self._tasks) if t is not None]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    # -- state --------------------------------------------------------------------------------------
    async def blocking(self, fn: Callable[[], T]) -> T:
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn)

    async def stop_robot(self, reason: str) -> str | None:
        """The robot's Stop, in a thread of its own: never queued behind a request in the executor."""
        return await asyncio.to_thread(cell.robot_stop, self.services, reason)

    async def show(self) -> None:
        """Write the state machines and SystemState where they changed."""
        m, problem = self.model, self.problem
        vision, auto = m.vision_state(problem), m.auto_state(problem)
        system = m.system_state(problem)
        note = cell.drift_note(self.services)  # OPC 40100 diagnostics: the drift alarm in SystemState's text
        if note is not None:
            system = (system[0], f"{system[1]}; {note}")
        values: dict[str, Any] = {
            "vision": ua.Variant(ua.LocalizedText(vision), ua.VariantType.LocalizedText),
            "vision_id": ua.Variant(_node_id(VISION_STATE_IDS[vision], self.ns), ua.VariantType.NodeId),
            # Not active: an empty name and the null NodeId (the variables' types admit no null value).
            "auto": ua.Variant(ua.LocalizedText(auto or ""), ua.VariantType.LocalizedText),
            "auto_id": ua.Variant(ua.NodeId() if auto is None else _node_id(AUTO_STATE_IDS[auto], self.ns),
                                  ua.VariantType.NodeId),
            "system": system}
        for name, value in values.items():
            if self._shown.get(name) == value:
                continue
            if name == "system":
                desc = mv_type("SystemStateDescriptionDataType")(State=value[0], StateDescription=value[1])
                variant = ua.Variant(desc, ua.VariantType.ExtensionObject)
            else:
                variant = value
            await self.server.write_attribute_value(self._nodes[name].nodeid, ua.DataValue(variant))
            self._shown[name] = value

    async def _poll_forever(self) -> None:
        while True:
            try:
                await self.poll()
            except Exception:  # noqa: BLE001 - the poll keeps running; the states stay as they were
                log.exception("OPC UA VisionSystem poll failed")
            await asyncio.sleep(POLL_S)

    async def poll(self) -> None:
        self.problem = cell.cell_problem(self.services)  # from memory: no I/O
        if self.model.starting:
            await self.show()  # Preoperational stays for one poll period (at start and after Reset)
            self.model.starting = False
            return
        if self.model.job == "continuous":
            await self._follow_run()
        await self.show()

    # -- jobs ---------------------------------------------------------------------------------------
    def next_job_id(self, prefix: str) -> str:
        self._jobs += 1
        return f"{prefix}-{self._jobs}"

    def spawn(self, coro: Awaitable[None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def single_job(self, job_id: str, recipe_id: int, ids: dict[str, str | None]) -> None:
        """Run one pick and emit its result; SingleExecution until then."""
        try:
            out = await self.call(cell.pick(recipe_id))
            content: dict[str, Any] = {"picks": out.picks}
            if not out.ok:
                content["error"] = out.message
            state = STATE_COMPLETED if out.ok else STATE_FAILED
            await self.emit(job_id, recipe_id, state, content, ids)
        finally:
            self.model.job = None
            await self.show()

    async def continuous_started(self, run_id: int, job_id: str, recipe_id: int, ids: dict[str, str | None]) -> None:
        self._run_id, self._run_seen, self._run_job = run_id, 0, (job_id, recipe_id, ids)
        self.model.job = "continuous"
        await self.show()

    async def _follow_run(self) -> None:
        """One result per new cycle of the run; back to Ready when it has ended."""
        snap = cell.run_snapshot(self.services)
        if snap is None or int(snap["run_id"]) != self._run_id:
            return
        job_id, recipe_id, ids = self._run_job
        last = snap.get("last")
        if last and int(last.get("n") or 0) > self._run_seen:
            self._run_seen = int(last.get("n") or 0)
            outcome = last.get("result")
            pick = {"pick_pose": last.get("pick_pose"), "score": last.get("score"),
                    "uncertainty": last.get("uncertainty")}
            state = {"stopped": STATE_ABORTED, "vision_failed": STATE_FAILED}.get(str(outcome), STATE_COMPLETED)
            await self.emit(job_id, recipe_id, state,
                            {"picks": [pick] if last.get("pick_pose") else [], "cycle": last}, ids)
        if snap.get("ended_because") is not None:
            self.model.job = None

    def job_kind(self) -> Job | None:
        return self.model.job

    async def emit(self, job_id: str, recipe_id: int, state: int, content: dict[str, Any],
                   ids: dict[str, str | None]) -> Result:
        """Keep a result and emit its ResultReady event from VisionSystem."""
        config = await self.blocking(lambda: cell.configuration_id(self.services))
        result = Result(self.results.next_id(), job_id, recipe_id, config, state, datetime.now(UTC),
                        json.dumps(_finite(content), default=_plain, allow_nan=False, separators=(",", ":")),
                        meas_id=ids.get("MeasId"), part_id=ids.get("PartId"), product_id=ids.get("ProductId"),
                        external_recipe_id=ids.get("ExternalRecipeId"))
        self.results.add(result)
        event = self._event.event
        for name in ("MeasId", "PartId", "ProductId", "ExternalRecipeId"):  # the last job's, when this has none
            setattr(event, name, None)
        for name, value in result.event_fields().items():
            setattr(event, name, value)
            # asyncua takes a field's type from the type's default value, null for these: say it.
            event.data_types[name] = _EVENT_TYPES.get(name, ua.VariantType.ExtensionObject)
        event.Message = ua.LocalizedText(f"result {result.result_id} of job {job_id}: "
                                         f"{'completed' if state == STATE_COMPLETED else 'not completed'}")
        event.Severity = 100 if state == STATE_COMPLETED else 500
        await self._event.trigger(result.created)
        return result


def _node_id(identifier: int, ns: int) -> ua.NodeId:
    return ua.NodeId(ua.Int32(identifier), ua.Int16(ns))


def _finite(value: Any) -> Any:
    """``value`` with numpy numbers and arrays as Python ones and non-finite floats as None (JSON null)."""
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _plain(value: Any) -> str:
    """Anything else JSON does not know, as text."""
    return str(value)


async def add_vision_system(server: Server, services: Services, call: Call, executor: Executor) -> VisionSystem:
    """Import the NodeSet and build ``Objects/VisionSystem`` (before the server starts)."""
    vs = VisionSystem(server, services, call, executor)
    await vs.build()
    return vs
