"""Pick-guidance benchmark (issue 8): cellctl's shape matcher against a plain OpenCV baseline.

Rendered 1280x960 scenes with known part poses (``tests.support.pick_scenes``): a taught bracket, 1-5
instances of it, 0-2 distractor parts of another type, clutter, uneven light, noise, and four
sets — top-down, slightly tilted camera (perspective), 0-30 % occlusion, and exactly 30 %
occlusion. Every image is searched by both matchers with the same model ROI.

Baseline (``bench/ncc_baseline.py``): ``cv2.matchTemplate`` (TM_CCOEFF_NORMED, absolute value so
contrast reversal is allowed) over templates rotated about the sub-pixel ROI centre —
4° steps at 1/4 scale, then 0.25° steps at full scale around each candidate, with parabolic
sub-pixel peaks in angle and position.

Run: ``.venv/bin/python bench/pick.py [--n 120] [--seed 8] [--out bench/results/pick.md]``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.first_search import first_ratio, measure  # noqa: E402
from bench.machine import cpu_model  # noqa: E402
from bench.ncc_baseline import Baseline, Found  # noqa: E402
from tests.support import pick_scenes  # noqa: E402
from vision import shape  # noqa: E402
from vision.types import Match  # noqa: E402

SIZE = (1280, 960)
MATCH_PX = 3.0
MATCH_DEG = 5.0


# ----------------------------------------------------------------------------- scenes


@dataclass
class Scene:
    name: str
    img: NDArray[np.uint8]
    truth: list[pick_scenes.Truth]


SETS = (("top-down", 0.0, 0.0, 0.0), ("tilted <= 5 deg", 5.0, 0.0, 0.0),
        ("occluded 0-30 %", 0.0, 0.0, 0.3), ("occluded 30 %", 0.0, 0.3, 0.3))


def make_scenes(n: int, seed: int) -> list[tuple[str, Scene]]:
    rng = np.random.default_rng(seed)
    target = pick_scenes.part_bracket()
    distractor = pick_scenes.part_tee()
    out = []
    per = max(n // len(SETS), 1)
    for set_name, tilt, occ_lo, occ_hi in SETS:
        for i in range(per):
            img, truth = _scene(rng, target, distractor, tilt, occ_lo, occ_hi)
            out.append((set_name, Scene(f"{set_name}#{i}", img, truth)))
    return out


def _scene(rng: np.random.Generator, target: pick_scenes.PartShape, distractor: pick_scenes.PartShape, tilt: float,
           occ_lo: float, occ_hi: float) -> tuple[NDArray[np.uint8], list[pick_scenes.Truth]]:
    n_t = int(rng.integers(1, 6))
    n_d = int(rng.integers(0, 3))
    w, h = SIZE
    placed: list[pick_scenes.Instance] = []
    tries = 0
    kinds = [target] * n_t + [distractor] * n_d
    while kinds and tries < 1000:
        tries += 1
        part = kinds[0]
        r = part.extent_px() + 4
        u, v = rng.uniform(r, w - r), rng.uniform(r, h - r)
        if any(math.hypot(u - p.u_px, v - p.v_px) < r + p.part.extent_px() + 4 for p in placed):
            continue
        occ = float(rng.uniform(occ_lo, occ_hi)) if occ_hi > 0 and part is target else 0.0
        placed.append(pick_scenes.Instance(part, float(u), float(v), float(rng.uniform(-180, 180)), occ))
        kinds.pop(0)
    H = None
    if tilt > 0:
        H = pick_scenes.tilt_homography(SIZE, float(rng.uniform(0.5, 1.0)) * tilt, float(rng.uniform(0, 360)))
    bright = rng.uniform() < 0.75
    style = pick_scenes.SceneStyle(
        background=float(rng.uniform(60, 110)) if bright else float(rng.uniform(160, 200)),
        part_value=float(rng.uniform(170, 220)) if bright else float(rng.uniform(40, 90)),
        blur_sigma_px=float(rng.uniform(0.5, 0.9)), noise_sigma=float(rng.uniform(1.0, 3.0)),
        light_gradient=float(rng.uniform(0.0, 0.5)), vignetting=float(rng.uniform(0.0, 0.3)),
        light_dir_deg=float(rng.uniform(0, 360)), clutter=int(rng.integers(10, 40)), size=SIZE, homography=H)
    img, truth = pick_scenes.render(placed, style, rng)
    return img, [t for t in truth if t.part == target.name]


# ----------------------------------------------------------------------------- scoring


def _nearest(t: pick_scenes.Truth, found: Sequence[Found | Match], used: set[int]) -> tuple[int, float]:
    """The index of the nearest answer not yet used within ``MATCH_PX`` and ``MATCH_DEG`` of the truth ``t``
    (-1 when none) and its distance, px."""
    best, bd = -1, MATCH_PX
    for k, f in enumerate(found):
        d = math.hypot(f.u_px - t.u_px, f.v_px - t.v_px)
        if k not in used and d < bd and abs(pick_scenes.wrap_deg(f.angle_deg - t.angle_deg)) < MATCH_DEG:
            best, bd = k, d
    return best, bd


@dataclass
class Tally:
    pos_err: list[float] = field(default_factory=list)
    ang_err: list[float] = field(default_factory=list)
    n_truth: int = 0
    missed: int = 0
    false: int = 0
    wall_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    stages: list[tuple[float, float, float]] = field(default_factory=list)
    pos_ratio: list[float] = field(default_factory=list)
    """Per found instance: position error / the match's reported 1-sigma (cellctl only)."""
    ang_ratio: list[float] = field(default_factory=list)

    def add_sigma(self, truth: list[pick_scenes.Truth], matches: list[Match]) -> None:
        """Actual / reported 1-sigma of each instance found (matched as ``add`` matches)."""
        used: set[int] = set()
        for t in truth:
            best, bd = _nearest(t, matches, used)
            if best < 0:
                continue
            used.add(best)
            m = matches[best]
            if m.sigma_px > 0 and m.sigma_angle_deg > 0:
                self.pos_ratio.append(bd / m.sigma_px)
                self.ang_ratio.append(abs(pick_scenes.wrap_deg(m.angle_deg - t.angle_deg)) / m.sigma_angle_deg)

    def add(self, truth: list[pick_scenes.Truth], found: list[Found]) -> None:
        used: set[int] = set()
        for t in truth:
            self.n_truth += 1
            best, _ = _nearest(t, found, used)
            if best < 0:
                self.missed += 1
                continue
            used.add(best)
            f = found[best]
            self.pos_err.append(math.hypot(f.u_px - t.u_px, f.v_px - t.v_px))
            self.ang_err.append(pick_scenes.wrap_deg(f.angle_deg - t.angle_deg))
        self.false += len(found) - len(used)

    def rms(self, xs: list[float]) -> float:
        return math.sqrt(sum(x * x for x in xs) / len(xs)) if xs else float("nan")


