"""Tables of the store (SQLAlchemy Core), the same on SQLite and PostgreSQL.

Every row carries ``cell_id``: one PostgreSQL database holds the store of many cells, and an
embedded SQLite file is simply a database that holds one. Calibration rows are immutable: a
trigger refuses ``UPDATE`` on both backends (rows are only ever inserted, and deleted by a forced
restore). ``robot_id`` is stored as ``''`` for camera-only records so that it can be part of
unique keys (SQL treats NULLs as distinct).
"""

from __future__ import annotations

import sqlalchemy as sa

SCHEMA_VERSION = 1
"""Bumped when the tables change; a store with a newer version is refused, not guessed at."""

STORE_MARKER = "cellctl-store"

metadata = sa.MetaData()

meta = sa.Table(
    "cellctl_meta", metadata,
    sa.Column("key", sa.String(64), primary_key=True),
    sa.Column("value", sa.Text, nullable=False),
)

calibrations = sa.Table(
    "calibrations", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("kind", sa.String(16), nullable=False),
    sa.Column("camera_id", sa.String(128), nullable=False),
    sa.Column("robot_id", sa.String(128), nullable=False),
    sa.Column("version", sa.Integer, nullable=False),
    sa.Column("result_json", sa.Text, nullable=False),
    sa.Column("inputs_json", sa.Text, nullable=False),
    sa.Column("sha256", sa.String(64), nullable=False),
    sa.Column("tool_version", sa.String(64), nullable=False),
    sa.Column("creator", sa.String(256), nullable=False),
    sa.Column("note", sa.Text, nullable=False),
    sa.Column("created_s", sa.Double, nullable=False),
    sa.UniqueConstraint("cell_id", "kind", "camera_id", "robot_id", "version", name="uq_calibration_version"),
    sa.CheckConstraint("kind IN ('camera', 'handeye', 'npoint')", name="ck_calibration_kind"),
)

activations = sa.Table(
    "activations", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("kind", sa.String(16), nullable=False),
    sa.Column("camera_id", sa.String(128), nullable=False),
    sa.Column("robot_id", sa.String(128), nullable=False),
    # 1, 2, ... per (cell_id, kind, camera_id, robot_id): the row with the highest is the current state
    sa.Column("seq", sa.Integer, nullable=False),
    # the active calibration in this state; NULL: none active
    sa.Column("calibration_id", sa.Integer, sa.ForeignKey("calibrations.id"), nullable=True),
    # the state a rollback returns to; NULL: the state before the first activation (none active)
    sa.Column("previous_seq", sa.Integer, nullable=True),
    sa.Column("action", sa.String(16), nullable=False),
    sa.Column("who", sa.String(256), nullable=False),
    sa.Column("at_s", sa.Double, nullable=False),
    sa.UniqueConstraint("cell_id", "kind", "camera_id", "robot_id", "seq", name="uq_activation_seq"),
)

recipes = sa.Table(
    "recipes", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("recipe_id", sa.Integer, nullable=False),
    sa.Column("version", sa.Integer, nullable=False),
    sa.Column("name", sa.String(256), nullable=False),
    sa.Column("data_json", sa.Text, nullable=False),
    sa.Column("creator", sa.String(256), nullable=False),
    sa.Column("created_s", sa.Double, nullable=False),
    sa.UniqueConstraint("cell_id", "recipe_id", "version", name="uq_recipe_version"),
)

audit = sa.Table(
    "audit", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("at_s", sa.Double, nullable=False),
    sa.Column("who", sa.String(256), nullable=False),
    sa.Column("action", sa.String(64), nullable=False),
    sa.Column("target", sa.String(512), nullable=False),
    sa.Column("detail_json", sa.Text, nullable=False),
    sa.Column("result", sa.Text, nullable=False),
)

latches = sa.Table(
    "robot_latches", metadata,
    # One row per latched robot (cleared: no row). Live safety state, not a record: not in CELL_TABLES,
    # so a backup's restore never latches or frees a robot (see latches.py).
    sa.Column("cell_id", sa.String(128), primary_key=True),
    sa.Column("robot_id", sa.String(128), primary_key=True),
    sa.Column("latched_by", sa.String(256), nullable=False),
    sa.Column("reason", sa.Text, nullable=False),
    sa.Column("since_s", sa.Double, nullable=False),
)

sa.Index("ix_calibrations_cell", calibrations.c.cell_id, calibrations.c.kind, calibrations.c.camera_id)
sa.Index("ix_activations_cell", activations.c.cell_id, activations.c.kind, activations.c.camera_id)
sa.Index("ix_recipes_cell", recipes.c.cell_id, recipes.c.recipe_id)
sa.Index("ix_audit_cell", audit.c.cell_id, audit.c.id)

CELL_TABLES: tuple[sa.Table, ...] = (calibrations, activations, recipes, audit)
"""The per-cell tables, in an order that satisfies the foreign keys when inserting."""

# Calibrations are immutable versions: refuse UPDATE in the database itself.
sa.event.listen(calibrations, "after_create", sa.DDL(
    "CREATE TRIGGER calibrations_immutable BEFORE UPDATE ON calibrations "
    "BEGIN SELECT RAISE(ABORT, 'calibrations are immutable versions; save a new one'); END",
).execute_if(dialect="sqlite"))
sa.event.listen(calibrations, "after_create", sa.DDL(
    "CREATE OR REPLACE FUNCTION cellctl_calibrations_immutable() RETURNS trigger LANGUAGE plpgsql AS $$ "
    "BEGIN RAISE EXCEPTION 'calibrations are immutable versions; save a new one'; END $$; "
    "CREATE TRIGGER calibrations_immutable BEFORE UPDATE ON calibrations "
    "FOR EACH ROW EXECUTE FUNCTION cellctl_calibrations_immutable()",
).execute_if(dialect="postgresql"))
