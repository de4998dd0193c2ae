"""Stored robot latches on SQLite and PostgreSQL: set, clear, read back, audited, per cell, reopened."""

from __future__ import annotations

import math

import pytest

from cellctl.latches import LatchKeeper
from cellctl.store import InvalidInput, Store
from cellctl.store.latches import AUDIT_ACTION, StoredLatch
from drivers.motion import MotionOwner


def test_a_latch_is_stored_with_its_audit_entry_and_read_back_after_reopening(store: Store, store_url: str,
                                                                               cell_id: str) -> None:
    assert store.latches() == []
    store.set_latch("robot0", "operator-1", "Stop", 1_790_000_000.25)
    with Store(store_url, cell_id) as again:  # another process's view: what a restart reads
        assert again.latches() == [StoredLatch("robot0", "operator-1", "Stop", 1_790_000_000.25)]
    entry = store.audit_log(1)[0]
    assert (entry.action, entry.target, entry.who, entry.result) == (AUDIT_ACTION, "robot0", "operator-1", "stored")
    assert entry.detail == {"latched": True, "latched_by": "operator-1", "reason": "Stop", "since_s": 1_790_000_000.25}


def test_latching_again_replaces_the_row_and_clearing_removes_it(store: Store) -> None:
    store.set_latch("robot0", "operator-1", "Stop", 100.0)
    store.set_latch("robot1", "ur-adapter", "controller dropped out mid-move", 101.0)
    store.set_latch("robot0", "operator-2", "Stop", 102.0)
    assert store.latches() == [StoredLatch("robot0", "operator-2", "Stop", 102.0),
                               StoredLatch("robot1", "ur-adapter", "controller dropped out mid-move", 101.0)]
    assert store.clear_latch("robot0", "engineer-1") is True
    assert store.latches() == [StoredLatch("robot1", "ur-adapter", "controller dropped out mid-move", 101.0)]
    entry = store.audit_log(1)[0]
    assert (entry.action, entry.target, entry.who) == (AUDIT_ACTION, "robot0", "engineer-1")
    assert entry.detail == {"latched": False, "resumed_by": "engineer-1", "was_stored": True}
    # A resume of a robot that was not stored latched is still audited, and says so.
    assert store.clear_latch("robot0", "engineer-1") is False
    assert store.audit_log(1)[0].detail["was_stored"] is False


def test_latches_belong_to_their_cell(store: Store, store_url: str, cell_id: str) -> None:
    store.set_latch("robot0", "operator-1", "Stop", 100.0)
    with Store(store_url, cell_id + "-other") as other:
        assert other.latches() == []
        other.set_latch("robot0", "operator-9", "Stop", 200.0)
        other.clear_latch("robot0", "engineer-9")
    assert store.latches() == [StoredLatch("robot0", "operator-1", "Stop", 100.0)]


def test_a_latch_is_not_a_calibration_record(store: Store) -> None:
    """Latches are live state: a backup's cell tables (and the store's emptiness) do not include them."""
    store.set_latch("robot0", "operator-1", "Stop", 100.0)
    assert "robot_latches" not in store.counts()


@pytest.mark.parametrize(("robot_id", "who", "since_s"), [
    ("", "operator-1", 1.0), ("robot0", " ", 1.0), ("robot0", "operator-1", math.nan),
    ("robot0", "operator-1", math.inf), ("robot0", "operator-1", True),
])
def test_bad_latch_input_is_refused_and_nothing_is_stored(store: Store, robot_id: str, who: str,
                                                          since_s: float) -> None:
    with pytest.raises(InvalidInput):
        store.set_latch(robot_id, who, "Stop", since_s)
    assert store.latches() == []
    assert store.audit_log(10, action=AUDIT_ACTION) == []


def test_the_service_keeper_carries_a_latch_over_a_restart_on_this_backend(store: Store, store_url: str,
                                                                           cell_id: str) -> None:
    """What the service does at start and on a Stop, on SQLite and on PostgreSQL."""
    owner = MotionOwner("robot0")
    keeper = LatchKeeper(store, {"robot0": owner})
    keeper.restore()
    keeper.start()
    owner.latch("operator-1", "Stop")
    assert keeper.wait_stored_blocking(10.0)
    keeper.close()
    with Store(store_url, cell_id) as again:
        fresh = MotionOwner("robot0")  # the restarted service's robot: nothing in memory
        after = LatchKeeper(again, {"robot0": fresh})
        assert after.restore() == ["robot0"]
        after.close()
        assert fresh.status()["latched_by"] == "operator-1"
        assert again.audit_log(1, action=AUDIT_ACTION)[0].result.startswith("latched at start: ")
