"""A process killed (SIGKILL) while writing the store loses nothing it reported as committed.

A writer subprocess saves ~2 MB calibrations (and activates every other one) in a loop; it is
killed at random moments, mostly inside ``save_calibration``. Then the store must open, pass
``PRAGMA integrity_check`` (SQLite), hold every version the writer reported, each intact and
complete (compared with the regenerated payload), with contiguous version numbers, exactly one
audit entry per stored version and an active version no older than the last reported one.
"""

from __future__ import annotations

import queue
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import sqlalchemy as sa

from cellctl.store import Store
from tests.store.kill_writer import payload

WRITER = Path(__file__).with_name("kill_writer.py")
ROUNDS = 5
REPO = Path(__file__).resolve().parents[2]


def _run_and_kill(url: str, cell_id: str, start: int, rng: random.Random) -> list[str]:
    """Start a writer at save number ``start``, SIGKILL it at a random moment, return its lines."""
    proc = subprocess.Popen([sys.executable, str(WRITER), url, cell_id, str(start)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue[str | None] = queue.Queue()

    def reader() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    t = threading.Thread(target=reader, daemon=True)
    t.start()
    got: list[str] = []
    begins_wanted = rng.randint(2, 3)  # let a save or two through, then kill inside the next one
    deadline = time.monotonic() + 60
    try:
        while True:
            line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            if line is None:
                raise AssertionError(f"the writer stopped by itself: {proc.stderr.read() if proc.stderr else ''}")
            got.append(line)
            if line.startswith("begin") and sum(x.startswith("begin") for x in got) >= begins_wanted:
                time.sleep(rng.uniform(0.0, 0.05))
                break
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    t.join(timeout=30)
    while (line := lines.get()) is not None:
        got.append(line)
    assert proc.returncode == -signal.SIGKILL
    return [x for x in got if x.endswith("\n")]  # a line cut by the kill was not reported


def test_sigkill_during_writes_loses_nothing_committed(store_url: str, cell_id: str) -> None:
    rng = random.Random(20261123)
    saved: dict[int, tuple[int, int, str]] = {}  # n -> (id, version, sha256)
    last_active: int | None = None
    killed_mid_save = 0
    start = 1
    with Store(store_url, cell_id):  # create the schema before the first kill
        pass
    for _ in range(ROUNDS):
        lines = _run_and_kill(store_url, cell_id, start, rng)
        for line in lines:
            words = line.split()
            if words[0] == "saved":
                saved[int(words[1])] = (int(words[2]), int(words[3]), words[4])
            elif words[0] == "active":
                last_active = int(words[1])
            elif words[0] == "begin":
                start = int(words[1]) + 1
        killed_mid_save += lines[-1].startswith("begin")
    assert killed_mid_save >= 1, "no kill landed inside a save; the test proved nothing"
    assert len(saved) >= ROUNDS

    with Store(store_url, cell_id) as store:
        if store.backend == "sqlite":
            with store.engine.connect() as conn:
                assert conn.exec_driver_sql("PRAGMA integrity_check").scalar() == "ok"
        for n, (cal_id, version, sha) in saved.items():
            rec = store.get_calibration(cal_id)  # verifies the checksum
            assert (rec.version, rec.sha256, rec.note) == (version, sha, f"n={n}")
        stored = store.list_calibrations()
        assert [s.version for s in stored] == list(range(1, len(stored) + 1))
        ns = [int(s.note.removeprefix("n=")) for s in stored]
        assert ns == sorted(ns) and set(saved) <= set(ns)
        for s, n in zip(stored, ns, strict=True):  # reported or not, every stored version is complete
            rec = store.get_calibration(s.id)
            result, inputs = payload(n)
            assert rec.result == result and rec.inputs == inputs
        log = store.audit_log(limit=10_000, action="calibration.save")
        assert sorted(e.target for e in log) == sorted(f"calibration:{s.id}" for s in stored)
        active = store.active("handeye", "cam0", "ur0")
        assert last_active is not None and active is not None and active.id >= last_active
        history = store.activation_history("handeye", "cam0", "ur0")
        assert len(store.audit_log(limit=10_000, action="calibration.activate")) == len(history)
        with store.engine.connect() as conn:  # the store still takes writes
            conn.execute(sa.text("SELECT 1"))
        after = store.save_calibration("handeye", "cam0", "ur0", {}, {}, "test")
        assert after.version == len(stored) + 1
    print(f"{store_url.split(':')[0]}: {len(stored)} versions, {len(saved)} reported, "
          f"{killed_mid_save}/{ROUNDS} kills inside a save")
