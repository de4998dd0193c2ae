"""The shared reconnect back-off and outage counter, on a clock the test advances."""

from __future__ import annotations

import pytest

from drivers.backoff import Backoff, Outages
from drivers.errors import DeviceInitError


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_waits_double_to_the_cap_and_reset_after_success() -> None:
    b = Backoff(0.25, 1.0, Clock())
    assert [b.next_wait_s() for _ in range(5)] == [0.25, 0.5, 1.0, 1.0, 1.0]
    b.reset()
    assert b.next_wait_s() == 0.25


def test_scheduled_attempts_are_due_after_their_wait() -> None:
    clock = Clock()
    b = Backoff(0.5, 4.0, clock)
    assert b.due() and not b.scheduled  # nothing failed yet: try at once
    assert b.schedule() == 0.5
    assert not b.due() and b.remaining_s() == pytest.approx(0.5)
    clock.t += 0.49
    assert not b.due()
    clock.t += 0.02
    assert b.due() and b.remaining_s() == 0.0
    assert b.schedule() == 1.0  # the second failure in a row waits twice as long
    clock.t += 0.99
    assert not b.due()
    b.reset()
    assert b.due() and b.delay_s == 0.5


def test_bad_limits_are_refused() -> None:
    with pytest.raises(DeviceInitError, match="initial"):
        Backoff(2.0, 1.0)
    with pytest.raises(DeviceInitError, match="initial"):
        Backoff(0.0, 1.0)


def test_outages_count_transitions_from_up_to_down_only() -> None:
    clock = Clock()
    o = Outages(clock)
    assert not o.down("no answer")  # never up: not an outage yet
    assert o.count == 0 and o.reason == "no answer"
    o.up()
    assert o.is_up and o.reason == ""
    assert o.down("cable pulled")
    assert not o.down("still gone")  # the same outage
    assert o.count == 1 and not o.is_up
    clock.t += 2.5
    o.up()
    assert o.last_outage_s == pytest.approx(2.5)
    clock.t += 1.0
    assert o.down("gone again", since_s=clock.t - 0.4)  # known to have stopped 0.4 s earlier
    clock.t += 1.0
    o.up()
    assert o.count == 2 and o.last_outage_s == pytest.approx(1.4)
    o.reconnected()
    assert o.reconnects == 1
