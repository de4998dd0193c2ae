"""Calibrations as stored versions, as methods of :class:`cellctl.store.Store`: save, list, get, and
the active pointer with its history (activate, rollback).

A calibration is saved as an immutable version of its key (kind, camera_id, robot_id) with the
inputs it was computed from and a SHA-256 of both; a version whose payload no longer matches its
checksum is :class:`CorruptRecord`. Which version is active is an append-only history of
activations (``activations``: each row points to the one before), so a rollback walks back through
it. Every change is one write transaction with its audit entry.
"""

from __future__ import annotations

import json
import time
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa

import cellctl
from cellctl.store import schema as S
from cellctl.store.errors import CorruptRecord, InvalidInput, NotFound, NothingToRollBack, StoreError
from cellctl.store.records import CALIBRATION_KINDS, CalibrationKind, CalibrationRecord, CalibrationSummary
from cellctl.store.values import check_key, check_text, describe_key, payload_sha256, to_json_text


class CalibrationRows:
    """The calibrations of one cell and which of them are active (mixed into ``Store``)."""

    cell_id: str
    recovery: str
    if TYPE_CHECKING:
        def _write(self) -> AbstractContextManager[sa.Connection]: ...
        def _read(self) -> AbstractContextManager[sa.Connection]: ...
        def _loads(self, text: str, what: str) -> Any: ...
        def _note(self, err: StoreError) -> StoreError: ...
        def describe(self) -> str: ...
        def _audit(self, conn: sa.Connection, who: str, action: str, target: str, detail: dict[str, Any],
                   result: str, at_s: float | None = None) -> None: ...

    def save_calibration(self, kind: CalibrationKind, camera_id: str, robot_id: str | None,
                         result: dict[str, Any], inputs: dict[str, Any], creator: str,
                         note: str = "") -> CalibrationRecord:
        """Store a new immutable version for (kind, camera_id, robot_id); it is not activated.

        ``result`` is the solver's output (``cam.json``/``he.json``/``np.json`` content), ``inputs``
        what it was computed from (observations, robot poses). The version number is one more than
        the highest stored for that key. Nothing is ever overwritten.
        """
        check_key(kind, camera_id, robot_id)
        check_text(creator, "creator")
        if not isinstance(result, dict) or not isinstance(inputs, dict):
            raise InvalidInput("save_calibration: result and inputs must be dicts")
        result_json = to_json_text(result, "calibration result")
        inputs_json = to_json_text(inputs, "calibration inputs")
        sha = payload_sha256(result_json, inputs_json)
        now = time.time()
        rid = robot_id or ""
        c = S.calibrations.c
        with self._write() as conn:
            version = conn.execute(sa.select(sa.func.coalesce(sa.func.max(c.version), 0)).where(
                c.cell_id == self.cell_id, c.kind == kind, c.camera_id == camera_id, c.robot_id == rid,
            )).scalar_one() + 1
            cal_id = conn.execute(S.calibrations.insert().values(
                cell_id=self.cell_id, kind=kind, camera_id=camera_id, robot_id=rid, version=version,
                result_json=result_json, inputs_json=inputs_json, sha256=sha,
                tool_version=cellctl.__version__, creator=creator, note=note, created_s=now,
            ).returning(c.id)).scalar_one()
            self._audit(conn, creator, "calibration.save", f"calibration:{cal_id}",
                        {"kind": kind, "camera_id": camera_id, "robot_id": robot_id, "version": version,
                         "note": note, "sha256": sha}, "ok", now)
            active_id = self._active_id(conn, kind, camera_id, rid)
        return CalibrationRecord(
            id=int(cal_id), cell_id=self.cell_id, kind=kind, camera_id=camera_id, robot_id=robot_id,
            version=int(version), tool_version=cellctl.__version__, creator=creator, note=note, created_s=now,
            active=active_id == cal_id, result=json.loads(result_json), inputs=json.loads(inputs_json), sha256=sha)

    def list_calibrations(self, kind: CalibrationKind | None = None, camera_id: str | None = None,
                          robot_id: str | None = None) -> list[CalibrationSummary]:
        """Stored versions (without result and inputs), oldest first; ``None`` filters match all."""
        if kind is not None and kind not in CALIBRATION_KINDS:
            raise InvalidInput(f"kind {kind!r} is not one of {', '.join(CALIBRATION_KINDS)}")
        c = S.calibrations.c
        q = sa.select(c.id, c.kind, c.camera_id, c.robot_id, c.version, c.tool_version, c.creator, c.note,
                      c.created_s).where(c.cell_id == self.cell_id)
        if kind is not None:
            q = q.where(c.kind == kind)
        if camera_id is not None:
            q = q.where(c.camera_id == camera_id)
        if robot_id is not None:
            q = q.where(c.robot_id == robot_id)
        with self._read() as conn:
            rows = conn.execute(q.order_by(c.id)).all()
            active = self._all_active_ids(conn)
        return [CalibrationSummary(
            id=r.id, cell_id=self.cell_id, kind=r.kind, camera_id=r.camera_id, robot_id=r.robot_id or None,
            version=r.version, tool_version=r.tool_version, creator=r.creator, note=r.note,
            created_s=r.created_s, active=r.id in active) for r in rows]

    def get_calibration(self, cal_id: int) -> CalibrationRecord:
        """One version, complete; :class:`NotFound` when this cell has no calibration ``cal_id``."""
        with self._read() as conn:
            row = self._calibration_row(conn, cal_id)
            active = self._active_id(conn, row.kind, row.camera_id, row.robot_id) == row.id
        return self._record(row, active)

    def activate(self, cal_id: int, who: str) -> CalibrationRecord:
        """Make ``cal_id`` the active version of its (kind, camera_id, robot_id); logged.

        Activating the version that is already active changes nothing but is still logged.
        """
        check_text(who, "who")
        with self._write() as conn:
            row = self._calibration_row(conn, cal_id)
            current = self._current_state(conn, row.kind, row.camera_id, row.robot_id)
            key = describe_key(row.kind, row.camera_id, row.robot_id or None)
            detail = {"kind": row.kind, "camera_id": row.camera_id, "robot_id": row.robot_id or None,
                      "version": row.version,
                      "previous_calibration_id": current.calibration_id if current is not None else None}
            if current is not None and current.calibration_id == row.id:
                self._audit(conn, who, "calibration.activate", f"calibration:{row.id}", detail, "already active")
            else:
                self._append_state(conn, row.kind, row.camera_id, row.robot_id, row.id,
                                   current.seq if current is not None else None, "activate", who,
                                   (current.seq if current is not None else 0) + 1)
                self._audit(conn, who, "calibration.activate", f"calibration:{row.id}", detail, f"ok: active {key}")
        return self._record(row, True)

    def active(self, kind: CalibrationKind, camera_id: str, robot_id: str | None = None) -> CalibrationRecord | None:
        """The active version of (kind, camera_id, robot_id), or ``None`` when none is."""
        check_key(kind, camera_id, robot_id)
        with self._read() as conn:
            cal_id = self._active_id(conn, kind, camera_id, robot_id or "")
            if cal_id is None:
                return None
            return self._record(self._calibration_row(conn, cal_id), True)

    def rollback(self, kind: CalibrationKind, camera_id: str, robot_id: str | None,
                 who: str) -> CalibrationRecord | None:
        """Re-activate the version that was active before the current one; logged.

        Repeated rollbacks walk back through the activation history. Rolling back the first
        activation leaves none active (returns ``None``); with nothing to go back to it raises
        :class:`NothingToRollBack`.
        """
        check_key(kind, camera_id, robot_id)
        check_text(who, "who")
        rid = robot_id or ""
        key = describe_key(kind, camera_id, robot_id)
        a = S.activations.c
        with self._write() as conn:
            current = self._current_state(conn, kind, camera_id, rid)
            if current is None or (current.calibration_id is None and current.previous_seq is None):
                raise NothingToRollBack(f"rollback: no earlier activation of the {key} calibration to go back to")
            if current.previous_seq is None:
                target_id, target_prev = None, None
            else:
                prev = conn.execute(sa.select(a.calibration_id, a.previous_seq).where(
                    a.cell_id == self.cell_id, a.kind == kind, a.camera_id == camera_id, a.robot_id == rid,
                    a.seq == current.previous_seq)).one()
                target_id, target_prev = prev.calibration_id, prev.previous_seq
            self._append_state(conn, kind, camera_id, rid, target_id, target_prev, "rollback", who, current.seq + 1)
            self._audit(conn, who, "calibration.rollback", key,
                        {"kind": kind, "camera_id": camera_id, "robot_id": robot_id,
                         "from_calibration_id": current.calibration_id, "to_calibration_id": target_id},
                        f"ok: active {target_id}" if target_id is not None else "ok: none active")
            row = self._calibration_row(conn, target_id) if target_id is not None else None
        return self._record(row, True) if row is not None else None

    def activation_history(self, kind: CalibrationKind, camera_id: str,
                           robot_id: str | None = None) -> list[dict[str, Any]]:
        """Every activation/rollback of (kind, camera_id, robot_id), oldest first."""
        check_key(kind, camera_id, robot_id)
        a = S.activations.c
        with self._read() as conn:
            rows = conn.execute(sa.select(a.seq, a.calibration_id, a.action, a.who, a.at_s).where(
                a.cell_id == self.cell_id, a.kind == kind, a.camera_id == camera_id,
                a.robot_id == (robot_id or "")).order_by(a.seq)).all()
        return [dict(r._mapping) for r in rows]

    def _calibration_row(self, conn: sa.Connection, cal_id: int) -> sa.Row[Any]:
        if isinstance(cal_id, bool) or not isinstance(cal_id, int):
            raise InvalidInput(f"calibration id must be an integer, got {cal_id!r}")
        c = S.calibrations.c
        row = conn.execute(sa.select(S.calibrations).where(c.id == cal_id, c.cell_id == self.cell_id)).one_or_none()
        if row is None:
            raise NotFound(f"calibration {cal_id} not found in the store of cell {self.cell_id!r}; "
                           "list the stored ones with list_calibrations / GET /calibrations")
        return row

    def _record(self, row: sa.Row[Any], active: bool) -> CalibrationRecord:
        if payload_sha256(row.result_json, row.inputs_json) != row.sha256:
            raise self._note(CorruptRecord(f"calibration {row.id}: stored payload does not match its checksum: the "
                                           f"store {self.describe()} is damaged; {self.recovery}"))
        return CalibrationRecord(
            id=row.id, cell_id=row.cell_id, kind=row.kind, camera_id=row.camera_id, robot_id=row.robot_id or None,
            version=row.version, tool_version=row.tool_version, creator=row.creator, note=row.note,
            created_s=row.created_s, active=active, result=self._loads(row.result_json, "a calibration"),
            inputs=self._loads(row.inputs_json, "a calibration"), sha256=row.sha256)

    def _current_state(self, conn: sa.Connection, kind: str, camera_id: str, rid: str) -> sa.Row[Any] | None:
        a = S.activations.c
        q = sa.select(S.activations).where(
            a.cell_id == self.cell_id, a.kind == kind, a.camera_id == camera_id, a.robot_id == rid,
        ).order_by(a.seq.desc()).limit(1)
        return conn.execute(q).one_or_none()

    def _active_id(self, conn: sa.Connection, kind: str, camera_id: str, rid: str) -> int | None:
        state = self._current_state(conn, kind, camera_id, rid)
        return None if state is None else state.calibration_id

    def _all_active_ids(self, conn: sa.Connection) -> set[int]:
        a = S.activations.c
        latest = sa.select(a.kind, a.camera_id, a.robot_id, sa.func.max(a.seq).label("seq")).where(
            a.cell_id == self.cell_id).group_by(a.kind, a.camera_id, a.robot_id).subquery()
        q = sa.select(a.calibration_id).join(latest, sa.and_(
            a.kind == latest.c.kind, a.camera_id == latest.c.camera_id, a.robot_id == latest.c.robot_id,
            a.seq == latest.c.seq)).where(a.cell_id == self.cell_id, a.calibration_id.is_not(None))
        return {int(x) for x in conn.execute(q).scalars()}

    def _append_state(self, conn: sa.Connection, kind: str, camera_id: str, rid: str, cal_id: int | None,
                      previous_seq: int | None, action: str, who: str, seq: int) -> None:
        conn.execute(S.activations.insert().values(
            cell_id=self.cell_id, kind=kind, camera_id=camera_id, robot_id=rid, seq=seq,
            calibration_id=cal_id, previous_seq=previous_seq, action=action, who=who, at_s=time.time()))
