"""Intrinsics on defect-laden renders, several seeds: every target type and lens model, cellctl vs
OpenCV's calibrateCamera on the same detections, and the honesty of the reported uncertainty.

Each set: ``--views`` views planned by ``calibration.intrinsics.plan_views`` (the whole printed
outline in view), rendered by ``drivers.sim.imaging.renderer`` with the virtual camera's defects (shot +
read noise, vignetting, blur, defocus away from the focus plane, gamma, JPEG), detected by
``calibration.detect``. Actual error = projection difference to the true lens over the covered
cells (best rotation compensated); reported = ``uncertainty.projection_rms_px`` (the honesty ratio
takes the actual error where that is evaluated: the mean of the points in each covered cell). Honesty per target
and model: the median of actual/reported over the sets with a bootstrap 90 % interval (one set's ratio
is a single draw dominated by a few parameter directions, so a median of 10 sets scatters by about
+-0.2), the pooled RMS actual / RMS reported (1 for an honest uncertainty), and the same for an
honest reference (the same views with independent Gaussian errors at the residual level). OpenCV gets our
detections (bias-corrected centres for circle marks: it has no bias model) and its nearest model
(opencv5 for division truth). For the circle plate OpenCV also runs its own pipeline on the same
images (``cv2.findCirclesGrid`` + ``calibrateCamera``, blob centres with their perspective bias):
that is what a user of OpenCV gets; the first comparison isolates the solver.

Times: both solvers after a warm-up (numba's compiled kernels are loaded once per process, as
the service does at start), wall and CPU (``time.process_time``) per calibration; the load
average is printed with the table.

Run: ``.venv/bin/python bench/intrinsics_rendered.py --targets chessboard --seeds 10 [--out F.md]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.intrinsics import TRUTHS, warm_up  # noqa: E402
from calibration.camera_model import CameraModel  # noqa: E402
from calibration.detect import detect  # noqa: E402
from calibration.detect.circle_grid import blob_detector  # noqa: E402
from calibration.intrinsics import calibrate, covered_point_means, covered_points, projection_difference  # noqa: E402
from calibration.observations import Detection  # noqa: E402
from calibration.synthetic import plan_views, synthetic_detections  # noqa: E402
from calibration.targets import Charuco, Chessboard, CirclePlate, PlanarTarget  # noqa: E402
from drivers.sim.imaging import Imaging, PlanarObject, render  # noqa: E402

TARGETS: dict[str, PlanarTarget] = {
    "chessboard": Chessboard(9, 6, 25.0),
    "charuco": Charuco(7, 5, 30.0, 22.0, "DICT_4X4_50"),
    "circle_plate": CirclePlate(7, 7, 15.0, 7.5),
}
DEFECTS = Imaging(blur_sigma_px=0.7, gain_dn_per_e=0.5, read_noise_dn=1.5, vignetting=0.25, gamma=1.1,
                  jpeg_quality=92, focus_distance_m=0.35, defocus_sigma_px_per_diopter=0.4)
CV_FLAGS = {"opencv5": 0, "opencv8": cv2.CALIB_RATIONAL_MODEL}
NEED_VS_CV = {"chessboard": 1.0, "charuco": 1.0, "circle_plate": 0.5}


def opencv_calibrate(dets: list[Detection], target: PlanarTarget, size: tuple[int, int], model: str
                     ) -> tuple[CameraModel, float, float]:
    """OpenCV's calibrateCamera on the detections: camera, wall and CPU seconds."""
    tp = target.points()
    where = {int(i): k for k, i in enumerate(tp.ids)}
    obj = [tp.xyz_m[[where[int(i)] for i in d.ids]].astype(np.float32) for d in dets]
    img = [d.uv.astype(np.float32) for d in dets]
    t0, c0 = time.perf_counter(), time.process_time()
    _, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, None, None, flags=CV_FLAGS[model])
    n = 8 if model == "opencv8" else 5
    cam = CameraModel(model, size[0], size[1], K, dist.ravel()[:n])  # type: ignore[arg-type]
    return cam, time.perf_counter() - t0, time.process_time() - c0


