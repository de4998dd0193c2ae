"""Large images: a 12-megapixel scene (4096 x 3000) with a large part, against OpenCV's NCC peer.

The part is the bench's bracket drawn 4.7x as large (ROI 870 x 588 px; issue 37's tray was 848 x 446),
taught from a 4096 x 3000 teach scene; each test scene holds 2 instances at random turns with clutter,
uneven light and noise (``tests.support.pick_scenes``). Times are in-process per image: wall
(``FindResult.elapsed_s``) and this process's CPU time; errors against the rendered truth.

What the pyramid does with a large part: ``teach`` gives it 5 levels (``auto_levels``: the top level
shows the ROI's smaller side at >= 8 px, at most 5), so the exhaustive search runs on the 256 x 188
top level with a 54 x 37 px model, tracking climbs down with +-1 steps, and the least-squares fits
run on crops around each candidate only; the taught patch is fitted on the level where its samples
lie about a pixel apart (``TeachPatch.fit_level``: level 3 here), not on 12 MP.

The peer (``bench.ncc_baseline.Baseline``): ``cv2.matchTemplate`` over rotated templates, 4-deg steps
at 1/4 scale, then 0.25-deg steps at full scale around each candidate.

Run: ``.venv/bin/python bench/pick_large.py [--scenes 3] [--no-baseline]``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_model  # noqa: E402
from bench.ncc_baseline import Baseline  # noqa: E402
from tests.support import pick_scenes  # noqa: E402
from vision import shape  # noqa: E402

SIZE = (4096, 3000)
PART_SCALE = 4.7


def run(n_scenes: int, with_baseline: bool) -> str:
    load0 = os.getloadavg()
    part = pick_scenes.part_bracket(PART_SCALE)
    teach, roi = pick_scenes.teach_scene(part, np.random.default_rng(1), centre=(2048.3, 1500.6),
                                         style=pick_scenes.SceneStyle(size=SIZE, noise_sigma=1.5, clutter=0))
    model = shape.teach(teach, roi)
    rng = np.random.default_rng(5)
    scenes = [pick_scenes.random_scene(rng, [part], n_min=2, n_max=2, size=SIZE, clutter=40)
              for _ in range(n_scenes)]
    shape.find(model, scenes[0][0])  # first touches of 12 MP buffers
    ms, cpu, errs, ang = [], [], [], []
    found = total = 0
    for img, truth in scenes:
        c0 = time.process_time()
        res = shape.find(model, img)
        cpu.append((time.process_time() - c0) * 1e3)
        ms.append(res.elapsed_s * 1e3)
        for t in truth:
            total += 1
            near = [m for m in res.matches if math.hypot(m.u_px - t.u_px, m.v_px - t.v_px) < 5]
            if near:
                found += 1
                errs.append(math.hypot(near[0].u_px - t.u_px, near[0].v_px - t.v_px))
                ang.append(abs((near[0].angle_deg - t.angle_deg + 180) % 360 - 180))
    b_ms: list[float] = []
    b_cpu: list[float] = []
    if with_baseline:
        base = Baseline.build(teach, roi)
        for img, _ in scenes:
            t0, c0 = time.perf_counter(), time.process_time()
            base.find(img, 0.5)
            b_ms.append((time.perf_counter() - t0) * 1e3)
            b_cpu.append((time.process_time() - c0) * 1e3)
    load1 = os.getloadavg()
    med = statistics.median
    lines = [
        "# Large images (issue 37): 12 MP, a large part",
        "",
        f"`.venv/bin/python bench/pick_large.py --scenes {n_scenes}` — {SIZE[0]}x{SIZE[1]} scenes, ROI "
        f"{roi[2]:.0f}x{roi[3]:.0f} px, {model.top_level + 1} pyramid levels (top level model "
        f"{len(model.levels[-1].points)} points), patch fitted on level "
        f"{model.patch.fit_level() if model.patch else '-'}. Machine: {cpu_model()}, {os.cpu_count()} cores "
        f"shared with other jobs; load average {load0[0]:.1f} at start, {load1[0]:.1f} at end.",
        "",
        "| matcher | found | position max px | angle max deg | median ms | median CPU ms |",
        "| --- | --- | --- | --- | --- | --- |",
        f"| cellctl | {found} of {total} | {max(errs, default=math.nan):.3f} | {max(ang, default=math.nan):.3f} | "
        f"{med(ms):.0f} | {med(cpu):.0f} |",
    ]
    if with_baseline:
        lines.append(f"| OpenCV NCC peer | - | - | - | {med(b_ms):.0f} | {med(b_cpu):.0f} |")
        lines += ["", f"Ratio peer / cellctl: {med(b_ms) / med(ms):.1f}x wall, {med(b_cpu) / med(cpu):.1f}x CPU."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    text = run(args.scenes, not args.no_baseline)
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
