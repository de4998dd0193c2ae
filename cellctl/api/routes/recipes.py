"""Recipes managed like calibrations: versions, roll back, duplicate, delete (``POST /recipes`` saves,
``GET /recipes`` lists: ``routes/pick.py``).

Every save is a new version and none is rewritten; the newest version is in force. Rolling back
(``POST /recipes/{id}/versions/{v}/activate``) stores version ``v``'s data as a new version. A
recipe a production run uses cannot be deleted (409 ``recipe_in_use``). Every act is audited.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path
from pydantic import BaseModel, ConfigDict, Field

from cellctl.api.body import EdgeRoute
from cellctl.api.deps import Engineer, Viewer
from cellctl.api.deps_services import ServicesDep
from cellctl.api.errors import ApiError
from cellctl.store import NotFound
from cellctl.store.recipe_versions import RecipeExists
from cellctl.strict_types import Count

router = APIRouter(tags=["pick"], route_class=EdgeRoute)

RecipeId = Annotated[int, Path(ge=0, le=65535, description="the PLC's recipe number")]
RecipeVersion = Annotated[int, Path(ge=1, le=2**31 - 1, description="a stored version of the recipe (1, 2, ...)")]


class DuplicateInput(BaseModel):
    model_config = ConfigDict(extra="forbid")
    new_recipe_id: Count = Field(ge=0, le=65535, description="an unused recipe number for the copy")
    name: str | None = Field(None, min_length=1, max_length=64, description="the copy's name (default: the same)")


def _summary(r: Any) -> dict[str, Any]:
    return {"recipe_id": r.recipe_id, "version": r.version, "name": r.name, "creator": r.creator,
            "created_s": r.created_s}


def _unknown(services: ServicesDep, recipe_id: int, version: int | None = None) -> ApiError:
    stored = sorted({r.recipe_id for r in services.store.list_recipes()})
    which = f"recipe {recipe_id}" + ("" if version is None else f" version {version}")
    return ApiError(404, "unknown_recipe", f"no {which} in cell {services.config.cell_id!r}; stored recipes: "
                                           f"{', '.join(map(str, stored)) or 'none'} (GET /recipes, "
                                           f"GET /recipes/{{id}}/versions)")


@router.get("/recipes/{recipe_id}/versions")
def recipe_versions(recipe_id: RecipeId, services: ServicesDep, _: Viewer) -> list[dict[str, Any]]:
    """Every version of the recipe, newest first; ``active`` marks the one in force (the newest)."""
    try:
        found = services.store.recipe_versions(recipe_id)
    except NotFound:
        raise _unknown(services, recipe_id) from None
    return [{**_summary(r), "active": k == 0, "place": (r.data.get("place") or {}).get("kind"),
             "models": len(r.data.get("models") or [])} for k, r in enumerate(found)]


@router.get("/recipes/{recipe_id}/versions/{version}")
def recipe_version(recipe_id: RecipeId, version: RecipeVersion, services: ServicesDep,
                   _: Viewer) -> dict[str, Any]:
    try:
        out: dict[str, Any] = services.store.get_recipe(recipe_id, version).to_dict()
    except NotFound:
        raise _unknown(services, recipe_id, version) from None
    return out


@router.post("/recipes/{recipe_id}/versions/{version}/activate")
def activate_recipe_version(recipe_id: RecipeId, version: RecipeVersion, services: ServicesDep,
                            who: Engineer) -> dict[str, Any]:
    """Roll back: version ``version``'s data becomes the recipe's newest version (audited
    ``recipe.activate`` with ``from_version``). A run already going keeps the version it started with."""
    try:
        r = services.store.activate_recipe_version(recipe_id, version, who.name)
    except NotFound:
        raise _unknown(services, recipe_id, version) from None
    return {**_summary(r), "from_version": version}


@router.post("/recipes/{recipe_id}/duplicate", status_code=201)
def duplicate_recipe(recipe_id: RecipeId, body: DuplicateInput, services: ServicesDep,
                     who: Engineer) -> dict[str, Any]:
    """The recipe's version in force copied as version 1 of ``new_recipe_id`` (409 ``recipe_exists`` if used)."""
    try:
        r = services.store.duplicate_recipe(recipe_id, body.new_recipe_id, who.name, body.name)
    except NotFound:
        raise _unknown(services, recipe_id) from None
    except RecipeExists as exc:
        raise ApiError(409, "recipe_exists", str(exc)) from None
    return {**_summary(r), "from_recipe": recipe_id}


@router.delete("/recipes/{recipe_id}")
def delete_recipe(recipe_id: RecipeId, services: ServicesDep, who: Engineer) -> dict[str, Any]:
    """Every version of the recipe removed (audited ``recipe.delete``); 409 ``recipe_in_use`` while a
    production run uses it."""
    from cellctl.production.manager import existing_manager

    manager = existing_manager(services)
    runs = [] if manager is None else manager.running(recipe_id)
    if runs:
        raise ApiError(409, "recipe_in_use", f"recipe {recipe_id} is used by production run "
                                             f"{runs[0].status.run_id} ({runs[0].status.state}); stop the run "
                                             "first (POST /production/stop)")
    try:
        gone = services.store.delete_recipe(recipe_id, who.name)
    except NotFound:
        raise _unknown(services, recipe_id) from None
    return {"recipe_id": recipe_id, "deleted_versions": gone}
