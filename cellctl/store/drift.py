"""Drift checks' records, as methods of :class:`cellctl.store.Store` (``cellctl.drift`` writes them).

One row per check of a fixed camera: its JSON record (``{"t", "drift_px", "drift_mm", "drift_deg",
"state", "rule", ...}``, docs/drift.md) and the hand-eye calibration it was judged against, so that
the chart of a calibration is rebuilt from the store after a restart. In the store's backups.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa

from cellctl.store import schema as S
from cellctl.store.values import check_text, to_json_text

MAX_DRIFT_LIMIT = 10_000


class DriftRows:
    """The drift checks of one cell (mixed into ``Store``)."""

    cell_id: str
    if TYPE_CHECKING:
        def _write(self) -> AbstractContextManager[sa.Connection]: ...
        def _read(self) -> AbstractContextManager[sa.Connection]: ...
        def _loads(self, text: str, what: str) -> Any: ...

    def add_drift_check(self, camera_id: str, calibration_id: int | None, record: dict[str, Any]) -> int:
        """Store one check's record; its row id."""
        check_text(camera_id, "camera_id")
        with self._write() as conn:
            row = conn.execute(S.drift_checks.insert().values(
                cell_id=self.cell_id, camera_id=camera_id, calibration_id=calibration_id, t=float(record["t"]),
                state=str(record["state"]), record_json=to_json_text(record, "drift record"))
                .returning(S.drift_checks.c.id)).scalar_one()
        return int(row)

    def drift_checks(self, camera_id: str, limit: int = 100, calibration_id: int | None = None) -> list[dict[str, Any]]:
        """The camera's last ``limit`` checks (of ``calibration_id`` when given), oldest first."""
        limit = max(1, min(int(limit), MAX_DRIFT_LIMIT))
        t = S.drift_checks.c
        q = sa.select(t.id, t.calibration_id, t.record_json).where(t.cell_id == self.cell_id, t.camera_id == camera_id)
        if calibration_id is not None:
            q = q.where(t.calibration_id == calibration_id)
        with self._read() as conn:
            rows = conn.execute(q.order_by(t.id.desc()).limit(limit)).all()
        out = []
        for r in reversed(rows):
            rec = self._loads(str(r[2]), f"drift check {r[0]}")
            out.append({**rec, "id": int(r[0]), "calibration_id": r[1]})
        return out
