"""Recipes as methods of :class:`cellctl.store.Store`: every save is a new version, the newest is in force.

``save_recipe``, ``get_recipe``, ``list_recipes`` here; rolling back to an older version, duplicating
and deleting in ``recipe_versions.py``. Each write is the store's one write transaction with its audit
entry (``recipe.save``, ``recipe.activate``, ...).
"""

from __future__ import annotations

import json
import time
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any, cast

import sqlalchemy as sa

from cellctl.store import recipe_versions as RV
from cellctl.store import schema as S
from cellctl.store.errors import InvalidInput, NotFound
from cellctl.store.records import Recipe
from cellctl.store.values import check_text, to_json_text

if TYPE_CHECKING:
    from cellctl.store.store import Store


class RecipeRows:
    """The recipes of one cell (mixed into ``Store``: the same connection pool and write path)."""

    cell_id: str
    if TYPE_CHECKING:
        def _write(self) -> AbstractContextManager[sa.Connection]: ...
        def _read(self) -> AbstractContextManager[sa.Connection]: ...
        def _loads(self, text: str, what: str) -> Any: ...
        def _audit(self, conn: sa.Connection, who: str, action: str, target: str, detail: dict[str, Any],
                   result: str, at_s: float | None = None) -> None: ...

    def save_recipe(self, recipe_id: int, name: str, data: dict[str, Any], who: str) -> Recipe:
        """Store a new version of recipe ``recipe_id`` (the latest version is the one in force)."""
        if isinstance(recipe_id, bool) or not isinstance(recipe_id, int) or recipe_id < 0:
            raise InvalidInput(f"recipe id must be a non-negative integer (the PLC's recipe number), got {recipe_id!r}")
        check_text(name, "recipe name")
        check_text(who, "who")
        if not isinstance(data, dict):
            raise InvalidInput("save_recipe: data must be a dict")
        data_json = to_json_text(data, "recipe data")
        now = time.time()
        r = S.recipes.c
        with self._write() as conn:
            version = conn.execute(sa.select(sa.func.coalesce(sa.func.max(r.version), 0)).where(
                r.cell_id == self.cell_id, r.recipe_id == recipe_id)).scalar_one() + 1
            conn.execute(S.recipes.insert().values(
                cell_id=self.cell_id, recipe_id=recipe_id, version=version, name=name, data_json=data_json,
                creator=who, created_s=now))
            self._audit(conn, who, "recipe.save", f"recipe:{recipe_id}", {"name": name, "version": version}, "ok", now)
        return Recipe(recipe_id=recipe_id, version=int(version), name=name, data=json.loads(data_json),
                      creator=who, created_s=now, cell_id=self.cell_id)

    def get_recipe(self, recipe_id: int, version: int | None = None) -> Recipe:
        """The latest version of recipe ``recipe_id`` (or the given ``version``); :class:`NotFound` if absent."""
        r = S.recipes.c
        q = sa.select(S.recipes).where(r.cell_id == self.cell_id, r.recipe_id == recipe_id)
        q = q.where(r.version == version) if version is not None else q.order_by(r.version.desc()).limit(1)
        with self._read() as conn:
            row = conn.execute(q).one_or_none()
        if row is None:
            which = f"recipe {recipe_id}" + (f" version {version}" if version is not None else "")
            raise NotFound(f"{which} not found in the store of cell {self.cell_id!r}; list them with list_recipes")
        return self._recipe(row)

    def list_recipes(self) -> list[Recipe]:
        """The latest version of every recipe, by recipe id."""
        r = S.recipes.c
        latest = sa.select(r.recipe_id, sa.func.max(r.version).label("version")).where(
            r.cell_id == self.cell_id).group_by(r.recipe_id).subquery()
        q = sa.select(S.recipes).join(latest, sa.and_(r.recipe_id == latest.c.recipe_id,
                                                      r.version == latest.c.version)).where(
            r.cell_id == self.cell_id).order_by(r.recipe_id)
        with self._read() as conn:
            return [self._recipe(row) for row in conn.execute(q).all()]

    # -- versions (recipe_versions.py) --------------------------------------------------------------
    def recipe_versions(self, recipe_id: int) -> list[Recipe]:
        """Every version of a recipe, newest first (the newest is in force)."""
        return RV.versions(cast("Store", self), recipe_id)

    def activate_recipe_version(self, recipe_id: int, version: int, who: str) -> Recipe:
        """Roll back: ``version``'s data stored as the recipe's new version (nothing is rewritten)."""
        return RV.activate_version(cast("Store", self), recipe_id, version, who)

    def duplicate_recipe(self, recipe_id: int, new_recipe_id: int, who: str, name: str | None = None) -> Recipe:
        return RV.duplicate(cast("Store", self), recipe_id, new_recipe_id, who, name)

    def delete_recipe(self, recipe_id: int, who: str) -> int:
        return RV.delete(cast("Store", self), recipe_id, who)

    def _recipe(self, row: sa.Row[Any]) -> Recipe:
        return Recipe(recipe_id=row.recipe_id, version=row.version, name=row.name, creator=row.creator,
                      data=self._loads(row.data_json, f"recipe {row.recipe_id}"), created_s=row.created_s,
                      cell_id=row.cell_id)
