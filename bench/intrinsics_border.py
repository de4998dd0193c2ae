"""What an uncovered image border costs a camera calibration, on held-out renders (issue 36 item 7).

Each seeded set plans a pool of chessboard views through the real-defects scene's lens
(``bench/intrinsics_heldout.py``'s lens and imaging: opencv5 with its distortion, 640x480) and sorts
them by the verdict's own rule (``calibration.verdict.border_coverage``): *border* views put corner
points in an image side's border strip (the outer 10%), *inner* views do not. Two training sets of
the same size share ``--inner`` inner views and add ``--extra`` more views each:

- **without**: ``--extra`` more inner views (the ring stays empty; the verdict says ``border_not_covered``);
- **with**: ``--extra`` border views: other inner views slid across the view (their depth and tilt kept)
  until the board 0.6 of a square beyond its outer corners lies 4 px from the top, bottom, left, right
  side in turn (its corners then in that side's strip).

Both are rendered (edge pixels integrated, the scene's defects), detected and calibrated by cellctl
(opencv5). Scores on ``--test`` held-out views drawn from the whole pool (border ones included):
the RMS of their true corner pixels fitted by each calibrated camera with the view's pose free
(``heldout_rms``), and the projection difference to the true lens (best rotation compensated) over
the border ring's pixels and over the whole image.

Run: ``.venv/bin/python bench/intrinsics_border.py --seeds 8 --out bench/results/intrinsics_border.md``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.intrinsics_heldout import BOARD, heldout_rms, scene_camera_and_imaging  # noqa: E402
from calibration.detect import detect  # noqa: E402
from calibration.intrinsics import calibrate, coverage_counts, projection_difference  # noqa: E402
from calibration.synthetic import plan_views  # noqa: E402
from calibration.verdict import BORDER_FRACTION, border_coverage  # noqa: E402
from drivers.sim.imaging import PlanarObject, render  # noqa: E402

EDGE_PX = 4.0
"""Border views put the board's printed outline this many pixels from the side."""


def ring_pixels(size: tuple[int, int], step: int = 8) -> np.ndarray:
    """Pixels of the border ring (the outer ``BORDER_FRACTION`` along every side), on a grid."""
    w, h = size
    g = np.array([[u, v] for v in range(0, h, step) for u in range(0, w, step)], dtype=np.float64)
    bw, bh = BORDER_FRACTION * w, BORDER_FRACTION * h
    ring = (g[:, 0] < bw) | (g[:, 0] > w - 1 - bw) | (g[:, 1] < bh) | (g[:, 1] > h - 1 - bh)
    return g[ring]


def to_side(truth: Any, T: np.ndarray, side: str, size: tuple[int, int]) -> np.ndarray | None:
    """``T`` slid across the view (camera x/y, its depth kept) until the board's printed outline lies
    ``EDGE_PX`` from ``side`` (the outline: 0.6 of a square beyond the outer corners; the detector needs 0.2);
    None when its corners then miss that side's border strip, or the outline leaves the image elsewhere."""
    w, h = size
    X = BOARD.points().xyz_m
    m = 0.6 * BOARD.square_mm * 1e-3  # the board beyond its outer corners that must be seen (0.2 squares: detect)
    (x0, y0), (x1, y1) = X[:, :2].min(0) - m, X[:, :2].max(0) + m
    outline = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]])
    axis, sign = {"top": (1, -1), "bottom": (1, 1), "left": (0, -1), "right": (0, 1)}[side]
    n = (w, h)[axis]
    out = T.copy()
    for _ in range(6):
        uv = truth.project(outline @ out[:3, :3].T + out[:3, 3])
        far = uv[:, axis].max() if sign > 0 else uv[:, axis].min()
        want = (n - 1 - EDGE_PX) if sign > 0 else EDGE_PX
        d_px = want - far
        if abs(d_px) < 0.5:
            break
        out[axis, 3] += d_px * out[2, 3] / (truth.fx if axis == 0 else truth.fy)
    box = truth.project(outline @ out[:3, :3].T + out[:3, 3])
    inside = (box[:, 0] >= 3).all() and (box[:, 0] <= w - 4).all() and (box[:, 1] >= 3).all() and \
        (box[:, 1] <= h - 4).all()
    corners = truth.project(X @ out[:3, :3].T + out[:3, 3])
    reached = border_coverage(coverage_counts(size, corners))[side] > 0
    return out if inside and reached else None


def whole_pixels(size: tuple[int, int], step: int = 16) -> np.ndarray:
    w, h = size
    return np.array([[u, v] for v in range(0, h, step) for u in range(0, w, step)], dtype=np.float64)


