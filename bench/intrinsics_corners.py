"""Corners on real chessboard sets, per corner: cellctl's against OpenCV's SB (``CALIB_CB_ACCURACY``) and
``cornerSubPix`` (issue 39 item 1).

For each set (the views every detector found):

- **per view**: RMS and worst distance of our corners to OpenCV's SB corners and to ``cornerSubPix`` (5x5
  window from the same sector-detector start), and the corner that differs most;
- **per corner class** (inner, board edge, the four board corners): the RMS of the residuals of one full
  calibration (opencv8, each corner source through the same solver, no weights: the corners alone differ);
- **split-half over many halvings**: the even/odd split is one draw; the same N seeded random halvings for
  each corner source give the distribution (10/50/90 %) and how often ours is better.

Run: ``.venv/bin/python bench/intrinsics_corners.py [--sets opencv_right,opencv_left,udacity,gopro]
[--halvings 20] [--per-view]``. Renders with truth: ``bench/intrinsics_heldout.py`` measures corners
against the true positions.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.intrinsics_heldout import opencv_corners  # noqa: E402
from bench.intrinsics_real import _opencv_in_our_order, halvings  # noqa: E402
from calibration.detect import detect, read_image  # noqa: E402
from calibration.detect.chessboard import find_corners_opencv  # noqa: E402
from calibration.intrinsics import calibrate, covered_points, projection_difference  # noqa: E402
from calibration.observations import Detection  # noqa: E402
from calibration.targets import Chessboard  # noqa: E402

DATA = ROOT / "tests" / "data"
SETS = {"opencv_right": ("opencv_stereo_9x6", "right*.jpg", 9, 6),
        "opencv_left": ("opencv_stereo_9x6", "left*.jpg", 9, 6),
        "udacity": ("udacity_camera_cal_9x6", "*.jpg", 9, 6), "gopro": ("udacity_gopro_wide_8x6", "*.jpg", 8, 6)}
CLASSES = ("inner", "edge", "board corner")


def corner_class(cols: int, rows: int) -> np.ndarray:
    """(cols * rows,) 0 inner, 1 on the grid's border, 2 one of its four corners (by id)."""
    r, c = np.divmod(np.arange(cols * rows), cols)
    er, ec = (r == 0) | (r == rows - 1), (c == 0) | (c == cols - 1)
    return np.where(er & ec, 2, np.where(er | ec, 1, 0))


def sources(key: str) -> tuple[Chessboard, tuple[int, int], dict[str, list[Detection]], list[str]]:
    folder, pattern, cols, rows = SETS[key]
    board = Chessboard(cols, rows, 1000.0)
    files = sorted((DATA / folder).glob(pattern))
    greys = [read_image(f) for f in files]
    sizes = [(g.shape[1], g.shape[0]) for g in greys]
    size = max(set(sizes), key=sizes.count)
    out: dict[str, list[Detection]] = {"ours": [], "opencv SB": [], "cornerSubPix": []}
    lines = []
    for f, g in zip(files, greys, strict=True):
        if (g.shape[1], g.shape[0]) != size:
            continue
        d = detect(g, board, f.name)
        sb = opencv_corners(g, board)
        start = find_corners_opencv(g, cols, rows)
        if not d.found or sb is None or start is None:
            continue
        sp = cv2.cornerSubPix(g, start.reshape(-1, 1, 2).astype(np.float32), (5, 5), (-1, -1),
                              (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)).reshape(-1, 2)
        uv = {"ours": d.uv, "opencv SB": _opencv_in_our_order(d, sb, board),
              "cornerSubPix": _opencv_in_our_order(d, sp.astype(np.float64), board)}
        for k, p in uv.items():
            out[k].append(Detection(f.name, True, ids=d.ids.copy(), uv=p, image_size=size))
        sq = float(np.median(np.hypot(*np.diff(d.uv.reshape(rows, cols, 2), axis=1).reshape(-1, 2).T)))
        e_sb, e_sp = (np.hypot(*(d.uv - uv[k]).T) for k in ("opencv SB", "cornerSubPix"))
        lines.append(f"| {f.name} | {sq:.1f} | {np.sqrt(np.mean(e_sb**2)):.3f} | {e_sb.max():.3f} (id {e_sb.argmax()}, "
                     f"{CLASSES[corner_class(cols, rows)[e_sb.argmax()]]}) | {np.sqrt(np.mean(e_sp**2)):.3f} | "
                     f"{e_sp.max():.3f} |")
    return board, size, out, lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="opencv_right,opencv_left,udacity,gopro")
    ap.add_argument("--halvings", type=int, default=20)
    ap.add_argument("--per-view", action="store_true", help="also the per-view table")
    a = ap.parse_args()
    t0 = time.time()
    for key in a.sets.split(","):
        board, size, src, lines = sources(key)
        print(f"\n### {key} ({len(src['ours'])} views)\n")
        if a.per_view:
            print("| view | square (px) | ours-SB RMS | ours-SB max | ours-subpix RMS | ours-subpix max |")
            print("|---|---|---|---|---|---|")
            print("\n".join(lines) + "\n")
        kind = corner_class(board.cols, board.rows)
        pts = covered_points(calibrate(src["ours"], board, "opencv8", image_size=size, jackknife=False))
        splits = halvings(len(src["ours"]), a.halvings)
        print("| corners | residual inner | edge | board corner | all | split-half even/odd | 10 % | median | 90 % |")
        print("|---|---|---|---|---|---|---|---|---|")
        diffs = {}
        for name, dets in src.items():
            res = calibrate(dets, board, "opencv8", image_size=size, jackknife=False)
            e = [np.concatenate([np.hypot(*v.residuals_px.T)[kind[v.ids] == k] for v in res.views if v.used])
                 for k in range(3)]
            ds = []
            for h in splits:
                cams = [calibrate([dets[i] for i in x], board, "opencv5", image_size=size, jackknife=False).camera
                        for x in h]
                ds.append(projection_difference(cams[0], cams[1], pts)["rms_px"])
            diffs[name] = np.array(ds)
            q = np.percentile(ds[1:], [10, 50, 90])
            print(f"| {name} | " + " | ".join(f"{np.sqrt(np.mean(x**2)):.3f}" for x in e)
                  + f" | {res.rms_px:.3f} | {ds[0]:.3f} | {q[0]:.3f} | {q[1]:.3f} | {q[2]:.3f} |")
        r = diffs["ours"][1:] / diffs["opencv SB"][1:]
        print(f"\nours / SB over {a.halvings} halvings (opencv5): median {np.median(r):.2f}, ours better in "
              f"{np.mean(r < 1):.0%}.")
    print(f"\n{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