def _pct(xs: list[float], q: float) -> float:
    return float(np.percentile(np.array(xs), q)) if xs else float("nan")


def run(n: int, seed: int, with_baseline: bool, first_processes: int = 3) -> str:
    load0 = os.getloadavg()
    part = pick_scenes.part_bracket()
    teach_img, roi = pick_scenes.teach_scene(part, np.random.default_rng(seed + 1000), centre=(640.3, 480.6),
                                       style=pick_scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=0))
    model = shape.teach(teach_img, roi)
    base = Baseline.build(teach_img, roi) if with_baseline else None
    scenes = make_scenes(n, seed)
    ours: dict[str, Tally] = {name: Tally() for name, *_ in SETS}
    theirs: dict[str, Tally] = {name: Tally() for name, *_ in SETS}
    shape.find(model, scenes[0][1].img)  # warm-up (imports, caches)
    # each matcher over all images in turn (same images, same run): the baseline's multi-threaded
    # OpenCV calls interleaved with ours would stretch our wall clock (and its caches)
    for k, (set_name, sc) in enumerate(scenes):
        t0, c0 = time.perf_counter(), time.process_time()
        res = shape.find(model, sc.img)
        t1, c1 = time.perf_counter(), time.process_time()
        ours[set_name].wall_s.append(t1 - t0)
        ours[set_name].cpu_s.append(c1 - c0)
        ours[set_name].add(sc.truth, [Found(m.u_px, m.v_px, m.angle_deg, m.score) for m in res.matches])
        ours[set_name].add_sigma(sc.truth, res.matches)
        st = res.stats
        ours[set_name].stages.append((st["cpu_top_s"], st["cpu_track_s"] - st["cpu_top_s"],
                                      st["cpu_total_s"] - st["cpu_track_s"]))
        if (k + 1) % 20 == 0:
            print(f"  cellctl {k + 1}/{len(scenes)} images", file=sys.stderr, flush=True)
    load_mid = os.getloadavg()
    for k, (set_name, sc) in enumerate(scenes if base is not None else []):
        t0, c0 = time.perf_counter(), time.process_time()
        fb = base.find(sc.img) if base is not None else []
        t1, c1 = time.perf_counter(), time.process_time()
        theirs[set_name].wall_s.append(t1 - t0)
        theirs[set_name].cpu_s.append(c1 - c0)
        theirs[set_name].add(sc.truth, fb)
        if (k + 1) % 20 == 0:
            print(f"  baseline {k + 1}/{len(scenes)} images", file=sys.stderr, flush=True)
    look = _look_alikes(model, base, part, seed)
    # issue 22: the first search in a fresh process, after the service's start-up warm-up, against the
    # median of its next 100 (bench/first_search.py's "service" mode; one process per measurement)
    first = [first_ratio(measure("service", None)) for _ in range(first_processes)]
    load1 = os.getloadavg()
    return _report(n, seed, ours, theirs if base is not None else None, load0, load_mid, load1,
                   len(scenes), first) + look