def one_set(seed: int, n_inner: int, n_extra: int, n_test: int, size: tuple[int, int], supersample: int
            ) -> dict[str, Any] | None:
    truth, imaging = scene_camera_and_imaging(size)
    rng = np.random.default_rng(seed)
    pool = plan_views(truth, BOARD, 60, rng, fill=0.45, margin_px=6, whole_outline=True)
    X = BOARD.points().xyz_m

    def sides(T: np.ndarray) -> set[str]:
        uv = truth.project(X @ T[:3, :3].T + T[:3, 3])
        return {k for k, f in border_coverage(coverage_counts(size, uv)).items() if f > 0}

    def touches(T: np.ndarray) -> bool:
        return bool(sides(T))

    order = rng.permutation(len(pool))
    test = [pool[i] for i in order[:n_test]]
    rest = [pool[i] for i in order[n_test:]]
    inner = [T for T in rest if not touches(T)]
    if len(inner) < n_inner + 2 * n_extra:
        return None
    shared = inner[:n_inner]
    # border views: further inner views slid (in the camera frame, at their distance) against the middle of
    # each side in turn, until the board's outermost corner lies in that side's strip, its outline in view
    chosen = [T for T in (to_side(truth, inner[n_inner + n_extra + k], side, size)
                          for k, side in enumerate(("top", "bottom", "left", "right")[:n_extra])) if T is not None]
    reached = set().union(*(sides(T) for T in chosen)) if chosen else set()
    if len(chosen) < n_extra or len(reached) < min(4, n_extra):
        return None
    sets = {"without": shared + inner[n_inner:n_inner + n_extra], "with": shared + chosen}
    rendered: dict[int, Any] = {}

    def detection(T: np.ndarray) -> Any:
        key = id(T)
        if key not in rendered:
            img = render(truth, [PlanarObject(T, BOARD.reflectance)], imaging, rng, supersample=supersample)
            rendered[key] = detect(img, BOARD, f"v{len(rendered):02d}")
        return rendered[key]

    out: dict[str, Any] = {"seed": seed}
    ring, whole = ring_pixels(size), whole_pixels(size)
    for name, poses in sets.items():
        dets = [d for d in (detection(T) for T in poses) if d.found]
        t0 = time.process_time()
        res = calibrate(dets, BOARD, "opencv5")
        out[f"{name}_s"] = time.process_time() - t0
        out[f"{name}_views"] = len(dets)
        out[f"{name}_ok"] = bool(res.verdict.get("ok"))
        out[f"{name}_codes"] = ",".join(p["code"] for p in res.verdict.get("problems", [])) or "-"
        out[f"{name}_border"] = res.verdict.get("border_covered", {})
        out[f"{name}_heldout"] = heldout_rms(res.camera, truth, test, BOARD)
        out[f"{name}_ring"] = projection_difference(res.camera, truth, ring)["rms_px"]
        out[f"{name}_whole"] = projection_difference(res.camera, truth, whole)["rms_px"]
    return out


def table(rows: list[dict[str, Any]], args: argparse.Namespace) -> list[str]:
    lines = [f"{len(rows)} seeded sets (seeds {args.seed0}..{args.seed0 + args.seeds - 1}; a set whose pool lacks the "
             "views of a kind, or border views reaching all four sides, skipped), "
             f"{args.width}x{args.height} px, 9x6 chessboard (20 mm), the real-defects scene's lens and defects, "
             f"edge pixels integrated on {args.supersample}x{args.supersample} samples; "
             f"{args.inner} shared inner views + {args.extra} more inner (without) or border (with) views; "
             f"{args.test} held-out views from the whole pool.", "",
             "| seed (views detected without / with) | verdict without | verdict with "
             "| held-out RMS without / with (px) "
             "| ring diff to truth without / with (px) "
             "| whole-image diff without / with (px) |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['seed']} ({r['without_views']} / {r['with_views']}) | {r['without_codes']} | "
                     f"{r['with_codes']} | "
                     f"{r['without_heldout']:.3f} / {r['with_heldout']:.3f} | "
                     f"{r['without_ring']:.3f} / {r['with_ring']:.3f} | "
                     f"{r['without_whole']:.3f} / {r['with_whole']:.3f} |")
    if rows:
        ok_with = sum(r["with_ok"] for r in rows)
        med = {k: float(np.median([r[k] for r in rows])) for k in
               ("without_heldout", "with_heldout", "without_ring", "with_ring", "without_whole", "with_whole")}
        better = sum(r["with_heldout"] < r["without_heldout"] for r in rows)
        flagged = sum("border_not_covered" in r["without_codes"] for r in rows)
        lines += ["", f"Median held-out RMS without / with border views: **{med['without_heldout']:.3f} / "
                      f"{med['with_heldout']:.3f} px** (with better on {better} of {len(rows)}); projection "
                      f"difference to the true lens over the border ring {med['without_ring']:.3f} / "
                      f"{med['with_ring']:.3f} px, over the whole image {med['without_whole']:.3f} / "
                      f"{med['with_whole']:.3f} px. The verdict flagged `border_not_covered` on {flagged} of "
                      f"{len(rows)} sets without border views and on "
                      f"{sum('border_not_covered' in r['with_codes'] for r in rows)} with them; {ok_with} of "
                      f"{len(rows)} sets with border views had an OK verdict (the others name what is still missing "
                      "or poorly determined)."]
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--seed0", type=int, default=700)
    ap.add_argument("--inner", type=int, default=8)
    ap.add_argument("--extra", type=int, default=4)
    ap.add_argument("--test", type=int, default=8)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--supersample", type=int, default=8)
    ap.add_argument("--out", type=str, default=None)
    args = ap.parse_args()
    rows = []
    t0 = time.time()
    for seed in range(args.seed0, args.seed0 + args.seeds):
        r = one_set(seed, args.inner, args.extra, args.test, (args.width, args.height), args.supersample)
        if r is not None:
            rows.append(r)
            print(f"seed {seed}: held-out {r['without_heldout']:.3f} / {r['with_heldout']:.3f} px, ring "
                  f"{r['without_ring']:.3f} / {r['with_ring']:.3f} px ({r['without_codes']})", flush=True)
        else:
            print(f"seed {seed}: skipped (too few views of a kind)", flush=True)
    lines = ["# An uncovered image border: held-out effect (bench/intrinsics_border.py)", "",
             f"`.venv/bin/python bench/intrinsics_border.py {' '.join(sys.argv[1:])}` ({time.time() - t0:.0f} s "
             "wall on the shared 2-core machine).", "", *table(rows, args)]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
