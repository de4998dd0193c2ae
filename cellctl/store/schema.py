"""Tables of the store (SQLAlchemy Core), the same on SQLite and PostgreSQL.

Every row carries ``cell_id``: one PostgreSQL database holds the store of many cells, and an
embedded SQLite file is simply a database that holds one. Calibration rows are immutable: a
trigger refuses ``UPDATE`` on both backends (rows are only ever inserted, and deleted by a forced
restore). ``robot_id`` is stored as ``''`` for camera-only records so that it can be part of
unique keys (SQL treats NULLs as distinct).

Production's state is part of the one schema: the runs, every cycle's record, the next free place
slot per recipe and the slots claimed for a part that is on its way or whose fate is in doubt
(``cellctl.store.production``). Version 1 stores kept the first three in tables created on first
use (same names, no ``progress_json``); opening one migrates it to version 2 in place.
"""

from __future__ import annotations

import sqlalchemy as sa

SCHEMA_VERSION = 3
"""Bumped when the tables change; a store with a newer version is refused, not guessed at.
1: calibrations, activations, recipes, audit, latches (production in tables of its own);
2: production runs, cycles, slots and slot claims in the schema (see :data:`MIGRATIONS`);
3: drift checks (``drift_checks``)."""

STORE_MARKER = "cellctl-store"
KIND_CHECK = "kind IN ('camera', 'handeye', 'npoint', 'conveyor')"
"""The calibration kinds a row may have (``conveyor`` came with conveyor tracking, in schema version 2: a
store made before it gets the wider check at its next start, ``Store._widen_kind_check``)."""

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
    sa.CheckConstraint(KIND_CHECK, name="ck_calibration_kind"),
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

production_runs = sa.Table(
    "production_runs", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("recipe_id", sa.Integer, nullable=False),
    sa.Column("robot_id", sa.String(128), nullable=False),
    sa.Column("started_by", sa.String(256), nullable=False),
    sa.Column("started_s", sa.Double, nullable=False),
    sa.Column("ended_s", sa.Double, nullable=True),
    sa.Column("state", sa.String(16), nullable=False),
    sa.Column("ended_because", sa.String(32), nullable=True),
    sa.Column("summary_json", sa.Text, nullable=False),
    # where the run is in its cycle (phase, cycle n, the part held, the slot claimed): what a run the
    # service did not end is ended with at the next start (interrupted)
    sa.Column("progress_json", sa.Text, nullable=False, server_default="{}"),
)

production_cycles = sa.Table(
    "production_cycles", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("run_id", sa.Integer, nullable=False),
    sa.Column("n", sa.Integer, nullable=False),
    sa.Column("t", sa.Double, nullable=False),
    sa.Column("result", sa.String(32), nullable=False),
    sa.Column("record_json", sa.Text, nullable=False),
    sa.UniqueConstraint("cell_id", "run_id", "n", name="uq_production_cycle"),
)

production_slots = sa.Table(
    "production_slots", metadata,
    # the recipe's next free place slot (the slot counter)
    sa.Column("cell_id", sa.String(128), primary_key=True),
    sa.Column("recipe_id", sa.Integer, primary_key=True),
    sa.Column("next_slot", sa.Integer, nullable=False),
    sa.Column("who", sa.String(256), nullable=False),
    sa.Column("at_s", sa.Double, nullable=False),
)

slot_claims = sa.Table(
    "production_slot_claims", metadata,
    # A slot a run took for the part it carries, before the part is released. 'claimed': the run is
    # on it; 'in_doubt': the run ended (a Stop, a kill, a power loss) before it knew the part was
    # placed: no run places there until an engineer confirms the slot (occupied or empty).
    sa.Column("cell_id", sa.String(128), primary_key=True),
    sa.Column("recipe_id", sa.Integer, primary_key=True),
    sa.Column("slot", sa.Integer, primary_key=True),
    sa.Column("run_id", sa.Integer, nullable=False),
    sa.Column("n", sa.Integer, nullable=False),
    sa.Column("state", sa.String(16), nullable=False),
    sa.Column("at_s", sa.Double, nullable=False),
    sa.Column("detail_json", sa.Text, nullable=False),
    sa.CheckConstraint("state IN ('claimed', 'in_doubt')", name="ck_slot_claim_state"),
)

drift_checks = sa.Table(
    "drift_checks", metadata,
    # One drift check of a fixed camera (cellctl.drift): its record (drift_px, drift_mm, drift_deg, state,
    # rule, ...) and the hand-eye calibration it was judged against (its chart is that calibration's).
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("cell_id", sa.String(128), nullable=False),
    sa.Column("camera_id", sa.String(128), nullable=False),
    sa.Column("calibration_id", sa.Integer, nullable=True),
    sa.Column("t", sa.Double, nullable=False),
    sa.Column("state", sa.String(16), nullable=False),
    sa.Column("record_json", sa.Text, nullable=False),
)

sa.Index("ix_calibrations_cell", calibrations.c.cell_id, calibrations.c.kind, calibrations.c.camera_id)
sa.Index("ix_activations_cell", activations.c.cell_id, activations.c.kind, activations.c.camera_id)
sa.Index("ix_recipes_cell", recipes.c.cell_id, recipes.c.recipe_id)
sa.Index("ix_audit_cell", audit.c.cell_id, audit.c.id)
sa.Index("ix_production_cycles_run", production_cycles.c.cell_id, production_cycles.c.run_id, production_cycles.c.n)
sa.Index("ix_drift_checks_cell", drift_checks.c.cell_id, drift_checks.c.camera_id, drift_checks.c.id)

CELL_TABLES: tuple[sa.Table, ...] = (calibrations, activations, recipes, audit, production_runs, production_cycles,
                                     production_slots, slot_claims, drift_checks)
"""The per-cell tables (a backup's content), in an order that satisfies the references when inserting."""

ADDED_COLUMNS: dict[int, tuple[tuple[sa.Table, sa.Column[object], str], ...]] = {
    2: ((production_runs, production_runs.c.progress_json, "'{}'"),),
}
"""Columns a version added to a table an older store may already hold (with the value old rows get):
the migration adds them; a backup of an older version gets them filled in."""

TABLES_SINCE: dict[str, int] = {**{t.name: 2 for t in (production_runs, production_cycles, production_slots,
                                                       slot_claims)}, drift_checks.name: 3}
"""Tables a backup of an older version may lack (restored empty)."""


def order_of(table: sa.Table) -> list[sa.Column[object]]:
    """A table's rows in a stable order (its primary key: ``id`` where it has one)."""
    return list(table.primary_key.columns)

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
