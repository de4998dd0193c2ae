"""Exactly-once placement under faults at random instants of a production cycle (issue 34).

Each block is a served ``cellctl`` on the virtual production cell (``tests/support/production_cell.py``,
real-time motion scaled by ``--time-scale``) with ``--parts`` parts; within a block, fault after fault:
a run is started, a phase of the cycle is drawn (``to_pick``, ``closing``, ``lifting``, ``carrying``,
``over_slot``, ``releasing``, ``leaving``, ``between``) and, once the run is there, after a further
random 0-40 ms, one of: a robot Stop (``POST /robots/robot0/stop``), a SIGTERM to the service, a
kill -9 of it (the service is started again on the same data dir: the sim keeps its parts). After
each fault the truth (``GET /sim/truth``) is checked against the store: parts beyond the first in any
slot (**double placements**: must be 0) and parts neither in the pick area, nor held after a stopped
run, nor in a slot the store has as placed or in doubt (**unaccounted**: must be 0); then the
engineer's recovery (resume, a held part put back, the slots in doubt confirmed from what lies there)
and the next fault. At the end of a block a last run places the rest and the books are checked again.

Run: ``.venv/bin/python bench/production_faults.py [--faults 30] [--seed 1] [--out bench/results/production_faults.md]``
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_model  # noqa: E402
from cellctl.production.config import GridPlace  # noqa: E402
from tests.support.production_cell import production_config, teach_recipe, wait_ended  # noqa: E402
from tests.support.production_faults import PHASES, books, recover, wait_phase  # noqa: E402
from tests.support.served import Served, start_served, stop_served  # noqa: E402

KINDS = ("stop", "sigterm", "kill9")


def one_block(faults: list[tuple[str, str, float]], parts: int, time_scale: float, seed: int) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="cellctl-faults-") as tmp_name:
        tmp = Path(tmp_name)
        config = production_config(tmp, count=parts, time_scale=time_scale, seed=seed)
        served: Served | None = start_served(tmp, config)
        try:
            assert served is not None
            http = served.client(timeout_s=60)
            grid = GridPlace.model_validate(teach_recipe(http)["place"])
            confirmed: set[int] = set()
            for kind, phase, extra_s in faults:
                r = http.post("/production/start", json={"recipe_id": 1})
                if r.status_code != 202:
                    raise RuntimeError(f"a run did not start: {r.text}")
                try:
                    wait_phase(http, phase)
                except AssertionError:  # the area ran empty first
                    rows.append({"kind": kind, "phase": phase, "landed": "(run ended)", "double": 0, "unaccounted": 0,
                                 "in_doubt": 0})
                    break
                time.sleep(extra_s)
                landed = phase
                if kind == "stop":
                    http.post("/robots/robot0/stop")
                    end = wait_ended(http)
                    cycles = http.get(f"/production/runs/{end['run_id']}/cycles").json()
                    landed = str(cycles[-1].get("phase") or phase)
                else:
                    os.kill(served.process.pid, signal.SIGKILL if kind == "kill9" else signal.SIGTERM)
                    served.process.wait(60)
                    served = None
                    served = start_served(tmp, config)
                    http = served.client(timeout_s=60)
                    st = http.get("/production").json()
                    cycles = http.get(f"/production/runs/{st['run_id']}/cycles").json()
                    landed = str(cycles[-1].get("phase") or phase)
                b = books(http, grid, confirmed)
                rows.append({"kind": kind, "phase": phase, "landed": landed, "double": b.double,
                             "unaccounted": len(b.unaccounted), "in_doubt": len(b.in_doubt)})
                print(rows[-1], flush=True)
                confirmed |= recover(http, grid)
            r = http.post("/production/start", json={"recipe_id": 1})
            if r.status_code == 202:
                wait_ended(http, timeout_s=300)
            b = books(http, grid, confirmed)
            placed = sum(len(v) for v in b.parts_in_slot.values())
            rows.append({"kind": "final run", "phase": "-", "landed": f"{placed}/{parts} in slots",
                         "double": b.double, "unaccounted": len(b.unaccounted), "in_doubt": len(b.in_doubt)})
            print(rows[-1], flush=True)
        finally:
            if served is not None:
                stop_served(served)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faults", type=int, default=30)
    ap.add_argument("--per-block", type=int, default=8, help="faults per served cell (then a fresh one)")
    ap.add_argument("--time-scale", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    plan = [(KINDS[i % len(KINDS)], rng.choice(PHASES), rng.uniform(0.0, 0.04)) for i in range(args.faults)]
    rng.shuffle(plan)
    t0 = time.monotonic()
    rows: list[dict[str, Any]] = []
    for b, start in enumerate(range(0, len(plan), args.per_block)):
        block = plan[start:start + args.per_block]
        rows += one_block(block, parts=len(block) + 3, time_scale=args.time_scale, seed=3 + b)
    wall = time.monotonic() - t0
    faults = [r for r in rows if r["kind"] in KINDS and r["landed"] != "(run ended)"]
    kinds = ", ".join(f"{n} {k}" for k, n in sorted(Counter(r["kind"] for r in faults).items()))
    lines = [
        "# Production: exactly once under faults at random instants",
        "",
        f"`.venv/bin/python bench/production_faults.py --faults {args.faults} --per-block {args.per_block} "
        f"--time-scale {args.time_scale} --seed {args.seed}` — {cpu_model()}, {wall:.0f} s wall.",
        "",
        f"**{len(faults)} faults** ({kinds}); "
        f"**double placements: {sum(r['double'] for r in rows)}**, **unaccounted parts: "
        f"{sum(r['unaccounted'] for r in rows)}**.",
        "",
        "| # | fault | drawn phase | phase stored | double | unaccounted | slots in doubt |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for i, r in enumerate(rows, 1):
        lines.append(f"| {i} | {r['kind']} | {r['phase']} | {r['landed']} | {r['double']} | {r['unaccounted']} | "
                     f"{r['in_doubt']} |")
    lines += ["", "`phase stored` is the stopped / interrupted cycle record's `phase` (for a kill -9: the last phase "
              "the run had stored, `to_pick`, `carrying` or `leaving`); a fault before the slot's claim leaves none "
              "in doubt. After each fault the engineer's recovery (`tests/support/production_faults.py` `recover`) "
              "confirmed the slots in doubt from the truth before the next run."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        args.out.write_text(text)
    bad = sum(r["double"] + r["unaccounted"] for r in rows)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
