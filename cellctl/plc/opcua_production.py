"""Production in the OPC UA address space: methods to start, pause, resume and stop a run, and the
run's state as variables of ``Cell`` (docs/plc-opcua.md).

Methods (the same requests as Modbus commands 4..7, :func:`cellctl.plc.production.execute_production`):
``StartProduction(RecipeId: Int32, Count: Int32) -> RunId: Int32`` (only with
``plc.allow_motion: true``; Count 0..1,000,000 as REST's, else BadOutOfRange),
``PauseProduction()``, ``ResumeProduction()``, ``StopProduction()``.
Failures are the status codes of the pick methods (``cellctl.plc.opcua_method_io.STATUS_OF_TEXT``).

Variables (read-only, refreshed every 0.1 s, from memory): ``ProductionRunId`` Int32 (0: none yet),
``ProductionState`` and ``ProductionEndedBecause`` String (REST's words; empty while running),
``ProductionPicked``, ``ProductionPlaced``, ``ProductionGripFailures``, ``ProductionRetries``,
``ProductionSkipped``, ``ProductionEmptyArea``, ``ProductionUnreachable``, ``ProductionNextSlot``
Int32, ``ProductionLastResult`` String, ``ProductionCycleMedianMs``, ``ProductionLastSigmaMm``,
``ProductionLastSigmaDeg`` Double (NaN: not known); the slots in doubt (docs/production.md, "Exactly
once"): ``ProductionSlotsInDoubt`` Int32 (how many; -1: the store cannot say),
``ProductionFirstSlotInDoubt`` and ``ProductionFirstSlotInDoubtRecipe`` Int32 (the first one by recipe,
then slot; -1: none). An engineer confirms a slot with ``POST /production/slots/{slot}/confirm``.
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import Node, ua

from cellctl.plc.engine import Kind, Request
from cellctl.plc.opcua_args import guarded, int_arg
from cellctl.plc.production import (
    CMD_PRODUCTION_PAUSE,
    CMD_PRODUCTION_RESUME,
    CMD_PRODUCTION_STOP,
    COUNTERS,
    doubt_values,
)
from cellctl.plc.requests import Outcome
from cellctl.production.manager import existing_manager
from cellctl.services import Services

_COUNTER_NAMES = {"picked": "ProductionPicked", "placed": "ProductionPlaced", "grip_failures": "ProductionGripFailures",
                  "retries": "ProductionRetries", "skipped": "ProductionSkipped", "empty_area": "ProductionEmptyArea",
                  "unreachable": "ProductionUnreachable"}
VARIABLES: tuple[tuple[str, Any, ua.VariantType], ...] = (
    ("ProductionRunId", 0, ua.VariantType.Int32),
    ("ProductionState", "", ua.VariantType.String),
    ("ProductionEndedBecause", "", ua.VariantType.String),
    *((_COUNTER_NAMES[k], 0, ua.VariantType.Int32) for k in COUNTERS),
    ("ProductionNextSlot", 0, ua.VariantType.Int32),
    ("ProductionLastResult", "", ua.VariantType.String),
    ("ProductionCycleMedianMs", math.nan, ua.VariantType.Double),
    ("ProductionLastSigmaMm", math.nan, ua.VariantType.Double),
    ("ProductionLastSigmaDeg", math.nan, ua.VariantType.Double),
    ("ProductionSlotsInDoubt", 0, ua.VariantType.Int32),
    ("ProductionFirstSlotInDoubt", -1, ua.VariantType.Int32),
    ("ProductionFirstSlotInDoubtRecipe", -1, ua.VariantType.Int32),
    ("ProductionMissedWindow", 0, ua.VariantType.Int32),
    ("ProductionQueueLength", 0, ua.VariantType.Int32),
)
"""``ProductionMissedWindow`` and ``ProductionQueueLength``: production from a belt (docs/conveyor.md)."""

Call = Callable[[Request], Awaitable[Outcome]]
Fail = Callable[[Outcome], Any]
Refused = Callable[[str], Awaitable[None]]
MAX_COUNT = 1_000_000
"""The largest production count a PLC may ask for (as ``POST /production/start``)."""


def production_values(services: Services) -> dict[str, Any]:
    """The variables' values now (from memory: the run's snapshot, the store's in-doubt summary)."""
    count, recipe_id, slot = doubt_values(services)
    doubt = {"ProductionSlotsInDoubt": -1 if count is None else count,
             "ProductionFirstSlotInDoubt": -1 if slot is None else slot,
             "ProductionFirstSlotInDoubtRecipe": -1 if recipe_id is None else recipe_id}
    manager = existing_manager(services)
    snap = None if manager is None else manager.snapshot()
    if snap is None:
        return doubt
    last = snap["last"] or {}
    unc = last.get("uncertainty") or {}
    sig = [s for s in (unc.get("sigma_mm") or []) if s is not None]
    median, sigma_deg = snap["cycle_median_ms"], unc.get("sigma_yaw_deg")
    out: dict[str, Any] = {
        "ProductionRunId": int(snap["run_id"]), "ProductionState": snap["state"],
        "ProductionEndedBecause": snap["ended_because"] or "", "ProductionNextSlot": int(snap["next_slot"]),
        "ProductionLastResult": str(last.get("result") or ""),
        "ProductionCycleMedianMs": math.nan if median is None else float(median),
        "ProductionLastSigmaMm": max(sig) if sig else math.nan,
        "ProductionLastSigmaDeg": math.nan if sigma_deg is None else float(sigma_deg), **doubt}
    for k in COUNTERS:
        out[_COUNTER_NAMES[k]] = int((snap["counters"] or {}).get(k, 0))  # a run killed early stored none
    out["ProductionMissedWindow"] = int((snap["counters"] or {}).get("missed_window", 0))
    out["ProductionQueueLength"] = int(snap.get("queue_length", 0))
    return out


