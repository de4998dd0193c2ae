"""Drift detection on the virtual production cell (issue 40): how soon a bump or a slow drift of the
fixed camera raises the alarm, how often a still cell false-alarms, what the re-solve leaves, and what
the checks cost a production cycle.

Each check is the cell's own path on a rendered frame of the built-in production scene (the arm out
of view): the six fiducial marks found near where the calibration (the scene's truth before any
fault) puts them (``calibration.drift.find_marks``), ``measure`` -> ``drift_mm``, judged on the I-MR
chart with the Western Electric rules (``calibration.drift.Chart``, the cell's defaults: 20 baseline
checks, ``min_sigma_mm`` 0.02). The camera is bumped with the sim's camera fault (a shift along /
a turn about the base frame's axes). The peer is a fixed-threshold detector on the same checks:
alarm when ``drift_mm`` exceeds the baseline's mean by a fixed tolerance (0.1 mm, and 0.5 mm: the
production cell's ``verify_tolerance_mm``).

- detection delay: checks after the bump until the alarm (1 = the first check after it), per bump;
- a ramp: the camera drifts by a fixed step per check; checks and drift at the alarm;
- false alarms: ``--still`` checks of the still cell (fresh sensor noise in every frame) after the baseline;
- re-solve: the camera's pose from the fiducials after each bump; the mapping error of points over the
  pick area (table plane) through the re-solved camera against the truth (max over a 7x5 grid);
- cycle time: the same production run (in process, a scattered area) with ``drift.every_cycles`` 10
  and with checks off: the median cycle time of each (``--cycles``, 0 skips it).

Run: ``.venv/bin/python bench/drift.py [--still 500] [--cycles 20] [--out bench/results/drift.md]``.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_model  # noqa: E402
from calibration import geometry as g  # noqa: E402
from calibration.drift import Chart  # noqa: E402
from calibration.drift.fiducials import find_marks, map_to_planes, measure, predict_px, resolve  # noqa: E402
from drivers.sim.camera_fault import Fault  # noqa: E402
from drivers.sim.scene import BUILTIN_SCENES, load_scene  # noqa: E402
from drivers.sim.world import SimWorld  # noqa: E402

BASELINE = 20
MIN_SIGMA_MM = 0.02
MAX_CHECKS = 12
THRESHOLDS_MM = (0.1, 0.5)
BUMPS: list[tuple[str, Fault]] = [
    *[(f"shift x {s:g} mm", Fault((s, 0.0, 0.0))) for s in (0.05, 0.1, 0.2, 0.3, 0.5, 1.0)],
    *[(f"turn z {a:g} deg", Fault(rot_deg=(0.0, 0.0, a))) for a in (0.01, 0.02, 0.05, 0.1, 0.2)],
    *[(f"turn x {a:g} deg", Fault(rot_deg=(a, 0.0, 0.0))) for a in (0.01, 0.02, 0.05, 0.1, 0.2)],
    ("shift 0.3 mm + turn z 0.05 deg", Fault((0.3, 0.0, 0.0), (0.0, 0.0, 0.05))),
]
RAMPS: list[tuple[str, Fault]] = [("shift x 0.01 mm / check", Fault((0.01, 0.0, 0.0))),
                                  ("turn x 0.002 deg / check", Fault(rot_deg=(0.002, 0.0, 0.0)))]


class Cell:
    """The production scene's camera and marks, the arm out of view; checks against the nominal pose."""

    def __init__(self) -> None:
        self.world = SimWorld(load_scene(BUILTIN_SCENES["production"]))
        self.world.place_tool(g.ur_pose_to_transform([0.45, -0.30, 0.25, math.pi, 0.0, 0.0]))
        self.camera = self.world.camera_model
        self.world.camera_fault.set(Fault())
        self.T_cal = self.world.T_base_cam()
        self.X = np.array([[m.x_mm, m.y_mm, m.z_mm] for m in self.world.scene.fiducials]) * 1e-3
        self.pred = predict_px(self.camera, self.T_cal, self.X)

    def fault(self, f: Fault) -> None:
        self.world.camera_fault.set(f)

    def seen(self) -> np.ndarray:
        return find_marks(self.world.render(), self.pred, 40.0, 5.6)

    def check(self) -> float:
        return measure(self.camera, self.T_cal, self.seen(), self.X).drift_mm


