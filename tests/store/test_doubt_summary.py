"""``Store.doubt_summary``: the slots in doubt the PLC front ends show on every read, kept in memory and
read again by the thread that changed a claim (so a PLC's read never waits for the database), and
"not known" (``StoreUnavailable``) without asking the store again at once when it could not be read."""

from __future__ import annotations

from contextlib import AbstractContextManager
from pathlib import Path

import pytest
import sqlalchemy as sa

from cellctl.store import Store, StoreUnavailable
from cellctl.store.production import DoubtSummary


def test_the_summary_follows_every_change_and_a_read_does_not_touch_the_store(tmp_path: Path,
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    store = Store(f"sqlite:///{tmp_path / 'cell.db'}", "cell")
    assert store.doubt_summary() == DoubtSummary(0)
    run = store.new_run(4, "robot0", "eng")
    store.claim_slot(4, 9, run, 1, {})
    assert store.doubt_summary() == DoubtSummary(0)  # claimed, not in doubt
    store.slot_in_doubt(4, 9, run, {"phase": "over_slot"})
    store.claim_slot(4, 10, run, 2, {})
    assert store.doubt_summary() == DoubtSummary(1, 4, 9)
    assert store.claims_in_doubt_at_start("test")[0]["slot"] == 10
    reads: list[int] = []
    real_read = store._read

    def counted() -> AbstractContextManager[sa.Connection]:
        reads.append(1)
        return real_read()

    monkeypatch.setattr(store, "_read", counted)
    for _ in range(100):  # a PLC polling
        assert store.doubt_summary() == DoubtSummary(2, 4, 9)
    assert reads == []
    store.confirm_slot(4, 9, False, "eng")  # the writer's thread reads it again once, right after its write
    assert len(reads) == 1 and store.doubt_summary() == DoubtSummary(1, 4, 10) and len(reads) == 1
    store.close()


def test_a_store_that_cannot_be_read_answers_not_known_without_waiting_on_it_each_time(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store = Store(f"sqlite:///{tmp_path / 'cell.db'}", "cell")
    attempts: list[int] = []

    def unreachable() -> AbstractContextManager[sa.Connection]:
        attempts.append(1)
        raise StoreUnavailable("store unreachable (test)")

    monkeypatch.setattr(store, "_read", unreachable)
    store.forget_doubt()  # a change met an unreachable store: logged, the summary is not known
    assert attempts == [1]
    for _ in range(50):
        with pytest.raises(StoreUnavailable):
            store.doubt_summary()
    assert attempts == [1]  # not asked again within DOUBT_RETRY_S
    monkeypatch.undo()
    store._doubt_retry_at = 0.0  # DOUBT_RETRY_S has passed
    assert store.doubt_summary() == DoubtSummary(0)  # reachable again: read
    store.close()