async def add_production(cell: Node, idx: int, services: Services, call: Call, fail: Fail,
                         refused: Refused | None = None) -> dict[str, Node]:
    """Add the production methods and variables to ``Cell``; the variables' nodes by name.

    Arguments are checked first (:mod:`cellctl.plc.opcua_args`): a wrong type or count answers
    ``BadInvalidArgument``, a recipe outside 0..65535 or a count outside 0..``MAX_COUNT``
    ``BadOutOfRange`` (REST's limit), and nothing starts."""
    nodes = {name: await cell.add_variable(idx, name, value, vtype) for name, value, vtype in VARIABLES}

    def arg(name: str, vtype: ua.VariantType, description: str) -> ua.Argument:
        a = ua.Argument()
        a.Name = name
        a.DataType = ua.NodeId(ua.Int32(vtype.value))
        a.ValueRank = -1
        a.Description = ua.LocalizedText(description)
        return a

    async def start(parent: ua.NodeId, recipe: ua.Variant, count: ua.Variant) -> Any:
        r = int_arg(recipe, "RecipeId", 0, 65535)
        c = int_arg(count, "Count", 0, MAX_COUNT)
        out = await call(Request(Kind.PRODUCTION_START, r, c))
        if not out.ok:
            return fail(out)
        manager = existing_manager(services)
        snap = None if manager is None else manager.snapshot()
        return [ua.Variant(0 if snap is None else int(snap["run_id"]), ua.VariantType.Int32)]

    def simple(command: int) -> Callable[[ua.NodeId], Awaitable[Any]]:
        request = Request.from_command(command)
        if request is None:
            raise ValueError(f"command {command} is not a PLC request (a production command is)")

        async def method(parent: ua.NodeId) -> Any:
            out = await call(request)
            return fail(out) if not out.ok else []

        return method

    await cell.add_method(idx, "StartProduction", guarded("StartProduction", start, 2, refused),
                          [arg("RecipeId", ua.VariantType.Int32, "recipe number 0..65535"),
                           arg("Count", ua.VariantType.Int32, "parts to place; 0: until the area is empty")],
                          [arg("RunId", ua.VariantType.Int32, "the run's id")])
    for name, command in (("PauseProduction", CMD_PRODUCTION_PAUSE), ("ResumeProduction", CMD_PRODUCTION_RESUME),
                          ("StopProduction", CMD_PRODUCTION_STOP)):
        await cell.add_method(idx, name, guarded(name, simple(command), 0, refused), [], [])
    return nodes


async def refresh_production(nodes: dict[str, Node], services: Services, shown: dict[str, Any]) -> None:
    """Write the variables that changed since ``shown`` (updated in place)."""
    types = {name: vtype for name, _, vtype in VARIABLES}
    for name, value in production_values(services).items():
        if shown.get(name) == value or (isinstance(value, float) and math.isnan(value)
                                        and isinstance(shown.get(name), float) and math.isnan(shown[name])):
            continue
        await nodes[name].write_value(ua.DataValue(ua.Variant(value, types[name])))
        shown[name] = value