def baseline(cell: Cell) -> tuple[Chart, float]:
    cell.fault(Fault())
    chart = Chart(BASELINE, MIN_SIGMA_MM)
    values = [cell.check() for _ in range(BASELINE)]
    for v in values:
        chart.add(v)
    return chart, float(np.mean(values))


def delay(cell: Cell, f: Fault) -> dict[str, Any]:
    chart, mean = baseline(cell)
    cell.fault(f)
    out: dict[str, Any] = {"chart": None, "rule": None, **{f"fixed {t:g}": None for t in THRESHOLDS_MM}}
    values = []
    for k in range(1, MAX_CHECKS + 1):
        v = cell.check()
        values.append(v)
        state, rule = chart.add(v)
        if state == "alarm" and out["chart"] is None:
            out["chart"], out["rule"] = k, rule
        for t in THRESHOLDS_MM:
            if v - mean > t and out[f"fixed {t:g}"] is None:
                out[f"fixed {t:g}"] = k
        if out["chart"] is not None and all(out[f"fixed {t:g}"] is not None for t in THRESHOLDS_MM):
            break
    out["drift_mm"] = float(np.median(values)) - mean
    # the re-solve on the bumped camera, and how it then maps the pick area against the truth
    r = resolve(cell.camera, cell.T_cal, cell.seen(), cell.X)
    out["resolve_mm"] = map_error_mm(cell, r.T_base_cam)
    out["before_mm"] = map_error_mm(cell, cell.T_cal)
    cell.fault(Fault())
    return out


def map_error_mm(cell: Cell, T_base_cam_used: np.ndarray) -> float:
    """Max over a grid of the pick area (table plane) of |mapped - true|, mm: the true camera sees each point
    at a pixel; the cell maps that pixel through ``T_base_cam_used``."""
    xs, ys = np.linspace(0.30, 0.60, 7), np.linspace(-0.12, 0.12, 5)
    P = np.array([[x, y, 0.0] for x in xs for y in ys])
    uv = cell.camera.project(g.transform_points(g.invert(cell.world.T_base_cam()), P))
    mapped = map_to_planes(cell.camera, T_base_cam_used, uv, P[:, 2])
    return float(np.max(np.linalg.norm((mapped - P)[:, :2], axis=1)) * 1e3)


def ramp(cell: Cell, step: Fault) -> dict[str, Any]:
    chart, mean = baseline(cell)
    s, r = np.array(step.shift_mm), np.array(step.rot_deg)
    out: dict[str, Any] = {"chart": None, "rule": None, **{f"fixed {t:g}": None for t in THRESHOLDS_MM}}
    for k in range(1, 80):
        cell.fault(Fault(tuple(s * k), tuple(r * k)))  # type: ignore[arg-type]
        v = cell.check()
        state, rule = chart.add(v)
        if state == "alarm" and out["chart"] is None:
            out["chart"], out["rule"], out["drift_at_alarm_mm"] = k, rule, v - mean
        for t in THRESHOLDS_MM:
            if v - mean > t and out[f"fixed {t:g}"] is None:
                out[f"fixed {t:g}"] = k
        if out["chart"] is not None and all(out[f"fixed {t:g}"] is not None for t in THRESHOLDS_MM):
            break
    cell.fault(Fault())
    return out


def still(cell: Cell, n: int) -> dict[str, Any]:
    chart, mean = baseline(cell)
    values, alarms, fixed = [], 0, dict.fromkeys(THRESHOLDS_MM, 0)
    t0 = time.perf_counter()
    for _ in range(n):
        v = cell.check()
        values.append(v)
        alarms += chart.add(v)[0] == "alarm"
        for t in THRESHOLDS_MM:
            fixed[t] += v - mean > t
    per_check_ms = (time.perf_counter() - t0) / n * 1e3
    lim = chart.lim
    assert lim is not None
    return {"n": n, "alarms": alarms, "fixed": fixed, "mean_mm": float(np.mean(values)),
            "sd_mm": float(np.std(values)), "sigma_measured_mm": lim.sigma_measured, "ucl_mm": lim.ucl,
            "per_check_ms": per_check_ms}


