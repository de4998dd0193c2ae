"""The latch keeper on real motion owners and a real SQLite store: every change stored, restored at start.

A "restart" here is what the service does at start-up: new motion owners (memory is gone) and a
new keeper over the same store file.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa

from cellctl.latches import UNREADABLE_REASON, LatchKeeper, when_text
from cellctl.store import Store
from cellctl.store import schema as S
from cellctl.store.latches import AUDIT_ACTION, StoredLatch
from drivers.motion import LatchChange, MotionOwner, RobotStopped


@pytest.fixture
def url(tmp_path: Path) -> str:
    return f"sqlite:///{tmp_path / 'cell.db'}"


def _started(store: Store, *robot_ids: str) -> tuple[LatchKeeper, dict[str, MotionOwner]]:
    owners = {rid: MotionOwner(rid) for rid in robot_ids}
    keeper = LatchKeeper(store, owners)
    keeper.restore()
    keeper.start()
    return keeper, owners


@pytest.fixture
def store(url: str) -> Iterator[Store]:
    with Store(url, "cell-a") as s:
        yield s


def test_a_latch_and_a_resume_are_stored_in_order_with_their_audit(store: Store) -> None:
    keeper, owners = _started(store, "robot0", "robot1")
    try:
        owners["robot0"].latch("operator-1", "Stop")
        assert keeper.wait_stored_blocking(10.0)
        since = owners["robot0"].status()["latched_since_s"]
        assert store.latches() == [StoredLatch("robot0", "operator-1", "Stop", since)]
        owners["robot0"].resume("engineer-1")
        owners["robot1"].latch("ur-adapter", "controller dropped out mid-move")
        assert keeper.wait_stored_blocking(10.0)
        assert [x.robot_id for x in store.latches()] == ["robot1"]
        entries = store.audit_log(10, action=AUDIT_ACTION)[::-1]
        assert [(e.target, e.who, e.detail["latched"]) for e in entries] == [
            ("robot0", "operator-1", True), ("robot0", "engineer-1", False), ("robot1", "ur-adapter", True)]
    finally:
        keeper.close()


def test_a_robot_latched_before_a_restart_is_latched_after_it_and_the_audit_says_so(store: Store, url: str) -> None:
    keeper, owners = _started(store, "robot0", "robot1")
    owners["robot0"].latch("operator-1", "Stop")
    since = owners["robot0"].status()["latched_since_s"]
    assert keeper.wait_stored_blocking(10.0)
    keeper.close()
    with Store(url, "cell-a") as again:
        keeper2, owners2 = _started(again, "robot0", "robot1")
        try:
            status = owners2["robot0"].status()
            assert (status["latched"], status["latched_by"], status["latched_reason"],
                    status["latched_since_s"]) == (True, "operator-1", "Stop", since)
            assert not owners2["robot1"].latched
            with pytest.raises(RobotStopped, match="operator-1"):
                owners2["robot0"].begin("engineer-1", "a move")
            note = again.audit_log(1, action=AUDIT_ACTION)[0]
            assert note.result == ("latched at start: stopped before the restart at "
                                   f"{when_text(since)} by operator-1 (Stop)")
            # The resume after the restart is stored too: a second restart finds the robot free.
            owners2["robot0"].resume("engineer-1")
            assert keeper2.wait_stored_blocking(10.0)
        finally:
            keeper2.close()
    with Store(url, "cell-a") as third:
        keeper3, owners3 = _started(third, "robot0")
        keeper3.close()
        assert not owners3["robot0"].latched


def test_a_stored_latch_of_a_robot_no_longer_configured_stays_stored(store: Store) -> None:
    store.set_latch("gone", "operator-1", "Stop", 100.0)
    keeper, owners = _started(store, "robot0")
    keeper.close()
    assert not owners["robot0"].latched
    assert [x.robot_id for x in store.latches()] == ["gone"]


def test_unreadable_latches_latch_every_robot(store: Store) -> None:
    with store.engine.begin() as conn:
        conn.execute(sa.text(f"DROP TABLE {S.latches.name}"))
    keeper, owners = _started(store, "robot0", "robot1")
    keeper.close()
    for owner in owners.values():
        status = owner.status()
        assert status["latched"] and status["latched_by"] == "cellctl"
        assert status["latched_reason"].startswith(UNREADABLE_REASON)


def test_a_change_the_store_refuses_is_retried_until_stored(store: Store) -> None:
    keeper, owners = _started(store, "robot0")
    try:
        with store.engine.begin() as conn:
            conn.execute(sa.text(f"DROP TABLE {S.latches.name}"))  # the store cannot take the write
        owners["robot0"].latch("operator-1", "Stop")
        assert not keeper.wait_stored_blocking(0.3)
        assert owners["robot0"].latched  # the latch in memory holds while the store is out
        S.latches.create(store.engine)  # the store is back
        assert keeper.wait_stored_blocking(10.0)
        assert [x.latched_by for x in store.latches()] == ["operator-1"]
    finally:
        keeper.close()


def test_a_change_told_after_a_newer_one_does_not_overwrite_it(store: Store) -> None:
    """Two threads latch and resume at once; their listeners may be told out of order: seq decides."""
    keeper, owners = _started(store, "robot0")
    try:
        now = time.time()
        keeper._on_change(LatchChange("robot0", False, "engineer-1", "resume", now, seq=7))
        keeper._on_change(LatchChange("robot0", True, "operator-1", "Stop", now, seq=6))
        assert keeper.wait_stored_blocking(10.0)
        assert store.latches() == []
    finally:
        keeper.close()


def test_after_close_the_keeper_stores_no_more_changes(store: Store) -> None:
    keeper, owners = _started(store, "robot0")
    keeper.close()
    owners["robot0"].latch("operator-1", "Stop")  # no longer listened to
    assert keeper.wait_stored_blocking(5.0)  # nothing told: nothing to wait for
    assert store.latches() == []


def test_a_controller_dropout_latch_is_stored_like_a_stop(store: Store) -> None:
    """The adapters latch a robot whose controller dropped out mid-sequence through the same latch."""
    keeper, owners = _started(store, "robot0")
    try:
        session = owners["robot0"].begin("engineer-1", "a two-move sequence")
        assert owners["robot0"].latch_if_owned("controller", "controller dropped out mid-sequence") is session
        assert keeper.wait_stored_blocking(10.0)
        assert [(x.latched_by, x.reason) for x in store.latches()] == [
            ("controller", "controller dropped out mid-sequence")]
        owners["robot0"].end(session)
    finally:
        keeper.close()
