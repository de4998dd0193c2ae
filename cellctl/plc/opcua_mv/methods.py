"""The VisionSystem's methods (OPC 40100-1) linked to the cell's requests.

Every method checks its arguments before anything runs (:mod:`cellctl.plc.opcua_args`): a wrong
count or type answers ``BadInvalidArgument``, a value outside its range ``BadOutOfRange``; a method
called in a state that does not allow it answers ``BadInvalidState``. Each answers its ``Error``
output 0 on success (a failure is the call's status code).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from asyncua import Node, ua

from cellctl.plc.opcua_args import BadArgument, guarded, int_arg, invalid, out_of_range, value_of
from cellctl.plc.opcua_mv import cell
from cellctl.plc.opcua_mv.cell import (
    TEXT_BUSY,
    TEXT_DEVICE,
    TEXT_MOTION_OFF,
    TEXT_RECIPE_RANGE,
    TEXT_ROBOT_BUSY,
    TEXT_ROBOT_STOPPED,
    TEXT_UNKNOWN_RECIPE,
    Outcome,
)
from cellctl.plc.opcua_mv.results import KEEP, id_of, ids_filter, internal_recipe_id, mv_type

if TYPE_CHECKING:
    from cellctl.plc.opcua_mv.system import VisionSystem

MAX_COUNT = 1_000_000
OK = ua.Variant(0, ua.VariantType.Int32)
FILTER_NAMES = ("MeasId", "PartId", "ExternalRecipeId", "InternalRecipeId", "ExternalConfigurationId",
                "InternalConfigurationId", "ProductId", "JobId")
STATUS_OF_TEXT = {TEXT_UNKNOWN_RECIPE: ua.StatusCodes.BadNotFound, TEXT_RECIPE_RANGE: ua.StatusCodes.BadOutOfRange,
                  TEXT_ROBOT_STOPPED: ua.StatusCodes.BadRequestNotAllowed, TEXT_ROBOT_BUSY: ua.StatusCodes.BadLocked,
                  TEXT_MOTION_OFF: ua.StatusCodes.BadNotExecutable, TEXT_DEVICE: ua.StatusCodes.BadResourceUnavailable,
                  TEXT_BUSY: ua.StatusCodes.BadTooManyOperations}


def _state_error(message: str) -> BadArgument:
    return BadArgument(ua.StatusCodes.BadInvalidState, message)


def _failed(out: Outcome) -> BadArgument:
    return BadArgument(STATUS_OF_TEXT.get(out.text_index, ua.StatusCodes.BadInvalidState), out.message)


def _struct(arg: Any, type_name: str, name: str, required: bool = False) -> Any:
    """A Machine Vision identifier structure argument (None when null and not ``required``)."""
    value = value_of(arg)
    if value is None and not required:
        return None
    if not isinstance(value, mv_type(type_name)):
        raise invalid(f"{name} must be a {type_name}, got {type(value).__name__}")
    ident = getattr(value, "Id", None)
    if ident is not None and (not isinstance(ident, str) or len(ident) > 255):
        raise invalid(f"{name}.Id must be a string of at most 255 characters")
    return value


def recipe_number(value: Any, name: str) -> int:
    """The recipe number in an identifier's ``Id`` ("1")."""
    ident = id_of(value)
    if ident is None or not ident.strip().lstrip("-").isdigit():
        raise invalid(f"{name}.Id must be the recipe number as a string (e.g. \"1\"), got {ident!r}")
    number = int(ident)
    if not 0 <= number <= 65535:
        raise out_of_range(f"recipe number {number} is out of range (0..65535)")
    return number


