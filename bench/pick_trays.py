"""Full trays (issue 14): many identical parts in one image, cellctl's shape matcher vs OpenCV NCC.

A tray, a PCB with a row of identical parts, a blister: every part alike, so each one's cluster of
top-level maxima competes with the others for the search's candidate list. Rendered 1280x960
trays (``tests.support.pick_scenes.tray_scene``) of 30 brackets in 6 x 5 cells, each turned at random, with
clutter, noise 2 grey levels and optical blur 0.7 px; the same trays at 1/2 and 1/4 size (small
parts: a model of 2 or 1 pyramid levels). Both matchers search every image with the part taught
once at that size, at their defaults; a match counts within 2 px (at that size) and 1 deg.

Baseline: ``bench/ncc_baseline.py`` (``cv2.matchTemplate`` over rotated templates, as in
``bench/pick.py``).

Run: ``.venv/bin/python bench/pick_trays.py [--trays 4] [--out bench/results/pick_trays.md]``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_model  # noqa: E402
from bench.ncc_baseline import Baseline, Found  # noqa: E402
from tests.support import pick_scenes  # noqa: E402
from vision import shape  # noqa: E402

SIZE = (1280, 960)
SCALES = (1, 2, 4)
MATCH_DEG = 1.0


@dataclass
class Tally:
    n_truth: int = 0
    found: int = 0
    false: int = 0
    pos_err: list[float] = field(default_factory=list)
    wall_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)

    def add(self, truth: list[tuple[float, float, float]], got: list[Found], tol_px: float) -> None:
        used: set[int] = set()
        for u, v, a in truth:
            self.n_truth += 1
            best, bd = -1, tol_px
            for k, f in enumerate(got):
                d = math.hypot(f.u_px - u, f.v_px - v)
                if k not in used and d < bd and abs(pick_scenes.wrap_deg(f.angle_deg - a)) < MATCH_DEG:
                    best, bd = k, d
            if best >= 0:
                used.add(best)
                self.found += 1
                self.pos_err.append(bd)
        self.false += len(got) - len(used)


def _shrink(img: NDArray[np.uint8], k: int) -> NDArray[np.uint8]:
    return img if k == 1 else cv2.resize(img, None, fx=1 / k, fy=1 / k, interpolation=cv2.INTER_AREA)


def run(n_trays: int, with_baseline: bool) -> str:
    load0 = os.getloadavg()
    part = pick_scenes.part_bracket()
    teach_img, (u, v, w, h) = pick_scenes.teach_scene(
        part, np.random.default_rng(1008), centre=(640.3, 480.6),
        style=pick_scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=0))
    trays = [pick_scenes.tray_scene(part, np.random.default_rng(100 + i)) for i in range(n_trays)]
    ours: dict[int, Tally] = {}
    theirs: dict[int, Tally] = {}
    for k in SCALES:
        roi = pick_scenes.roi_at_scale((u, v, w, h), k)
        small_teach = _shrink(teach_img, k)
        model = shape.teach(small_teach, roi)
        base = Baseline.build(small_teach, roi) if with_baseline else None
        ours[k], theirs[k] = Tally(), Tally()
        shape.find(model, _shrink(trays[0][0], k))  # warm-up
        for img, truth in trays:
            small = _shrink(img, k)
            # pixel-centre convention: the centre of the top-left pixel is (0, 0) at every size
            t_k = [((t.u_px + 0.5) / k - 0.5, (t.v_px + 0.5) / k - 0.5, t.angle_deg) for t in truth]
            t0, c0 = time.perf_counter(), time.process_time()
            res = shape.find(model, small)
            ours[k].wall_s.append(time.perf_counter() - t0)
            ours[k].cpu_s.append(time.process_time() - c0)
            ours[k].add(t_k, [Found(m.u_px, m.v_px, m.angle_deg, m.score) for m in res.matches], 2.0)
            if base is not None:
                t0, c0 = time.perf_counter(), time.process_time()
                fb = base.find(small)
                theirs[k].wall_s.append(time.perf_counter() - t0)
                theirs[k].cpu_s.append(time.process_time() - c0)
                theirs[k].add(t_k, fb, 2.0)
        print(f"  1/{k} done", file=sys.stderr, flush=True)
    return _report(n_trays, ours, theirs if with_baseline else None, load0, os.getloadavg())


def _row(k: int, who: str, t: Tally) -> str:
    rms = math.sqrt(sum(e * e for e in t.pos_err) / len(t.pos_err)) if t.pos_err else float("nan")
    return (f"| 1/{k} ({SIZE[0] // k}x{SIZE[1] // k}) | {who} | {t.n_truth} | {t.found} | {t.false} | "
            f"{100.0 * t.found / max(t.n_truth, 1):.1f} | {rms:.3f} | {1e3 * statistics.median(t.wall_s):.0f} | "
            f"{1e3 * statistics.median(t.cpu_s):.0f} |")


def _report(n_trays: int, ours: dict[int, Tally], theirs: dict[int, Tally] | None,
            load0: tuple[float, float, float], load1: tuple[float, float, float]) -> str:
    lines = [
        "# Full trays (issue 14): 30 identical parts per image, cellctl vs OpenCV NCC",
        "",
        f"`.venv/bin/python bench/pick_trays.py --trays {n_trays}` — {n_trays} rendered trays of 30 "
        "brackets (6 x 5 cells, each turned at random; clutter, noise 2, blur 0.7 px), searched at full, "
        "half and quarter size with the part taught at that size. A match counts within 2 px (at that "
        "size) and 1 deg of the truth; position RMS over the found ones.",
        "",
        f"Machine: {cpu_model()}, {os.cpu_count()} cores shared with other jobs; load average at start "
        f"{load0[0]:.2f}, at end {load1[0]:.2f}. Times in-process per image (wall, and this process's CPU).",
        "",
        "| size | matcher | parts | found | false | found % | position RMS px | median ms | median CPU ms |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for k in SCALES:
        lines.append(_row(k, "cellctl", ours[k]))
        if theirs is not None:
            lines.append(_row(k, "OpenCV NCC", theirs[k]))
    missed = {k: t.n_truth - t.found for k, t in ours.items()}
    lines += [
        "",
        "Target (issue 14: every instance found, 0 false): "
        + ("met at every size." if not any(missed.values()) and not any(t.false for t in ours.values())
           else "**missed**: " + ", ".join(f"1/{k}: {m} missed, {ours[k].false} false"
                                           for k, m in missed.items() if m or ours[k].false) + "."),
        "",
        "Notes. Each part is a cluster of the top level's maxima (neighbouring positions and angles); "
        "the search keeps its 64 best candidates wherever they lie and adds the best of every other "
        "position scoring at least 0.7 of the best part (`vision.shape.top_search.TOP_BEST`, "
        "`TOP_EXTRA_OF_BEST`). With the 64 alone (the code before this table) the full-size trays "
        "were 12-16 of 30 found. A model of 1-2 levels has no level to track on, and its candidates "
        "are settled on unspread responses before the least-squares stage (without it 105 of 120 were "
        "found at 1/4 when it was measured). The time grows with the number of parts: the least-squares "
        "refinement is per part, and so is the verification (`vision/shape/verify.py`), whose check "
        "that a match's edges are not those of better matches only compares neighbours whose contours "
        "can touch. The previous table (before the verification) had the same counts: 120 / 120 / 119, "
        "0 false.",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trays", type=int, default=4, help="trays (each searched at three sizes)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the (slow) OpenCV baseline")
    ap.add_argument("--out", default=None, help="also write the markdown here")
    args = ap.parse_args()
    text = run(args.trays, not args.no_baseline)
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