def check_cost_ms(cell: Cell, n: int = 30) -> float:
    """The check itself on one frame (marks found, measured, charted), ms median; the frame is the run's."""
    img = cell.world.render()
    chart = Chart(BASELINE, MIN_SIGMA_MM)
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        uv = find_marks(img, cell.pred, 40.0, 5.6)
        chart.add(measure(cell.camera, cell.T_cal, uv, cell.X).drift_mm)
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def cycle_times(parts: int, repeats: int = 2) -> dict[str, dict[str, Any]]:
    """The median cycle time of in-process production runs without checks and with one every 10 pictures,
    alternated ``repeats`` times (B A B A: a load that changes meanwhile hits both)."""
    import yaml

    from cellctl.drift.monitor import DriftMonitor
    from tests.support.app import in_process_cell
    from tests.support.production_cell import production_config, teach_recipe, wait_ended

    hook = DriftMonitor.on_production_picture
    spent: list[float] = []

    def timed(self: DriftMonitor, *args: Any) -> None:  # the only drift code on the cycle's own thread
        t0 = time.perf_counter()
        try:
            hook(self, *args)
        finally:
            spent.append(time.perf_counter() - t0)

    DriftMonitor.on_production_picture = timed  # type: ignore[method-assign,assignment]
    out: dict[str, dict[str, Any]] = {}
    for label, every in (("no checks", 0), ("checks every 10 cycles", 10)) * repeats:
        spent.clear()
        with tempfile.TemporaryDirectory() as tmp_s:
            tmp = Path(tmp_s)
            path = production_config(tmp, count=parts, time_scale=0.2)
            cfg = yaml.safe_load(path.read_text())
            cfg["drift"].update({"every_s": 0, "every_cycles": every, "baseline_checks": 2})
            path.write_text(yaml.safe_dump(cfg))
            with in_process_cell(tmp, path) as app:
                http = app.http()
                teach_recipe(http, search_roi=True)
                r = http.post("/production/start", json={"recipe_id": 1, "count": 0})
                assert r.status_code == 202, r.text
                end = wait_ended(http, 600.0)
                checks = [c for c in http.get("/drift").json()["records"] if c.get("source") == "production"]
                row = out.setdefault(label, {"placed": [], "median_ms": [], "vision_ms": [], "checks": [],
                                             "hook_ms": []})
                row["hook_ms"].append(1e3 * sum(spent) / max(len(spent), 1))
                row["placed"].append(end["counters"]["placed"])
                row["median_ms"].append(end["cycle_ms"]["median"])
                row["vision_ms"].append(end["cycle_ms"]["vision_median"])
                row["checks"].append(len(checks))
                print(label, row, flush=True)
    DriftMonitor.on_production_picture = hook  # type: ignore[method-assign]
    return out


