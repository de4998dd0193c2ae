"""Recipes managed like calibrations: every save is a new version, and none is ever rewritten.

The version in force is a recipe's newest. Rolling back to an older version (``activate_version``)
therefore stores a *new* version holding that version's data (``data`` unchanged, the audit entry
names the version it came from): the history only grows, and what a run or a PLC read before stays
readable. ``duplicate`` copies a recipe's version in force under a new recipe id (its version 1);
``delete`` removes every version of a recipe (the caller checks that no run uses it). Each act is
written in one transaction with its audit entry (``recipe.activate``, ``recipe.duplicate``,
``recipe.delete``).

Used through :class:`cellctl.store.Store` (``recipe_versions``, ``activate_recipe_version``,
``duplicate_recipe``, ``delete_recipe``).
"""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING

import sqlalchemy as sa

from cellctl.store import schema as S
from cellctl.store.errors import InvalidInput, NotFound
from cellctl.store.records import Recipe

if TYPE_CHECKING:
    from cellctl.store.store import Store


class RecipeExists(InvalidInput):
    """The recipe id a duplicate was asked to take is already used."""


def versions(store: Store, recipe_id: int) -> list[Recipe]:
    """Every version of recipe ``recipe_id``, newest first; :class:`NotFound` when it has none."""
    r = S.recipes.c
    q = sa.select(S.recipes).where(r.cell_id == store.cell_id, r.recipe_id == recipe_id).order_by(r.version.desc())
    with store._read() as conn:
        rows = conn.execute(q).all()
    if not rows:
        raise NotFound(f"recipe {recipe_id} not found in the store of cell {store.cell_id!r}")
    return [store._recipe(row) for row in rows]


def activate_version(store: Store, recipe_id: int, version: int, who: str) -> Recipe:
    """Put ``version`` of ``recipe_id`` back in force: a new version with its data (``NotFound`` if absent)."""
    old = store.get_recipe(recipe_id, version)
    new = _insert(store, recipe_id, old.name, old.data, who, "recipe.activate",
                  {"name": old.name, "from_version": version})
    return new


def duplicate(store: Store, recipe_id: int, new_recipe_id: int, who: str, name: str | None = None) -> Recipe:
    """Recipe ``recipe_id``'s version in force stored as version 1 of ``new_recipe_id`` (unused id)."""
    if isinstance(new_recipe_id, bool) or not isinstance(new_recipe_id, int) or new_recipe_id < 0:
        raise InvalidInput(f"new recipe id must be a non-negative integer, got {new_recipe_id!r}")
    src = store.get_recipe(recipe_id)
    if any(r.recipe_id == new_recipe_id for r in store.list_recipes()):
        raise RecipeExists(f"recipe {new_recipe_id} already exists; choose an unused recipe id "
                           f"(GET /recipes lists the used ones)")
    return _insert(store, new_recipe_id, name or src.name, src.data, who, "recipe.duplicate",
                   {"name": name or src.name, "from_recipe": recipe_id, "from_version": src.version})


def delete(store: Store, recipe_id: int, who: str) -> int:
    """Remove every version of ``recipe_id`` (audited with its name and version count); the count removed."""
    latest = store.get_recipe(recipe_id)
    r = S.recipes.c
    with store._write() as conn:
        gone = conn.execute(S.recipes.delete().where(r.cell_id == store.cell_id, r.recipe_id == recipe_id)).rowcount
        store._audit(conn, who, "recipe.delete", f"recipe:{recipe_id}",
                     {"name": latest.name, "versions": int(gone), "last_version": latest.version}, "ok")
    return int(gone)


def _insert(store: Store, recipe_id: int, name: str, data: dict[str, object], who: str, action: str,
            detail: dict[str, object]) -> Recipe:
    now = time.time()
    data_json = json.dumps(data)
    r = S.recipes.c
    with store._write() as conn:
        version = conn.execute(sa.select(sa.func.coalesce(sa.func.max(r.version), 0)).where(
            r.cell_id == store.cell_id, r.recipe_id == recipe_id)).scalar_one() + 1
        conn.execute(S.recipes.insert().values(cell_id=store.cell_id, recipe_id=recipe_id, version=version, name=name,
                                               data_json=data_json, creator=who, created_s=now))
        store._audit(conn, who, action, f"recipe:{recipe_id}", {**detail, "version": int(version)}, "ok", now)
    return Recipe(recipe_id=recipe_id, version=int(version), name=name, data=json.loads(data_json), creator=who,
                  created_s=now, cell_id=store.cell_id)