def _parameters(arg: Any, allowed: tuple[str, ...]) -> dict[str, Any]:
    """``Parameters`` (BaseDataType[]): KeyValuePairs whose keys are in ``allowed``."""
    value = value_of(arg)
    if value is None:
        return {}
    if not isinstance(value, list):
        raise invalid("Parameters must be an array of KeyValuePair")
    out: dict[str, Any] = {}
    for item in value:
        item = value_of(item)
        if not isinstance(item, ua.KeyValuePair) or item.Key is None:
            raise invalid(f"Parameters must be KeyValuePairs, got {type(item).__name__}")
        key = item.Key.Name
        if key not in allowed:
            raise invalid(f"unknown parameter {key!r}" + (f" (known: {', '.join(allowed)})" if allowed else
                                                          " (this method takes none)"))
        out[key] = item.Value
    return out


async def link_methods(vs: VisionSystem, node: Node) -> None:
    """Link the implemented methods of ``node`` (``vs``'s VisionSystem; a method not linked answers
    BadNothingToDo)."""
    ns, services = vs.ns, vs.services
    m = vs.model

    def operational(what: str) -> None:
        state = m.vision_state(vs.problem)
        if state != "Operational":
            raise _state_error(f"{what} needs the Operational state; the vision system is {state}"
                               + (f" ({vs.problem})" if vs.problem and state == "Error" else ""))

    def automatic(what: str, *states: str) -> None:
        operational(what)
        auto = m.auto_state(vs.problem)
        if auto not in states:
            raise _state_error(f"{what} needs AutomaticModeStateMachine in {' or '.join(states)}; it is "
                               f"{auto or 'not selected (call SelectModeAutomatic)'}")

    async def select_automatic(parent: ua.NodeId) -> Any:
        operational("SelectModeAutomatic")
        m.automatic = True
        await vs.show()
        return [OK]

    async def halt(parent: ua.NodeId, cause: Any, description: Any) -> Any:
        problem = await vs.stop_robot("Halt (OPC UA VisionSystem)")
        m.halted, m.automatic = True, False
        await vs.show()
        if problem:
            raise BadArgument(ua.StatusCodes.BadResourceUnavailable, problem)
        return [OK]

    async def reset(parent: ua.NodeId, cause: Any, description: Any) -> Any:
        if m.vision_state(vs.problem) not in ("Halted", "Error"):
            raise _state_error("Reset is for the Halted or Error state")
        m.halted, m.starting = False, True
        await vs.show()
        return [OK]

    async def prepare(parent: ua.NodeId, external: Any, internal_in: Any) -> Any:
        ext = _struct(external, "RecipeIdExternalDataType", "ExternalId")
        internal = _struct(internal_in, "RecipeIdInternalDataType", "InternalIdIn")
        if id_of(ext) is None and id_of(internal) is None:
            raise invalid("PrepareRecipe needs ExternalId (or InternalIdIn) with the recipe number in Id")
        number = recipe_number(ext if id_of(ext) is not None else internal, "ExternalId")
        automatic("PrepareRecipe", "Initialized", "Ready")
        stored = await vs.blocking(lambda: cell.stored_recipe(services, number))
        if stored is None:
            raise BadArgument(ua.StatusCodes.BadNotFound, f"no recipe {number} is stored (POST /recipes)")
        m.prepared = number
        await vs.show()
        return [ua.Variant(internal_recipe_id(number, stored.name, stored.version, stored.sha256),
                           ua.VariantType.ExtensionObject), ua.Variant(True, ua.VariantType.Boolean), OK]

    async def unprepare(parent: ua.NodeId, external: Any, internal_in: Any) -> Any:
        _struct(external, "RecipeIdExternalDataType", "ExternalId")
        _struct(internal_in, "RecipeIdInternalDataType", "InternalIdIn")
        automatic("UnprepareRecipe", "Initialized", "Ready")
        number, m.prepared = m.prepared, None
        await vs.show()
        return [ua.Variant(None if number is None else internal_recipe_id(number), ua.VariantType.ExtensionObject),
                OK]

    async def recipe_list(parent: ua.NodeId, external: Any, product: Any, is_prepared: Any, max_results: Any,
                          start: Any, timeout: Any) -> Any:
        ext = _struct(external, "RecipeIdExternalDataType", "ExternalId")
        _struct(product, "ProductIdDataType", "ProductId")
        prepared_filter = 2 if value_of(is_prepared) is None else int_arg(is_prepared, "IsPrepared", 0, 2)
        limit = 0 if value_of(max_results) is None else int_arg(max_results, "MaxResults", 0, 2**32 - 1)
        first = 0 if value_of(start) is None else int_arg(start, "StartIndex", 0, 2**32 - 1)
        want = None if id_of(ext) is None else recipe_number(ext, "ExternalId")
        recipes = await vs.blocking(lambda: cell.stored_recipes(services))
        hits = [r for r in recipes if (want is None or r.recipe_id == want)
                and (prepared_filter == 2 or (r.recipe_id == m.prepared) == (prepared_filter == 1))]
        end = len(hits) if limit == 0 else first + limit
        page = [internal_recipe_id(r.recipe_id, r.name, r.version, r.sha256) for r in hits[first:end]]
        return [ua.Variant(end >= len(hits), ua.VariantType.Boolean), ua.Variant(len(page), ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(page, ua.VariantType.ExtensionObject), OK]

    def job_ids(meas: Any, part: Any, recipe: Any, product: Any) -> tuple[dict[str, str | None], int]:
        values = (_struct(meas, "MeasIdDataType", "MeasId"), _struct(part, "PartIdDataType", "PartId"),
                  _struct(recipe, "RecipeIdExternalDataType", "RecipeId"),
                  _struct(product, "ProductIdDataType", "ProductId"))
        ids = ids_filter(("MeasId", "PartId", "ExternalRecipeId", "ProductId"), values)
        if ids["ExternalRecipeId"] is not None:
            number = recipe_number(values[2], "RecipeId")
        elif m.prepared is not None:
            number = m.prepared
        else:
            raise _state_error("no recipe is prepared (PrepareRecipe) and RecipeId names none")
        ids["ExternalRecipeId"] = ids["ExternalRecipeId"] or str(number)
        return ids, number

    async def single_job(parent: ua.NodeId, meas: Any, part: Any, recipe: Any, product: Any, params: Any) -> Any:
        _parameters(params, ())
        ids, number = job_ids(meas, part, recipe, product)
        automatic("StartSingleJob", "Ready", "Initialized")
        job_id = vs.next_job_id("job")
        m.job = "single"
        await vs.show()
        vs.spawn(vs.single_job(job_id, number, ids))
        return [ua.Variant(mv_type("JobIdDataType")(Id=job_id), ua.VariantType.ExtensionObject), OK]

    async def continuous(parent: ua.NodeId, meas: Any, part: Any, recipe: Any, product: Any, params: Any) -> Any:
        count_value = _parameters(params, ("Count",)).get("Count")
        count = 0 if count_value is None else int_arg(count_value, "Parameters Count", 0, MAX_COUNT)
        ids, number = job_ids(meas, part, recipe, product)
        automatic("StartContinuous", "Ready", "Initialized")
        out = await vs.call(cell.start_run(number, count))
        if not out.ok:
            raise _failed(out)
        snap = await vs.blocking(lambda: cell.run_snapshot(services))
        run_id = 0 if snap is None else int(snap["run_id"])
        job_id = f"run-{run_id}"
        await vs.continuous_started(run_id, job_id, number, ids)
        return [ua.Variant(mv_type("JobIdDataType")(Id=job_id), ua.VariantType.ExtensionObject), OK]

    async def stop(parent: ua.NodeId, cause: Any, description: Any) -> Any:
        if m.job != "continuous":
            raise _state_error(f"Stop ends a continuous execution; none runs (job: {m.job or 'none'})")
        out = await vs.call(cell.stop_run())
        if not out.ok:
            raise _failed(out)
        return [OK]

    async def abort(parent: ua.NodeId, cause: Any, description: Any) -> Any:
        problem = await vs.stop_robot("Abort (OPC UA VisionSystem)")
        await vs.show()
        if problem:
            raise BadArgument(ua.StatusCodes.BadResourceUnavailable, problem)
        return [OK]

    async def result_by_id(parent: ua.NodeId, result_id: Any, timeout: Any) -> Any:
        rid = id_of(_struct(result_id, "ResultIdDataType", "ResultId", required=True))
        if value_of(timeout) is not None:
            int_arg(timeout, "Timeout", -1, 2**31 - 1)
        result = vs.results.get(rid or "")
        if result is None:
            raise BadArgument(ua.StatusCodes.BadNotFound, f"no result {rid!r} among the last {KEEP} results")
        return [ua.Variant(0, ua.VariantType.UInt32), ua.Variant(result.structure(), ua.VariantType.ExtensionObject),
                OK]

    async def result_list(parent: ua.NodeId, state: Any, *rest: Any) -> Any:
        filters, (max_results, start, timeout) = rest[:8], rest[8:]
        types = ("MeasIdDataType", "PartIdDataType", "RecipeIdExternalDataType", "RecipeIdInternalDataType",
                 "ConfigurationIdDataType", "ConfigurationIdDataType", "ProductIdDataType", "JobIdDataType")
        values = [_struct(v, t, n) for v, t, n in zip(filters, types, FILTER_NAMES, strict=True)]
        wanted_state = 0 if value_of(state) is None else int_arg(state, "ResultState", -2**31, 2**31 - 1)
        limit = 0 if value_of(max_results) is None else int_arg(max_results, "MaxResults", 0, 2**32 - 1)
        first = 0 if value_of(start) is None else int_arg(start, "StartIndex", 0, 2**32 - 1)
        if value_of(timeout) is not None:
            int_arg(timeout, "Timeout", -1, 2**31 - 1)
        page, complete = vs.results.filtered(wanted_state, ids_filter(FILTER_NAMES, values), first, limit)
        return [ua.Variant(complete, ua.VariantType.Boolean), ua.Variant(len(page), ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant([r.structure() for r in page], ua.VariantType.ExtensionObject), OK]

    async def release(parent: ua.NodeId, handle: Any) -> Any:
        int_arg(handle, "Handle", 0, 2**32 - 1)
        return [OK]

    vsm = f"{ns}:VisionStateMachine"
    auto = [vsm, f"{ns}:AutomaticModeStateMachine"]
    table: tuple[tuple[list[str], Any, int], ...] = (
        ([vsm, f"{ns}:SelectModeAutomatic"], select_automatic, 0),
        ([vsm, f"{ns}:Halt"], halt, 2),
        ([vsm, f"{ns}:Reset"], reset, 2),
        ([*auto, f"{ns}:StartSingleJob"], single_job, 5),
        ([*auto, f"{ns}:StartContinuous"], continuous, 5),
        ([*auto, f"{ns}:Stop"], stop, 2),
        ([*auto, f"{ns}:Abort"], abort, 2),
        ([f"{ns}:RecipeManagement", f"{ns}:PrepareRecipe"], prepare, 2),
        ([f"{ns}:RecipeManagement", f"{ns}:UnprepareRecipe"], unprepare, 2),
        ([f"{ns}:RecipeManagement", f"{ns}:GetRecipeListFiltered"], recipe_list, 6),
        ([f"{ns}:RecipeManagement", f"{ns}:ReleaseRecipeHandle"], release, 1),
        ([f"{ns}:ResultManagement", f"{ns}:GetResultById"], result_by_id, 2),
        ([f"{ns}:ResultManagement", f"{ns}:GetResultListFiltered"], result_list, 12),
        ([f"{ns}:ResultManagement", f"{ns}:ReleaseResultHandle"], release, 1),
    )
    for path, fn, n_args in table:
        method = await node.get_child(path)
        vs.server.link_method(method, guarded(path[-1], fn, n_args))