def fmt(v: Any) -> str:
    return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--still", type=int, default=500)
    ap.add_argument("--cycles", type=int, default=20, help="parts of the cycle-time runs (0: skip them)")
    ap.add_argument("--cycles-only", action="store_true", help="only the cycle-time runs (printed, not written)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "drift.md")
    args = ap.parse_args(argv)
    if args.cycles_only:
        print(cycle_times(args.cycles))
        return 0
    cell = Cell()
    t0 = time.time()
    lines = ["# Drift detection on the virtual production cell", "",
             f"`.venv/bin/python bench/drift.py --still {args.still} --cycles {args.cycles}`; "
             f"{time.strftime('%Y-%m-%d')}, {cpu_model()}.", "",
             "Each check: the production scene rendered (sensor noise 1 DN, blur 0.5 px), six 4 mm marks found, "
             f"`drift_mm` judged on the I-MR chart ({BASELINE} baseline checks, `min_sigma_mm` {MIN_SIGMA_MM}). "
             "Delay = checks after the bump until the alarm (1: the first); `-`: none within "
             f"{MAX_CHECKS}. Peer: a fixed threshold on `drift_mm` above the baseline's mean.", "",
             "## Detection delay against the bump", "",
             "| bump | drift_mm seen | chart: checks to alarm | rule | fixed 0.1 mm | fixed 0.5 mm "
             "| map error before re-solve, mm | after re-solve, mm |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for label, f in BUMPS:
        d = delay(cell, f)
        lines.append(f"| {label} | {d['drift_mm']:.3f} | {fmt(d['chart'])} | {fmt(d['rule'])} | {fmt(d['fixed 0.1'])} "
                     f"| {fmt(d['fixed 0.5'])} | {d['before_mm']:.3f} | {d['resolve_mm']:.3f} |")
        print(lines[-1], flush=True)
    lines += ["", "## A slow drift (ramp)", "",
              "| ramp | chart: checks to alarm | rule | drift at the alarm, mm | fixed 0.1 mm | fixed 0.5 mm |",
              "| --- | --- | --- | --- | --- | --- |"]
    for label, f in RAMPS:
        d = ramp(cell, f)
        lines.append(f"| {label} | {fmt(d['chart'])} | {fmt(d['rule'])} | {fmt(d.get('drift_at_alarm_mm'))} "
                     f"| {fmt(d['fixed 0.1'])} | {fmt(d['fixed 0.5'])} |")
        print(lines[-1], flush=True)
    s = still(cell, args.still)
    lines += ["", "## A still cell", "",
              f"{s['n']} checks after the baseline, a fresh frame each: **{s['alarms']} chart alarms**; fixed "
              f"0.1 mm: {s['fixed'][0.1]}, fixed 0.5 mm: {s['fixed'][0.5]}. drift_mm mean {s['mean_mm']:.4f} mm, "
              f"sd {s['sd_mm']:.4f} mm; the chart's measured sigma {s['sigma_measured_mm']:.4f} mm (floored to "
              f"{MIN_SIGMA_MM}), UCL {s['ucl_mm']:.4f} mm. A check with its render took {s['per_check_ms']:.0f} ms."]
    print(lines[-1], flush=True)
    cost = check_cost_ms(cell)
    lines += ["", "## What a check costs a production cycle", "",
              f"The check on a frame the run took (marks found, measured, charted): {cost:.1f} ms median, on the "
              "run's store thread, not the cycle's; the cycle's own thread only counts the picture and queues it."]
    if args.cycles > 0:
        ct = cycle_times(args.cycles)
        lines += ["", "Production runs in process (motion at 0.2 x real time), alternated without / with checks, "
                  "twice; each run's median cycle, and the time the cycle's own thread spent in the drift hook "
                  "(counting the picture; every 10th: queueing its check), per picture:", "",
                  "| run | placed | drift checks | median cycle, ms | vision median, ms | hook per picture, ms |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for label, v in ct.items():
            lines.append(f"| {label} | {', '.join(str(p) for p in v['placed'])} "
                         f"| {', '.join(str(c) for c in v['checks'])} "
                         f"| {', '.join(f'{m:.0f}' for m in v['median_ms'])} "
                         f"| {', '.join(f'{m:.0f}' for m in v['vision_ms'])} "
                         f"| {', '.join(f'{m:.3f}' for m in v['hook_ms'])} |")
        a, b = (float(np.mean(ct[k]["median_ms"])) for k in ("checks every 10 cycles", "no checks"))
        spread = max(float(np.ptp(ct[k]["median_ms"])) for k in ct)
        lines.append(f"\nWith checks the mean of the runs' median cycles is {100 * (a - b) / b:+.2f} % of the one "
                     f"without; the same setting's runs differ by up to {100 * spread / b:.1f} % between them (the "
                     "search's time on a shared 2-core machine dominates the scatter). The bound that does not "
                     f"depend on the load: a check every 10 cycles costs {cost:.1f} ms / 10 = {cost / 10:.2f} ms of "
                     f"CPU per cycle, {100 * cost / 10 / b:.3f} % of the {b:.0f} ms cycle, and none of it on the "
                     "cycle's own thread.")
        print("\n".join(lines[-5:]), flush=True)
    lines += ["", f"Bench wall time {time.time() - t0:.0f} s."]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