LOOK_ALIKE_SEEDS = 2
CHECKS = (("bunch", "coverage"), ("flips", "polarity"), ("noise", "contrast"), ("missing", "missing"),
          ("one side", "surround"), ("better matches", "unclaimed"), ("score", "score"))
"""Words of a rejection's reason (``vision/shape/verify.py``) and the check they name, the first that
occurs (every reason that names min_score says 'score': that one last)."""


def middle_half(part: pick_scenes.PartShape, angle_deg: float) -> pick_scenes.PartShape:
    """The part's half cut through the middle of its area (the centroid of outline less holes) at
    ``angle_deg``, named ``<part>-middle-half-<angle>``."""
    def moments(p: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        x, y = p[:, 0], p[:, 1]
        xn, yn = np.roll(x, -1), np.roll(y, -1)
        cr = x * yn - xn * y
        return float(cr.sum() / 2), np.array([((x + xn) * cr).sum() / 6, ((y + yn) * cr).sum() / 6])
    area, first = moments(part.outer)
    for h in part.holes:
        a, f = moments(h)
        sign = 1.0 if (a > 0) == (area > 0) else -1.0
        area, first = area - sign * a, first - sign * f
    c = first / area
    moved = pick_scenes.PartShape(part.name, part.outer - c, tuple(h - c for h in part.holes))
    half = pick_scenes.part_half(moved, angle_deg)
    return pick_scenes.PartShape(f"{part.name}-middle-half-{angle_deg:g}", half.outer, half.holes)


def _checks(reasons: list[str]) -> str:
    """How many rejections each check made, e.g. ``missing 8, surround 2``."""
    n: dict[str, int] = {}
    for r in reasons:
        name = next((c for w, c in CHECKS if w in r), "other")
        n[name] = n.get(name, 0) + 1
    return ", ".join(f"{k} {v}" for k, v in sorted(n.items())) or "-"


def _look_alikes(model: shape.ShapeModel, base: Baseline | None, part: pick_scenes.PartShape, seed: int) -> str:
    """Scenes of 4 look-alikes of the part each, where nothing is to be found: a table of the matches
    (all false) of cellctl and the baseline, and the candidates cellctl's verification rejected."""
    kinds = [pick_scenes.mirrored_part(part)]
    kinds += [pick_scenes.part_without_hole(part, k) for k in range(len(part.holes))]
    kinds += [pick_scenes.part_half(part, a) for a in (0.0, 45.0, 90.0, 180.0, 270.0)]
    kinds += [middle_half(part, a) for a in (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0)]
    rows = []
    tot = [0, 0, 0]
    for d in kinds:
        ours = rej = theirs = 0
        best = 0.0
        reasons: list[str] = []
        for k in range(LOOK_ALIKE_SEEDS):
            img = pick_scenes.distractor_scene(d, np.random.default_rng(seed * 1000 + k))
            res = shape.find(model, img)
            ours += len(res.matches)
            rej += len(res.rejected)
            reasons += [r.reason for r in res.rejected]
            best = max([best] + [m.score for m in res.matches])
            theirs += len(base.find(img)) if base is not None else 0
        tot[0] += ours
        tot[1] += rej
        tot[2] += theirs
        rows.append(f"| {d.name} | {4 * LOOK_ALIKE_SEEDS} | {ours} | {best:.2f} | {rej} | {_checks(reasons)} | "
                    + (f"{theirs} |" if base is not None else "- |"))
    return "\n".join([
        "", "## Look-alikes: nothing to find", "",
        f"{LOOK_ALIKE_SEEDS} images of 4 instances per look-alike (`pick_scenes.distractor_scene`: clutter, "
        "uneven light, noise 1-3): the part's mirror image, the part without one of its holes, and its "
        "halves (cut through the reference point, or through the middle of its area, at the angle named). "
        "Every match is false. 'rejected' counts the candidates that reached min_score and failed the "
        "verification (`vision/shape/verify.py`), 'by check' the check that failed them (a half: "
        "`surround`, its seen edges on one side of the part's centre; a half and a part half hidden by "
        "background pasted beyond a straight cut, as the 'occluded' sets render, are the same image, so "
        "it is the share hidden that decides: 30 % hidden keeps surround >= 0.28, the bar is 0.2).", "",
        "| look-alike | instances | cellctl matches | best score | rejected by verification | by check | "
        "baseline matches |",
        "| --- | --- | --- | --- | --- | --- | --- |", *rows,
        f"| **all** | {4 * LOOK_ALIKE_SEEDS * len(kinds)} | {tot[0]} | - | {tot[1]} | - | "
        + (f"{tot[2]} |" if base is not None else "- |"), ""])


PREVIOUS = {"label": "previous table (2026-12-02, before the verification, load 0.6-0.7)", "top": 4.9,
            "track": 3.9, "refine": 6.2, "cpu": 14.9, "wall": 13.7}
"""The last table's numbers (bench/results/pick.md before this work), kept as the reference row."""


def _cpu_text() -> str:
    """The CPU's model name with its family and model numbers (``/proc/cpuinfo``; a VM may hide the name)."""
    fam = mod = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, val = line.partition(":")
            if key.strip() == "cpu family" and not fam:
                fam = val.strip()
            elif key.strip() == "model" and not mod:
                mod = val.strip()
    except OSError:
        pass
    extra = f" (family {fam}, model {mod})" if fam and mod else ""
    return f"{cpu_model()}{extra}"


def _largest_stage(stg: NDArray[np.float64]) -> str:
    names = ("top level", "tracking", "least-squares refinement")
    k = int(np.argmax(stg))
    return f"{names[k]} ({stg[k]:.1f} ms CPU, {100.0 * stg[k] / max(float(stg.sum()), 1e-9):.0f} % of the stages)"


def _row(name: str, who: str, t: Tally) -> str:
    found = 100.0 * (t.n_truth - t.missed) / max(t.n_truth, 1)
    return (f"| {name} | {who} | {t.n_truth} | {t.rms(t.pos_err):.4f} | {t.rms(t.ang_err):.4f} | "
            f"{t.missed} | {t.false} | {found:.1f} | {1e3 * statistics.median(t.wall_s):.1f} | "
            f"{1e3 * _pct(t.wall_s, 99):.1f} | {1e3 * statistics.median(t.cpu_s):.1f} | "
            f"{1e3 * _pct(t.cpu_s, 99):.1f} |")


def _merge(ts: list[Tally]) -> Tally:
    out = Tally()
    for t in ts:
        out.pos_err += t.pos_err
        out.ang_err += t.ang_err
        out.n_truth += t.n_truth
        out.missed += t.missed
        out.false += t.false
        out.wall_s += t.wall_s
        out.cpu_s += t.cpu_s
        out.stages += t.stages
        out.pos_ratio += t.pos_ratio
        out.ang_ratio += t.ang_ratio
    return out


def _report(n: int, seed: int, ours: dict[str, Tally], theirs: dict[str, Tally] | None,
            load0: tuple[float, float, float], load_mid: tuple[float, float, float],
            load1: tuple[float, float, float], n_images: int, first: list[float]) -> str:
    lines = [
        "# Pick benchmark (issues 8, 14): shape-based matching vs OpenCV matchTemplate",
        "",
        f"`{' '.join(['.venv/bin/python', 'bench/pick.py', '--n', str(n), '--seed', str(seed)])}` — "
        f"{n_images} rendered 1280x960 images, the part taught once (bracket ~180x120 px, ROI 204x144 px "
        "centred on a sub-pixel reference point); 1-5 instances + 0-2 distractor parts per image, "
        "clutter, uneven light, noise 1-3 grey levels, optical blur 0.5-0.9 px, 25 % of scenes with "
        "reversed contrast. Errors are against the rendered ground truth (reference point and angle).",
        "",
        f"Machine: {_cpu_text()}, {os.cpu_count()} cores shared with other jobs; load average at start "
        f"{load0[0]:.2f}, after cellctl's images {load_mid[0]:.2f}, at end {load1[0]:.2f}. cellctl searches "
        "every image first, then the baseline (timed apart, so neither's threads stretch the other's "
        "clock). Wall times are in-process per image (`time.perf_counter` "
        "around `shape.find`, what `pick find` reports as `time_ms`); CPU is this process's CPU time "
        "(`time.process_time`: steadier on a busy machine; OpenCV's own threads count in it).",
        "",
        "| set | matcher | instances | position RMS px | angle RMS deg | missed | false | found % "
        "| median ms | p99 ms | median CPU ms | p99 CPU ms |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, *_ in SETS:
        lines.append(_row(name, "cellctl", ours[name]))
        if theirs is not None:
            lines.append(_row(name, "OpenCV baseline", theirs[name]))
    allo = _merge(list(ours.values()))
    lines.append(_row("**all**", "cellctl", allo))
    if theirs is not None:
        allt = _merge(list(theirs.values()))
        lines.append(_row("**all**", "OpenCV baseline", allt))
    lines += ["", "## Against the targets", ""]
    clean = _merge([ours["top-down"]])
    unocc = _merge([ours["top-down"], ours["tilted <= 5 deg"]])
    occ30 = ours["occluded 30 %"]

    def mark(ok: bool) -> str:
        return "met" if ok else "**missed**"

    found30 = 100.0 * (occ30.n_truth - occ30.missed) / max(occ30.n_truth, 1)
    med = 1e3 * statistics.median(allo.wall_s)
    p99 = 1e3 * _pct(allo.wall_s, 99)
    med_cpu = 1e3 * statistics.median(allo.cpu_s)
    p99_cpu = 1e3 * _pct(allo.cpu_s, 99)
    lines += [
        "| target | cellctl | verdict |",
        "| --- | --- | --- |",
        f"| position <= 0.05 px RMS (top-down) | {clean.rms(clean.pos_err):.4f} px | "
        f"{mark(clean.rms(clean.pos_err) <= 0.05)} |",
        f"| angle <= 0.05 deg RMS (top-down) | {clean.rms(clean.ang_err):.4f} deg | "
        f"{mark(clean.rms(clean.ang_err) <= 0.05)} |",
        f"| zero missed / false on the un-occluded sets (top-down + tilted) | {unocc.missed} / "
        f"{unocc.false} | {mark(unocc.missed == 0 and unocc.false == 0)} |",
        f"| >= 95 % found at 30 % occlusion | {found30:.1f} % | {mark(found30 >= 95.0)} |",
        f"| median <= 15 ms per image (issue 14; 20 ms in issue 8) | {med:.1f} ms wall ({med_cpu:.1f} ms CPU) "
        f"| {mark(med <= 15.0)} |",
        f"| p99 <= 50 ms per image | {p99:.1f} ms wall ({p99_cpu:.1f} ms CPU) | {mark(p99 <= 50.0)} |",
    ]
    for name, *_ in SETS:
        t = ours[name]
        pr, ar = t.rms(t.pos_ratio), t.rms(t.ang_ratio)
        lines.append(f"| 1-sigma honest, {name}: actual / reported RMS within 0.5-2 (issue 37; the renderer's own "
                     f"sub-pixel bias, ~0.01 px, is in the error) | position {pr:.2f}, angle {ar:.2f} | "
                     f"{mark(0.5 <= pr <= 2.0 and 0.5 <= ar <= 2.0)} |")
    if first:
        lines.append(
            "| first search in a fresh process, after the service's start-up warm-up, <= 1.5x the median of its "
            f"next 100 (issue 22; `bench/first_search.py`) | {statistics.median(first):.2f}x (median of "
            f"{len(first)} processes, max {max(first):.2f}x) | {mark(statistics.median(first) <= 1.5)} |")
    stg = np.median(np.array(allo.stages), axis=0) * 1e3 if allo.stages else np.zeros(3)
    lines += [
        "",
        "## Where cellctl's time goes (median CPU ms per image, all sets)",
        "",
        "| run | pyramid + top level: response maps, exhaustive search | tracking down the pyramid "
        "| least-squares refinement (levels 1 and 0) | total (median) |",
        "| --- | --- | --- | --- | --- |",
        f"| {PREVIOUS['label']} | {PREVIOUS['top']:.1f} | {PREVIOUS['track']:.1f} | {PREVIOUS['refine']:.1f} "
        f"| {PREVIOUS['cpu']:.1f} CPU / {PREVIOUS['wall']:.1f} wall |",
        f"| this run (load {min(load0[0], load_mid[0]):.1f}-{max(load0[0], load_mid[0]):.1f}) "
        f"| {stg[0]:.1f} | {stg[1]:.1f} | {stg[2]:.1f} "
        f"| {med_cpu:.1f} CPU / {med:.1f} wall |",
        "",
        "Notes. The matcher is `vision.shape` at its default settings (polarity "
        "`ignore_local_polarity`, no scale range, no mirror). Its inner loops are compiled (numba): "
        "the top level's score planes on LINE-MOD's linearised memories and their local maxima over "
        "position and angle, the neighbourhood tracking down the pyramid "
        "(`vision/shape/search_kernels.py`), and the refinement's edge association, Gauss-Newton "
        "loops, profile centroids and plane-homography fit (`vision/shape/kernels.py`, `fit_kernels.py`); the "
        "pyramid, gradients, orientation quantisation and max filters are OpenCV calls. "
        + (f"Wall time is {med / max(med_cpu, 1e-9):.1f}x the CPU time in this run: the other jobs on "
           "the 2 cores (see the load average) stretch the wall clock, so the CPU column is the "
           "steadier figure of the matcher's own cost. " if med > 1.15 * med_cpu else
           f"Wall time is {med / max(med_cpu, 1e-9):.2f}x the CPU time in this run: the other jobs on the "
           "2 cores left this process a core (at a load of 7-12 on this shared machine the wall clock has "
           "been 2.5-3x the CPU time, so the CPU column is the steadier figure of the matcher's own cost). ")
        + "Narrowing the search (an angle range, a search "
        "ROI) cuts the time in proportion; max_count only trims the answer. The baseline's false "
        "detections are other parts and clutter reaching |NCC| >= 0.5 at some rotation (the same "
        "minimum score as cellctl's); its misses grow with occlusion. The compiled loops return what "
        "their numpy versions return (tests/vision/test_shape_search_kernels.py): accuracy, misses and "
        "false matches are those of the matcher's score and model (`vision/shape/score.py`, `teaching.py`); "
        "the search changes of 2026-12-02 (the first tracking level climbs on from a window's edge, a "
        "candidate list that keeps room for every position, near ties of turned hypotheses) found 3 more "
        "instances at 30 % occlusion on this set (seed 8) and left the poses of the ones found before "
        "as they were (the top-down and tilted rows unchanged to 4 decimals). Every match then passes the "
        "verification (`vision/shape/verify.py`: coverage of the model's features, contrast polarity along "
        "its chains, contrast over the noise, no feature missing where nothing hides it, edges not "
        "claimed by a better match), timed in the refinement column; on this set it rejects no instance "
        "(the found counts are those before it), and the look-alikes below are where it matters.",
    ]
    if med > 15.0:
        lines += [
            "",
            "## Speed target: missed, with the numbers",
            "",
            f"In-process median {med:.1f} ms wall / {med_cpu:.1f} ms CPU per image against the 15 ms target "
            f"(previous run: {PREVIOUS['wall']:.1f} ms wall / {PREVIOUS['cpu']:.1f} ms CPU). "
            + ("The CPU median is within the target: the wall clock misses it because this process got "
               f"about {100.0 * med_cpu / max(med, 1e-9):.0f} % of a core while the load average was "
               f"{load0[0]:.1f}-{load_mid[0]:.1f} on 2 cores (other sessions' jobs)."
               if med_cpu <= 15.0 else
               "The matcher's own cost (CPU) is above the target too: the largest stage is the "
               f"{_largest_stage(stg)}; per stage see the table above."),
        ]
    if theirs is not None:
        allt = _merge(list(theirs.values()))
        ratio = statistics.median(allt.wall_s) / statistics.median(allo.wall_s)
        ratio_cpu = statistics.median(allt.cpu_s) / statistics.median(allo.cpu_s)
        lines += ["", f"Speed ratio (median wall time, baseline / cellctl): {ratio:.1f}x "
                  f"({ratio_cpu:.1f}x in CPU time). "
                  f"Position RMS ratio (baseline / cellctl, all found): "
                  f"{allt.rms(allt.pos_err) / allo.rms(allo.pos_err):.1f}x; angle: "
                  f"{allt.rms(allt.ang_err) / allo.rms(allo.ang_err):.1f}x."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=120, help="images (split over the four sets)")
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--no-baseline", action="store_true", help="skip the (slow) OpenCV baseline")
    ap.add_argument("--first-processes", type=int, default=3,
                    help="fresh processes timing a first search against the next 100 (0: skip)")
    ap.add_argument("--out", default=None, help="also write the markdown here")
    args = ap.parse_args()
    text = run(args.n, args.seed, not args.no_baseline, args.first_processes)
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
