"""BeltWatch read on one thread while another samples the count (REST's ``GET /production`` reads the belt's
speed while the run's thread reads the encoder): the reader never fails and sees a consistent speed."""

from __future__ import annotations

import sys
import threading
import time

import pytest

from cellctl.production.belt import BeltWatch

TICKS_PER_M = 10000.0
TICKS_PER_S = 1000  # 100 mm/s


def test_the_speed_is_read_safely_while_the_run_samples_the_count() -> None:
    """A writer samples as fast as it can (a full window: every sample drops the oldest) while the reader asks
    the speed for 0.5 s, thread switches forced often: no ``deque mutated during iteration``, and every speed
    read is the belt's (the samples' times and counts are exact, so any consistent window gives 100 mm/s)."""
    w = BeltWatch(TICKS_PER_M)
    for k in range(400):
        w.sample(k, t=k / TICKS_PER_S)
    halt = threading.Event()

    def sample_fast() -> None:
        k = 400
        while not halt.is_set():
            w.sample(k, t=k / TICKS_PER_S)
            k += 1

    errors: list[BaseException] = []
    speeds: list[float] = []
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    writer = threading.Thread(target=sample_fast, daemon=True)
    writer.start()
    try:
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            try:
                speeds.append(w.speed_mm_s(0.1))
            except RuntimeError as exc:  # the race: the samples changed under the reader
                errors.append(exc)
    finally:
        halt.set()
        writer.join(5.0)
        sys.setswitchinterval(old)
    assert not errors, f"{len(errors)} of {len(errors) + len(speeds)} reads failed: {errors[0]!r}"
    assert speeds and all(s == pytest.approx(100.0, rel=1e-9) for s in speeds)


def test_reads_of_the_count_are_one_at_a_time_so_two_readers_never_fake_a_jump() -> None:
    """The run's thread and its count watcher both read the count (``BeltWatch.read``). One reader held in its
    read (a driver's slow answer, a loaded machine) while the belt moves 100 ticks: the other reader's read waits
    until the first one's count is sampled, so the newer count is sampled after the older one, over the time it
    took (100 mm/s), never an older count just after a newer one (100 ticks in a few ms: a jump that was not)."""
    w = BeltWatch(TICKS_PER_M)
    entered, release = threading.Event(), threading.Event()
    second_read_at: list[float] = []
    answers: dict[str, tuple[int, str | None]] = {}

    def held_read() -> int:
        entered.set()
        release.wait(5.0)
        return 1000

    def second_read() -> int:
        second_read_at.append(time.monotonic())
        return 1100

    first = threading.Thread(target=lambda: answers.update(first=w.read(held_read)), daemon=True)
    first.start()
    assert entered.wait(5.0)
    second = threading.Thread(target=lambda: answers.update(second=w.read(second_read)), daemon=True)
    second.start()
    second.join(0.1)
    assert second.is_alive() and not second_read_at  # waits for the first read's sample
    released_at = time.monotonic()
    release.set()
    first.join(5.0)
    second.join(5.0)
    assert second_read_at and second_read_at[0] >= released_at
    assert answers == {"first": (1000, None), "second": (1100, None)}  # 100 ticks since the held read began