def opencv_plate_points(img: np.ndarray, plate: CirclePlate) -> np.ndarray | None:
    """OpenCV's own circle-grid detection of the plate's marks, ordered as the plate's ids (row by
    row; a mirrored order, which no pose can produce, is flipped), or None when not found."""
    ok, c = cv2.findCirclesGrid(img, (plate.cols, plate.rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID,
                                blobDetector=blob_detector(img.shape[0] * img.shape[1], plate.cols * plate.rows))
    if not ok:
        return None
    uv = np.asarray(c, dtype=np.float64).reshape(plate.rows, plate.cols, 2)
    ex, ey = uv[0, -1] - uv[0, 0], uv[-1, 0] - uv[0, 0]
    if ex[0] * ey[1] - ex[1] * ey[0] < 0:   # target x, y, z = into the target: counter-clockwise on screen
        uv = uv[:, ::-1]
    return uv.reshape(-1, 2)



def one_set(tname: str, model: str, seed: int, views: int, size: tuple[int, int]) -> dict[str, Any]:
    w, h = size
    K = np.array([[0.875 * w, 0.0, w / 2 + 1.5], [0.0, 0.873 * w, h / 2 - 2.0], [0.0, 0.0, 1.0]])
    truth = CameraModel(model, w, h, K, TRUTHS[model])  # type: ignore[arg-type]
    target = TARGETS[tname]
    rng = np.random.default_rng(seed)
    poses = plan_views(truth, target, views, rng, fill=0.6, margin_px=6, whole_outline=True)
    imgs = [render(truth, [PlanarObject(T, target.reflectance)], DEFECTS, rng) for T in poses]
    dets = [detect(img, target, f"v{k:02d}") for k, img in enumerate(imgs)]
    found = [d for d in dets if d.found]
    t0, c0 = time.perf_counter(), time.process_time()
    res = calibrate(found, target, model)
    t_ours, c_ours = time.perf_counter() - t0, time.process_time() - c0
    pts = covered_points(res)
    cv_model = "opencv5" if model == "division" else model
    cv_cam, t_cv, c_cv = opencv_calibrate(found, target, size, cv_model)
    # the honesty ratio compares the actual error where the reported one is taken (the points' mean
    # in each covered cell); the accuracy columns stay at the covered cells' centres
    act_at = projection_difference(res.camera, truth, covered_point_means(res))["rms_px"]
    out = {"found": len(found), "act": projection_difference(res.camera, truth, pts)["rms_px"], "act_at": act_at,
           "rep": res.uncertainty["projection_rms_px"], "cv": projection_difference(cv_cam, truth, pts)["rms_px"],
           "inflation": res.uncertainty.get("inflation", 1.0), "t_ours": t_ours, "t_cv": t_cv,
           "c_ours": c_ours, "c_cv": c_cv, "verdict": res.verdict["ok"], "cv_model": cv_model}
    # The same geometry with independent Gaussian noise at the residual level: what the median
    # actual/reported of a perfectly honest uncertainty is on such a set (a single set's error is
    # dominated by a few parameter directions, so the median ratio sits well below 1).
    ref_rng = np.random.default_rng([seed, 7])
    ref_dets = synthetic_detections(truth, target, poses, res.sigma_px, ref_rng)
    ref = calibrate(ref_dets, target, model)
    out["ref_ratio"] = (projection_difference(ref.camera, truth, covered_point_means(ref))["rms_px"]
                        / ref.uncertainty["projection_rms_px"])
    if isinstance(target, CirclePlate):
        own = [(k, opencv_plate_points(img, target)) for k, img in enumerate(imgs)]
        cv_dets = [Detection(f"v{k:02d}", True, target.points().ids.copy(), uv, image_size=size)
                   for k, uv in own if uv is not None]
        out["cv_own_found"] = len(cv_dets)
        out["cv_own"] = float("nan")
        if len(cv_dets) >= 3:
            cam_own, _, _ = opencv_calibrate(cv_dets, target, size, cv_model)
            out["cv_own"] = projection_difference(cam_own, truth, pts)["rms_px"]
    return out


def run(targets: list[str], models: list[str], seeds: int, views: int, size: tuple[int, int]) -> list[dict[str, Any]]:
    rows = []
    for tname in targets:
        for model in models:
            per = []
            for s in range(seeds):
                try:
                    per.append(one_set(tname, model, 100 + s, views, size))
                except Exception as exc:  # a failed set is counted and reported, not hidden
                    print(f"{tname} {model} seed {s}: {exc}", file=sys.stderr)
            rows.append({"target": tname, "model": model, "per": per, "failed": seeds - len(per)})
            print(f"rendered {tname} {model}: done", file=sys.stderr)
    return rows


def _need(tname: str, model: str) -> float:
    """The issue's accuracy target as a ratio to OpenCV: circle plate 0.5x, division truth 0.5x
    (OpenCV's polynomial can only approximate it), the matching model 1.0x."""
    return 0.5 if tname == "circle_plate" or model == "division" else 1.0


def table(rows: list[dict[str, Any]], views: int, size: tuple[int, int], seeds: int) -> str:
    load = os.getloadavg()
    L = [f"Defect-laden renders ({size[0]}x{size[1]}, {views} views per set, {seeds} seeds; shot + read noise, "
         "vignetting 25 %, blur 0.7 px + defocus, gamma 1.1, JPEG 92). Medians over seeds. Times per "
         f"calibration after a warm-up, wall / CPU; load average during the run {load[0]:.1f} / {load[1]:.1f} "
         f"({platform.machine()}, {os.cpu_count()} cores shared, OpenCV {cv2.__version__}).", "",
         "| target | truth | OpenCV model | sets | views found | actual ours / cv (px) | ratio ours/cv (median) "
         "| OpenCV own pipeline: views / actual (px) / ratio ours/it | actual/reported median (honest reference) "
         "| actual/reported RMS (honest reference) | median 90 % interval (bootstrap over sets) "
         "| pooled RMS actual / RMS reported | within [0.5, 2] "
         "| inflated sets | time ours / cv wall (s) | time ours / cv CPU (s) | CPU ratio | verdict ok |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p = r["per"]
        if not p:
            L.append(f"| {r['target']} | {r['model']} | - | 0 |" + " - |" * 14)
            continue
        act = np.array([x["act"] for x in p])
        cv = np.array([x["cv"] for x in p])
        act_at = np.array([x["act_at"] for x in p])
        rq = act_at / np.array([x["rep"] for x in p])
        r["ratio"] = float(np.median(act / cv))
        r["unc"] = float(np.median(rq))
        rr = np.array([x["ref_ratio"] for x in p])
        r["unc_ref"] = float(np.median(rr))
        r["unc_rms"] = float(np.sqrt(np.mean(rq**2)))
        r["unc_rms_ref"] = float(np.sqrt(np.mean(rr**2)))
        rep = np.array([x["rep"] for x in p])
        r["unc_pooled"] = float(np.sqrt(np.mean(act_at**2) / np.mean(rep**2)))
        # how far the median of this many sets scatters: one set's ratio is a single draw dominated
        # by a few parameter directions (an honest uncertainty's median sits ~0.5-0.9 on 6 views)
        boot = np.median(rq[np.random.default_rng(0).integers(0, len(rq), (2000, len(rq)))], axis=1)
        r["unc_ci"] = (float(np.percentile(boot, 5)), float(np.percentile(boot, 95)))
        c_ours = float(np.median([x["c_ours"] for x in p]))
        c_cv = float(np.median([x["c_cv"] for x in p]))
        r["cpu_ratio"] = c_ours / max(c_cv, 1e-9)
        own = "-"
        if "cv_own" in p[0]:
            o = np.array([x["cv_own"] for x in p])
            ok = np.isfinite(o)
            r["ratio_own"] = float(np.median(act[ok] / o[ok])) if ok.any() else float("nan")
            own = (f"{np.mean([x['cv_own_found'] for x in p]):.1f} / "
                   f"{np.median(o[ok]) if ok.any() else float('nan'):.4f} / {r['ratio_own']:.2f}")
        failed = f" (+{r['failed']} failed)" if r["failed"] else ""
        L.append(f"| {r['target']} | {r['model']} | {p[0]['cv_model']} | {len(p)}{failed} "
                 f"| {np.mean([x['found'] for x in p]):.1f} | {np.median(act):.4f} / {np.median(cv):.4f} "
                 f"| {r['ratio']:.2f} | {own} | {r['unc']:.2f} ({r['unc_ref']:.2f}) | {r['unc_rms']:.2f} "
                 f"({r['unc_rms_ref']:.2f}) | {r['unc_ci'][0]:.2f}-{r['unc_ci'][1]:.2f} | {r['unc_pooled']:.2f} "
                 f"| {np.mean((rq >= 0.5) & (rq <= 2)):.0%} "
                 f"| {sum(x['inflation'] > 1 for x in p)} | {np.median([x['t_ours'] for x in p]):.3f} / "
                 f"{np.median([x['t_cv'] for x in p]):.3f} | {c_ours:.3f} / {c_cv:.3f} | {r['cpu_ratio']:.1f}x "
                 f"| {sum(x['verdict'] for x in p)}/{len(p)} |")
    L += ["", "### Against the targets", "",
          "| target | truth | measure | measured | target | verdict |", "|---|---|---|---|---|---|"]
    for r in rows:
        if "ratio" not in r:
            L.append(f"| {r['target']} | {r['model']} | all | no set calibrated | - | MISSED |")
            continue
        need = _need(r["target"], r["model"])
        L.append(f"| {r['target']} | {r['model']} | projection error vs OpenCV on our detections | {r['ratio']:.2f}x "
                 f"| <= {need}x | {'met' if r['ratio'] <= need * 1.005 else 'MISSED'} |")
        if "ratio_own" in r:
            ro = r["ratio_own"]
            L.append(f"| {r['target']} | {r['model']} | projection error vs OpenCV's own pipeline | {ro:.2f}x "
                     f"| <= {need}x | {'met' if ro <= need * 1.005 else 'MISSED'} |")
        L.append(f"| {r['target']} | {r['model']} | actual / reported uncertainty (median) | {r['unc']:.2f} "
                 f"| 0.5-2 | {'met' if 0.5 <= r['unc'] <= 2 else 'MISSED'} |")
        L.append(f"| {r['target']} | {r['model']} | time with uncertainty / OpenCV (CPU) | {r['cpu_ratio']:.1f}x "
                 f"| <= 10x | {'met' if r['cpu_ratio'] <= 10 else 'MISSED'} |")
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", default="chessboard,charuco,circle_plate")
    ap.add_argument("--models", default="opencv5,opencv8,division")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--size", default="480x360", help="image size WxH")
    ap.add_argument("--out", help="write the markdown table here too")
    a = ap.parse_args()
    size = tuple(int(v) for v in a.size.split("x"))
    t0 = time.time()
    warm_up()
    rows = run(a.targets.split(","), a.models.split(","), a.seeds, a.views, (size[0], size[1]))
    md = table(rows, a.views, (size[0], size[1]), a.seeds) + f"\nRun time {time.time() - t0:.0f} s.\n"
    print(md)
    if a.out:
        Path(a.out).write_text(md)


if __name__ == "__main__":
    main()
