"""Influential-view rejection (``calibrate(reject_views=True)``, issue 39): does it find a bad view, and
does it leave good sets alone?

- **Renders with truth** (the real-defects scene, 960x720, 12 views of a 9x6 board, as
  bench/intrinsics_real.py): each seed clean, and with one view made bad the way a moving camera
  makes it: a rolling-shutter shear (each row shifted sideways in proportion to its read-out time,
  ``--shear-px`` from the top of the image to the bottom) and a horizontal motion blur (``--blur-px``
  long). cellctl's opencv5 with and without the rejection: which views are rejected, and the
  projection difference to the true lens over the covered cells.
- **Real sets** (udacity 9x6, GoPro 8x6, OpenCV's left and right 9x6, mrcal's fisheye corners): the
  product's answer (``select_by_cross_validation`` over division / opencv5 / fisheye4 / opencv8, flat
  and warped; fisheye4 alone on the fisheye corners, the product's choice there) with and without the
  rejection, the split-half difference over the same covered cells (the even and the odd views of the
  views each kept) and the views rejected.

Run: ``.venv/bin/python bench/intrinsics_influence.py [--render-seeds 3] [--sets udacity,gopro,opencv_left,
opencv_right,fisheye]`` (prints JSON rows; the table is in bench/results/intrinsics_influence.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.intrinsics import warm_up  # noqa: E402
from bench.intrinsics_heldout import scene_camera_and_imaging  # noqa: E402
from bench.intrinsics_real import HALVES, fisheye_set, image_set, stereo_set  # noqa: E402
from calibration.detect import detect  # noqa: E402
from calibration.intrinsics import calibrate, covered_points, projection_difference, select_by_cross_validation  # noqa: E402
from calibration.synthetic import plan_views  # noqa: E402
from calibration.targets import Chessboard  # noqa: E402
from drivers.sim.imaging import PlanarObject, render  # noqa: E402


def rolling_shutter(img: np.ndarray, shear_px: float, blur_px: int) -> np.ndarray:
    """The image a panning rolling-shutter camera takes: row ``y`` shifted by ``shear_px * (y / H - 1/2)``,
    then blurred along the rows by a ``blur_px``-long box (the motion during one row's exposure)."""
    h, w = img.shape[:2]
    A = np.array([[1.0, shear_px / h, -shear_px / 2], [0.0, 1.0, 0.0]])
    out = cv2.warpAffine(img, A, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if blur_px > 1:
        out = cv2.blur(out, (blur_px, 1))
    return out


def render_rows(seed: int, shear_px: float, blur_px: int, n_views: int = 12,
                size: tuple[int, int] = (960, 720), clean_only: bool = False) -> list[dict[str, Any]]:
    board = Chessboard(9, 6, 20.0)
    truth, imaging = scene_camera_and_imaging(size)
    rng = np.random.default_rng(seed)
    poses = plan_views(truth, board, n_views, rng, fill=0.6, margin_px=6, whole_outline=True)
    imgs = [render(truth, [PlanarObject(T, board.reflectance)], imaging, rng, supersample=32) for T in poses]
    bad = seed % n_views
    rows = []
    sets = [("clean", imgs)]
    if not clean_only:
        sets.append(("bad view", [rolling_shutter(g, shear_px, blur_px) if k == bad else g
                                  for k, g in enumerate(imgs)]))
    for label, images in sets:
        dets = [d for d in (detect(g, board, f"v{k:02d}") for k, g in enumerate(images)) if d.found]
        plain = calibrate(dets, board, "opencv5")
        pts = covered_points(plain)
        res = calibrate(dets, board, "opencv5", reject_views=True)
        rej = [r["image"] for r in (res.view_rejection or {}).get("rejected", [])]
        med = float(np.median([v.rms_px for v in plain.views if v.used]))
        bad_rms = next((v.rms_px for v in plain.views if v.image == f"v{bad:02d}"), float("nan"))
        row = {"seed": seed, "set": label, "bad_view": f"v{bad:02d}" if label != "clean" else "",
               "views": len(dets), "rejected": rej,
               "bad_view_rms_over_median": round(bad_rms / med, 2) if label != "clean" else None,
               "truth_px_all": projection_difference(plain.camera, truth, pts)["rms_px"],
               "truth_px_rejecting": projection_difference(res.camera, truth, pts)["rms_px"]}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


CANDIDATES = [(m, w) for m in ("division", "opencv5", "fisheye4", "opencv8") for w in (False, True)]


def real_rows(key: str) -> list[dict[str, Any]]:
    if key == "fisheye":
        s = fisheye_set()
        dets = s.corners["mrcal"]
        cands = [("fisheye4", False)]
    else:
        s = {"udacity": lambda: image_set("udacity_camera_cal_9x6", 9, 6),
             "gopro": lambda: image_set("udacity_gopro_wide_8x6", 8, 6),
             "opencv_left": lambda: stereo_set("left"), "opencv_right": lambda: stereo_set("right")}[key]()
        dets = s.corners["ours"]
        cands = CANDIDATES
    pts = covered_points(calibrate(dets, s.board, "opencv8", image_size=s.size))
    rows = []
    for reject in (False, True):
        t0 = time.process_time()
        if len(cands) > 1:
            res, sel = select_by_cross_validation(dets, s.board, cands, image_size=s.size, reject_views=reject)
            model, warp = sel["chosen"]["model"], sel["chosen"]["board_warp"]
        else:
            (model, warp), = cands
            res = calibrate(dets, s.board, model, image_size=s.size, reject_views=reject)
        kept = {v.image for v in res.views if v.used}
        used = [d for d in dets if d.image in kept]
        halves = [calibrate(used[h], s.board, model, image_size=s.size, board_warp=warp).camera for h in HALVES]
        row = {"set": s.name, "rejecting": reject, "model": model + (", warp" if warp else ""),
               "views": len(used), "of": len(dets),
               "split_px": projection_difference(halves[0], halves[1], pts)["rms_px"],
               "rejected": [] if res.view_rejection is None else res.view_rejection["rejected"],
               "kept_significant": [] if res.view_rejection is None else res.view_rejection["kept_significant"],
               "scale": None if res.view_rejection is None else res.view_rejection["scale"],
               "cpu_s": round(time.process_time() - t0, 1)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--render-seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=300)
    ap.add_argument("--shear-px", type=float, default=4.0)
    ap.add_argument("--blur-px", type=int, default=5)
    ap.add_argument("--sets", default="udacity,gopro,opencv_left,opencv_right,fisheye")
    ap.add_argument("--clean-only", action="store_true", help="renders without the bad view only (false alarms)")
    a = ap.parse_args()
    warm_up()
    for key in [k for k in a.sets.split(",") if k]:
        real_rows(key)
    for seed in range(a.first_seed, a.first_seed + a.render_seeds):
        render_rows(seed, a.shear_px, a.blur_px, clean_only=a.clean_only)


if __name__ == "__main__":
    main()
