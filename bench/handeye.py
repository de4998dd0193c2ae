"""Hand-eye and N-point benchmark (issues 5, 15): cellctl against OpenCV's seven methods.

Virtual-cell data with truth (``calibration.handeye.simulate_handeye``): both setups, 8/12/20
robot stations, robot pose noise 0.02 mm/0.005°, 0.05 mm/0.01° and 0.1 mm/0.02° (per axis, the
module's stated noise model), a 11x8 chessboard (25 mm) seen by a 1920x1200 camera (f = 1900 px)
from 0.38-0.52 m, several seeds. The point-level sets add Gaussian pixel noise of 0.05 px (what
a good detector achieves at 1-3 grey levels); the image-based sets render each station with
``drivers.sim.imaging.renderer`` at 1 and 3 grey levels of noise and detect it with ``calibration.detect``.
Both solvers get the same detections: OpenCV's ``calibrateHandEye`` (TSAI, PARK, HORAUD, ANDREFF,
DANIILIDIS) and ``calibrateRobotWorldHandEye`` (RW_SHAH, RW_LI) get the per-station target poses
from ``calibration.pose.pnp`` (eye-to-hand: inverted robot poses, as OpenCV documents); cellctl runs
its whole pipeline (checks, closed form, joint ML refinement with the stated robot noise,
covariance). The accuracy tables run it without leave-one-out (the stated-noise fit); a separate
table runs the default (leave-one-out, error model chosen) on some of the same sets. On the
point-level sets the Cramér-Rao bound of the data (``handeye_common.cramer_rao``) says how close
any unbiased estimator could come. Times: cellctl includes the per-station PnP and the checks;
OpenCV's exclude PnP.

Robots that are not the stated model (bench/handeye_robots.py): the real ETH ASL arm and a
virtual UR5e with kinematic error, by leave-one-out prediction, with a plain joint reprojection
refinement as a further peer. N-point: 9 marks (3x3 over 200x140 mm), camera 0.5 m above the
table tilted 1.5°, 0.1 px and 0.02 mm noise, against OpenCV's estimateAffine2D,
estimateAffinePartial2D and findHomography.

    .venv/bin/python bench/handeye.py [--quick] [--out bench/results/handeye.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # fair, quiet timing on a shared 2-core machine
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.handeye_common import BOARD, CAM, PEERS, cramer_rao, fmt_noise, median_method  # noqa: E402
from bench.handeye_real import default_vs_plain, evaluate, real_sets, section  # noqa: E402
from bench.handeye_robots import eth_real, eth_table, kinematic, kinematic_table  # noqa: E402
from calibration.camera_model import CameraModel  # noqa: E402
from calibration.detect import detect  # noqa: E402
from calibration.handeye import RobotNoise, calibrate_handeye, make_stations, transform_error_deg_mm
from calibration.npoint import fit_npoint  # noqa: E402
from calibration.observations import Detection  # noqa: E402
from calibration.synthetic import (  # noqa: E402
    simulate_handeye,
    simulate_npoint,
)
from drivers.sim.imaging import Imaging, PlanarObject, render  # noqa: E402

NOISES = [RobotNoise(0.02, 0.005), RobotNoise(0.05, 0.01), RobotNoise(0.1, 0.02)]
PIXEL_SIGMA_PX = 0.05


def run_one(setup: str, G: list[np.ndarray], dets: list[Detection], X_true: np.ndarray, noise: RobotNoise,
            Z_true: np.ndarray | None = None, default: bool = False) -> dict[str, Any]:
    """One data set: cellctl (stated-noise fit; with ``default`` also the default pipeline), every
    peer, and (``Z_true`` given: point-level data of the stated model) the Cramér-Rao bound."""
    t0 = time.perf_counter()
    res = calibrate_handeye(setup, G, dets, CAM, BOARD, noise, leave_one_out=False)
    t_cellctl = time.perf_counter() - t0
    row: dict[str, Any] = {"cellctl": transform_error_deg_mm(res.X, X_true), "time_cellctl": t_cellctl,
                           "sigma": (res.uncertainty_rot_deg, res.uncertainty_trans_mm)}
    if default:
        full = calibrate_handeye(setup, G, dets, CAM, BOARD, noise)
        row["default"] = transform_error_deg_mm(full.X, X_true)
        row["default_model"] = full.error_model["chosen"]
    stations, _ = make_stations(G, dets, CAM, BOARD)
    if Z_true is not None:
        row["crb"] = cramer_rao(setup, stations, CAM, PIXEL_SIGMA_PX, noise, X_true, Z_true)
    Gs, Cs = [s.G for s in stations], [s.C for s in stations]
    kept = {p["image"] for p in res.stations}
    Gk = [s.G for s in stations if s.image in kept]
    Ck = [s.C for s in stations if s.image in kept]
    row["dropped"] = len(stations) - len(Gk)
    for m in PEERS:
        try:
            row[m + "_kept"] = transform_error_deg_mm(PEERS[m](setup, Gk, Ck), X_true)
        except cv2.error:
            row[m + "_kept"] = (float("nan"), float("nan"))
    for m in PEERS:
        t0 = time.perf_counter()
        try:
            row[m] = transform_error_deg_mm(PEERS[m](setup, Gs, Cs), X_true)
        except cv2.error:  # e.g. ANDREFF's "determinant(R) is null": counted as a failure
            row[m] = (float("nan"), float("nan"))
        row["time_" + m] = time.perf_counter() - t0
    return row


def synthetic(quick: bool) -> list[dict[str, Any]]:
    rows = []
    seeds = range(8) if quick else range(12)
    n_list = [12] if quick else [8, 12, 20]
    for setup in ("eye-in-hand", "eye-to-hand"):
        for noise in NOISES:
            for n in n_list:
                for seed in seeds:
                    rng = np.random.default_rng(1000 * seed + n)
                    sim = simulate_handeye(setup, n, rng, camera=CAM, target=BOARD, robot_noise=noise,
                                           pixel_sigma_px=PIXEL_SIGMA_PX)
                    default = n == 12 and noise == NOISES[1] and seed < (3 if quick else 5)
                    r = run_one(setup, sim.G_recorded, sim.detections, sim.X_true, noise, sim.Z_true, default)
                    r.update(setup=setup, noise=noise, n=n, seed=seed, kind="points, 0.05 px")
                    rows.append(r)
        print(f"synthetic {setup} done", file=sys.stderr)
    return rows


def image_based(quick: bool) -> list[dict[str, Any]]:
    """Rendered 1920x1200 stations, detected by calibration.detect (chessboard)."""
    rows = []
    noise = RobotNoise(0.05, 0.01)
    for setup in ("eye-in-hand", "eye-to-hand"):
        for grey in (1.0, 3.0):
            for seed in range(1 if quick else 2):
                rng = np.random.default_rng(77 + seed + int(grey))
                sim = simulate_handeye(setup, 10, rng, camera=CAM, target=BOARD, robot_noise=noise, pixel_sigma_px=0.0)
                dets = []
                for k, C in enumerate(sim.C_true):
                    img = render(CAM, [PlanarObject(C, BOARD.reflectance)],
                                 Imaging(noise_sigma=grey, blur_sigma_px=0.7), rng)
                    dets.append(detect(img, BOARD, f"v{k:02d}.png"))
                G = [g for g, d in zip(sim.G_recorded, dets, strict=True) if d.found]
                dets = [d for d in dets if d.found]
                r = run_one(setup, G, dets, sim.X_true, noise)
                r.update(setup=setup, noise=noise, n=len(dets), seed=seed, kind=f"images, {grey:g} grey levels")
                rows.append(r)
    return rows
def summarise(rows: list[dict[str, Any]], keys: tuple[str, ...]) -> list[dict[str, Any]]:
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    out = []
    for key, rs in groups.items():
        s: dict[str, Any] = dict(zip(keys, key, strict=True))
        s["count"] = len(rs)
        for m in ("cellctl", *PEERS):
            s[m + "_rot"] = float(np.nanmedian([r[m][0] for r in rs]))
            s[m + "_trans"] = float(np.nanmedian([r[m][1] for r in rs]))
            s[m + "_fail"] = int(np.sum([np.isnan(r[m][1]) for r in rs]))
            s[m + "_time"] = float(np.median([r["time_" + m] for r in rs]))
        for m in PEERS:
            s[m + "_kept_rot"] = float(np.nanmedian([r[m + "_kept"][0] for r in rs]))
            s[m + "_kept_trans"] = float(np.nanmedian([r[m + "_kept"][1] for r in rs]))
        s["dropped"] = int(sum(r["dropped"] for r in rs))
        best_t = min(PEERS, key=lambda m: s[m + "_trans"])
        best_r = min(PEERS, key=lambda m: s[m + "_rot"])
        s["best_t"], s["best_r"] = best_t, best_r
        s["ratio_t"] = s["cellctl_trans"] / s[best_t + "_trans"]
        s["ratio_r"] = s["cellctl_rot"] / s[best_r + "_rot"]
        s["rms_err_rot"] = float(np.sqrt(np.mean([r["cellctl"][0] ** 2 for r in rs])))
        s["rms_err_trans"] = float(np.sqrt(np.mean([r["cellctl"][1] ** 2 for r in rs])))
        s["rms_sig_rot"] = float(np.sqrt(np.mean([r["sigma"][0] ** 2 for r in rs])))
        s["rms_sig_trans"] = float(np.sqrt(np.mean([r["sigma"][1] ** 2 for r in rs])))
        for m in ("cellctl", *PEERS):
            s[m + "_rms_rot"] = float(np.sqrt(np.nanmean([r[m][0] ** 2 for r in rs])))
            s[m + "_rms_trans"] = float(np.sqrt(np.nanmean([r[m][1] ** 2 for r in rs])))
        if all("crb" in r for r in rs):
            s["crb_rot"] = float(np.sqrt(np.mean([r["crb"][0] ** 2 for r in rs])))
            s["crb_trans"] = float(np.sqrt(np.mean([r["crb"][1] ** 2 for r in rs])))
        out.append(s)
    return out


def accuracy_table(summary: list[dict[str, Any]], label_keys: tuple[str, ...]) -> str:
    head = ("| " + " | ".join(label_keys) + " | sets | cellctl rot ° | best CV rot ° (method) | ratio | "
            "cellctl trans mm | best CV trans mm (method) | ratio | reported 1σ rot ° / trans mm | actual RMS "
            "rot ° / trans mm | actual/reported | cellctl ms | CV ms (best) |")
    lines = [head, "|" + "---|" * (len(label_keys) + 12)]
    for s in summary:
        labels = [(fmt_noise(s[k]) if k == "noise" else str(s[k])) for k in label_keys]
        q = (s["rms_err_trans"] / s["rms_sig_trans"], s["rms_err_rot"] / s["rms_sig_rot"])
        lines.append(
            "| " + " | ".join(labels) + f" | {s['count']} | {s['cellctl_rot']:.4f} | {s[s['best_r'] + '_rot']:.4f} "
            f"({s['best_r']}) | {s['ratio_r']:.2f} | {s['cellctl_trans']:.3f} | {s[s['best_t'] + '_trans']:.3f} "
            f"({s['best_t']}) | {s['ratio_t']:.2f} | {s['rms_sig_rot']:.4f} / {s['rms_sig_trans']:.3f} | "
            f"{s['rms_err_rot']:.4f} / {s['rms_err_trans']:.3f} | {q[1]:.2f} / {q[0]:.2f} | "
            f"{1e3 * s['cellctl_time']:.0f} | {1e3 * s[s['best_t'] + '_time']:.2f} |")
    return "\n".join(lines)


def kept_table(summary: list[dict[str, Any]]) -> str:
    lines = ["| setup | views dropped by cellctl's checks | cellctl | " + " | ".join(PEERS) + " |",
             "|---|---|---|" + "---|" * len(PEERS)]
    for s in summary:
        cells = [f"{s[m + '_kept_rot']:.4f}° / {s[m + '_kept_trans']:.3f} mm" for m in PEERS]
        lines.append(f"| {s['setup']} | {s['dropped']} | {s['cellctl_rot']:.4f}° / {s['cellctl_trans']:.3f} mm | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def method_table(summary: list[dict[str, Any]]) -> str:
    lines = ["| setup | " + " | ".join(["cellctl", *PEERS]) + " |",
             "|---|" + "---|" * (1 + len(PEERS))]
    for s in summary:
        cells = [f"{s[m + '_rot']:.4f}° / {s[m + '_trans']:.3f} mm" + (f" ({s[m + '_fail']} failed)"
                                                                       if s[m + "_fail"] else "")
                 for m in ("cellctl", *PEERS)]
        lines.append(f"| {s['setup']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# N-point
# ----------------------------------------------------------------------------------------------
def npoint_bench(quick: bool) -> str:
    cam = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958.3], [0, 1900.0, 601.2], [0, 0, 1]]),
                      np.zeros(5))
    seeds = range(10 if quick else 30)
    errs: dict[str, list[float]] = {k: [] for k in ("cellctl default", "cellctl affine", "cv2.estimateAffine2D",
                                                   "cv2.estimateAffinePartial2D", "cv2.findHomography")}
    chosen: dict[str, int] = {}
    sig: list[float] = []
    t_c, t_cv = [], []
    for s in seeds:
        uv, xy, truth = simulate_npoint(np.random.default_rng(500 + s), cam, tilt_deg=1.5, pixel_sigma_px=0.1,
                                        jog_sigma_mm=0.02)
        g = np.stack(np.meshgrid(np.linspace(uv[:, 0].min(), uv[:, 0].max(), 30),
                                 np.linspace(uv[:, 1].min(), uv[:, 1].max(), 30)), -1).reshape(-1, 2)
        tg = truth(g)

        def rms(pred: np.ndarray, tg: np.ndarray = tg) -> float:
            return float(np.sqrt(np.mean(np.sum((pred - tg) ** 2, axis=1))))

        t0 = time.perf_counter()
        res = fit_npoint(uv, xy)
        t_c.append(time.perf_counter() - t0)
        chosen[res.model] = chosen.get(res.model, 0) + 1
        errs["cellctl default"].append(rms(res.map(g)))
        sig.append(res.field_sigma_mm["rms"])
        errs["cellctl affine"].append(rms(fit_npoint(uv, xy, "affine").map(g)))
        t0 = time.perf_counter()
        A, _ = cv2.estimateAffine2D(uv, xy)
        t_cv.append(time.perf_counter() - t0)
        errs["cv2.estimateAffine2D"].append(rms(g @ A[:, :2].T + A[:, 2]))
        P, _ = cv2.estimateAffinePartial2D(uv, xy)
        errs["cv2.estimateAffinePartial2D"].append(rms(g @ P[:, :2].T + P[:, 2]))
        Hh, _ = cv2.findHomography(uv, xy, 0)
        q = np.column_stack([g, np.ones(len(g))]) @ Hh.T
        errs["cv2.findHomography"].append(rms(q[:, :2] / q[:, 2:]))
    lines = ["| method | field error RMS mm (median over seeds) | worst seed |", "|---|---|---|"]
    for k, v in errs.items():
        lines.append(f"| {k} | {np.median(v):.4f} | {np.max(v):.4f} |")
    med = float(np.median(errs["cellctl default"]))
    verdict = "met" if med <= 0.05 else "MISSED"
    lines.append("")
    lines.append(f"{len(list(seeds))} seeds; model chosen by LOO: {chosen}; cellctl's predicted field σ (RMS) "
                 f"median {np.median(sig):.4f} mm vs actual {med:.4f} mm; target ≤ 0.05 mm RMS: **{verdict}**. "
                 f"Time: cellctl fit with LOO model selection {1e3 * np.median(t_c):.1f} ms, "
                 f"cv2.estimateAffine2D {1e3 * np.median(t_cv):.2f} ms. OpenCV's estimateAffinePartial2D "
                 "cannot represent the image→robot reflection, hence its ~100 mm error.")
    return "\n".join(lines) + "\n"


def bound_table(overall: list[dict[str, Any]], per_group: list[dict[str, Any]]) -> str:
    """RMS errors against the Cramér-Rao bound, and the best ratio to OpenCV's median method any
    unbiased estimator could expect (bound / median method, RMS)."""
    L = ["| setup | noise | sets | cellctl RMS rot ° / trans mm | Cramér-Rao bound RMS rot ° / trans mm | cellctl / "
         "bound | OpenCV median method RMS rot ° / trans mm | attainable ratio (bound / median method) rot / trans |",
         "|---|---|---|---|---|---|---|---|"]
    for s in [*per_group, *overall]:
        mr = float(np.median([s[m + "_rms_rot"] for m in PEERS]))
        mt = float(np.median([s[m + "_rms_trans"] for m in PEERS]))
        L.append(f"| {s['setup']} | {fmt_noise(s['noise']) if 'noise' in s else 'all'} | {s['count']} | "
                 f"{s['cellctl_rms_rot']:.4f} / {s['cellctl_rms_trans']:.3f} | "
                 f"{s['crb_rot']:.4f} / {s['crb_trans']:.3f} | "
                 f"{s['cellctl_rms_rot'] / s['crb_rot']:.2f} / {s['cellctl_rms_trans'] / s['crb_trans']:.2f} | "
                 f"{mr:.4f} / {mt:.3f} | {s['crb_rot'] / mr:.2f} / {s['crb_trans'] / mt:.2f} |")
    return "\n".join(L)


def default_table(syn: list[dict[str, Any]]) -> str:
    """The default pipeline (leave-one-out, error model chosen) against the stated-noise fit."""
    L = ["| setup | sets | models chosen | default rot ° / trans mm (median) | stated-noise fit rot ° / trans mm | "
         "OpenCV median method rot ° / trans mm |", "|---|---|---|---|---|---|"]
    for setup in ("eye-in-hand", "eye-to-hand"):
        rs = [r for r in syn if r["setup"] == setup and "default" in r]
        if not rs:
            continue
        chosen: dict[str, int] = {}
        for r in rs:
            chosen[r["default_model"]] = chosen.get(r["default_model"], 0) + 1
        med = [float(np.median([np.nanmedian([r[m][j] for r in rs]) for m in PEERS])) for j in (0, 1)]
        L.append(f"| {setup} | {len(rs)} | {chosen} | {np.median([r['default'][0] for r in rs]):.4f} / "
                 f"{np.median([r['default'][1] for r in rs]):.3f} | {np.median([r['cellctl'][0] for r in rs]):.4f} / "
                 f"{np.median([r['cellctl'][1] for r in rs]):.3f} | {med[0]:.4f} / {med[1]:.3f} |")
    return "\n".join(L)


def target_table(overall: list[dict[str, Any]], per_group: list[dict[str, Any]], eth: dict[str, Any] | None,
                 kin: list[dict[str, Any]], real: list[dict[str, Any]] | None = None) -> str:
    """The 'against the targets' table: each target, what this run measured, met or missed."""
    rows: list[tuple[str, str, bool]] = []
    for o in overall:
        su = o["setup"]
        rt = o["cellctl_trans"] / median_method(o, "trans")
        rr = o["cellctl_rot"] / median_method(o, "rot")
        groups = [g for g in per_group if g["setup"] == su]
        wt = max(g["cellctl_trans"] / median_method(g, "trans") for g in groups)
        wr = max(g["cellctl_rot"] / median_method(g, "rot") for g in groups)
        rows += [
            (f"issue 15, {su}: translation ≤ 0.8x OpenCV's median method (medians over all {o['count']} sets)",
             f"{rt:.2f}", rt <= 0.8),
            (f"issue 15, {su}: rotation ≤ 1.0x OpenCV's median method (all {o['count']} sets)", f"{rr:.2f}", rr <= 1.0),
            (f"issue 15, {su}: the same at every noise level (worst level), translation / rotation",
             f"{wt:.2f} / {wr:.2f}", wt <= 0.8 and wr <= 1.0),
            (f"issue 5, {su}: translation ≤ 0.7x the best OpenCV method (chosen per row after seeing the truth)",
             f"{o['ratio_t']:.2f}", o["ratio_t"] <= 0.7),
            (f"issue 5, {su}: rotation ≤ 1.0x the best OpenCV method", f"{o['ratio_r']:.2f}", o["ratio_r"] <= 1.0),
        ]
    q = [g["rms_err_trans"] / g["rms_sig_trans"] for g in per_group] + \
        [g["rms_err_rot"] / g["rms_sig_rot"] for g in per_group]
    rows.append(("actual/reported error within 0.5–2 (every point-level row, rot and trans)",
                 f"{min(q):.2f}–{max(q):.2f}", min(q) >= 0.5 and max(q) <= 2.0))
    if kin:
        worst = max(r["loo"] / r["truth"] for r in kin)
        rows.append((f"kinematic-error arm: LOO ≤ 1.2x the true X, Z's own prediction (worst of {len(kin)} sets)",
                     f"{worst:.2f}", worst <= 1.2))
        wp = max(r["loo"] / r["plain"] for r in kin)
        n_ok = sum(r["loo"] <= r["plain"] for r in kin)
        rows.append((f"kinematic-error arm: default LOO ≤ the plain joint reprojection refinement's (worst of "
                     f"{len(kin)} sets; {n_ok} met)", f"{wp:.2f}", wp <= 1.0))
    if eth is not None:
        best = min(PEERS, key=lambda m: eth[m]["rms"])
        r = eth["cellctl_loo"]["rms"] / eth[best]["rms"]
        rows.append((f"ETH real arm: LOO target position no worse than the best OpenCV method ({best})",
                     f"{eth['cellctl_loo']['rms']:.2f} vs {eth[best]['rms']:.2f} mm ({r:.2f}x)", r <= 1.0))
        rp = eth["cellctl_loo"]["rms"] / eth["plain"]["mm"]
        rows.append(("ETH real arm: no worse than the plain joint reprojection refinement",
                     f"{eth['cellctl_loo']['rms']:.2f} vs {eth['plain']['mm']:.2f} mm ({rp:.2f}x)", rp <= 1.0))
    if real:
        worst, said = default_vs_plain(real)
        rows.append((f"issue 26, every real set: default LOO px ≤ the plain refinement's, intrinsics fixed (worst of "
                     f"{len(real)})", f"{worst:.2f} ({said})", worst <= 1.0))
    lines = ["| target | measured | result |", "|---|---|---|"]
    lines += [f"| {t} | {m} | **{'met' if ok else 'MISSED'}** |" for t, m, ok in rows]
    return "\n".join(lines)


def findings(overall: list[dict[str, Any]], per_group: list[dict[str, Any]], kin: list[dict[str, Any]]) -> str:
    """Why the issue-15 figures are what they are (numbers from this run)."""
    o = {s["setup"]: s for s in overall}
    lvl = [g["crb_trans"] / float(np.median([g[m + "_rms_trans"] for m in PEERS]))
           for g in per_group if g["setup"] == "eye-in-hand"]
    eih, eth = o["eye-in-hand"], o["eye-to-hand"]
    n_plain = sum(r["loo"] <= r["plain"] for r in kin)
    eth_lvl = [g["cellctl_rot"] / median_method(g, "rot") for g in per_group if g["setup"] == "eye-to-hand"]
    return "\n".join([
        "- **Both setups are at the Cramér-Rao bound.** The joint refinement is joint over X, Z and a pose "
        "correction per station, with the robot's rotation noise in the base frame exactly as the generator "
        "draws it; its RMS error is "
        f"{eih['cellctl_rms_rot'] / eih['crb_rot']:.2f}x / {eih['cellctl_rms_trans'] / eih['crb_trans']:.2f}x "
        "(eye-in-hand rot / trans) and "
        f"{eth['cellctl_rms_rot'] / eth['crb_rot']:.2f}x / {eth['cellctl_rms_trans'] / eth['crb_trans']:.2f}x "
        f"(eye-to-hand) of the bound (1σ sampling noise of an RMS over {eih['count']} sets of 3 dof: "
        f"±{100 / np.sqrt(6 * eih['count']):.0f} %). No weighting, initial estimate or robot-noise frame can do "
        "better on these data: the ratio to OpenCV is fixed by how close OpenCV's closed forms already come to "
        "the bound.",
        "- **Why eye-to-hand rotation looked behind (1.14x in the previous run):** that figure was the median over 9 "
        "sets pooled across three noise levels (the pooled median picks whichever set lands in the middle). With "
        f"{eth['count']} sets it is {eth['cellctl_rot'] / median_method(eth, 'rot'):.2f}x, and "
        f"{min(eth_lvl):.2f}-{max(eth_lvl):.2f}x per noise level. The rotation is limited by the robot's "
        "reported orientation, which every method uses alike "
        "(the camera sees the target's rotation far more precisely than the robot's 0.01°): the bound is only "
        f"{eth['crb_rot'] / float(np.median([eth[m + '_rms_rot'] for m in PEERS])):.2f}x of OpenCV's median method "
        "in rotation. calibrateRobotWorldHandEye (RW_SHAH, RW_LI) is among the peers; it does not come closer.",
        "- **Why eye-in-hand translation is near 0.8-0.9x:** OpenCV's translation step (linear least squares on the "
        "pairs, after the rotation) is already close to efficient when the robot's position noise dominates; the "
        "bound is "
        f"{eih['crb_trans'] / float(np.median([eih[m + '_rms_trans'] for m in PEERS])):.2f}x of the median method "
        f"(RMS, all sets; {min(lvl):.2f}-{max(lvl):.2f}x per noise level), so ≤ 0.8x at every noise level is out "
        "of reach for an unbiased estimator on these sets; pooled over all sets the median ratio meets it.",
        "- **What was wrong, and fixed:** the default pipeline chose its robot error model by leave-one-out "
        "prediction alone. On data that follow the stated model, held-out prediction is dominated by each held-out "
        "station's own robot noise, so a wrong model could win by a few per cent by chance and cost ten times the "
        "ML error (tests/calibration/test_handeye_error_model.py: an eye-to-hand set where the plain refinement "
        "won leave-one-out by 2.8 % with 0.049° error against the ML fit's 0.0074°). Now the stated-noise fit is "
        "kept while its reduced χ² is consistent with 1, and another model must win leave-one-out by 2 % and by "
        "two standard errors of the paired per-station gain. The default-pipeline table above shows the ML fit "
        "kept on every ideal set.",
        f"- **Plain joint reprojection refinement** as a peer on the kinematic arm: cellctl's default predicts at "
        f"least as well on {n_plain} of {len(kin)} sets; where the stated model's χ² is consistent with 1 the ML fit "
        "is kept and the plain refinement may be a few per cent better on leave-one-out (it fits the very "
        "quantity leave-one-out measures), at the cost of a worse X when the robot is as stated.",
    ])


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer seeds and station counts")
    ap.add_argument("--out", help="write the markdown here too")
    a = ap.parse_args()
    t0, c0 = time.time(), time.process_time()
    load0 = os.getloadavg()
    syn = synthetic(a.quick)
    print(f"synthetic done ({time.time() - t0:.0f} s)", file=sys.stderr)
    img = image_based(a.quick)
    print(f"image-based done ({time.time() - t0:.0f} s)", file=sys.stderr)
    eth = eth_real(a.quick)
    real = [evaluate(s) for s in real_sets(60 if a.quick else 40)]
    print(f"real done ({time.time() - t0:.0f} s)", file=sys.stderr)
    npt = npoint_bench(a.quick)
    kin = kinematic(a.quick)
    print(f"kinematic done ({time.time() - t0:.0f} s)", file=sys.stderr)

    overall = summarise(syn, ("setup",))
    per_group = summarise(syn, ("setup", "noise", "n"))
    cmd = ".venv/bin/python bench/handeye.py" + (" --quick" if a.quick else "") + (f" --out {a.out}" if a.out else "")
    parts = [
        "# Hand-eye benchmark (issues 5, 15): cellctl vs OpenCV calibrateHandEye (5 methods) and "
        "calibrateRobotWorldHandEye (2)\n",
        f"Command: `{cmd}`. Errors against truth: rotation (deg) and translation (mm) of T_tool_cam / T_base_cam; "
        "medians over seeds. 'best CV' = the OpenCV method (of 7) with the lowest median in that row; 'OpenCV's "
        "median method' = the median of the seven methods' medians. 'actual/reported' = RMS actual error / RMS "
        "reported 1σ (RMS over 3 dof), target within 0.5–2.\n",
        "## Targets\n",
        target_table(overall, per_group, eth, kin, real),
        "\n## Findings (issue 15)\n",
        findings(overall, per_group, kin),
        "\n## Point-level sets (pixel noise 0.05 px), per setup, robot noise and station count\n",
        accuracy_table(per_group, ("setup", "noise", "n")),
        "\n## Point-level sets, per setup (all noise levels and station counts)\n",
        accuracy_table(overall, ("setup",)),
        "\n### Median error of every method (rot / trans)\n",
        method_table(overall),
        "\n### Against the Cramér-Rao bound (RMS over the sets)\n",
        "The data follow the stated model exactly, so the inverse Fisher information at the truth bounds the "
        "expected error of any unbiased estimator.\n",
        bound_table(overall, per_group),
        "\n### The default pipeline (leave-one-out on, error model chosen) on some of the same sets "
        "(12 stations, 0.05 mm / 0.01°)\n",
        default_table(syn),
        "\n## Image-based sets (rendered, detected by calibration.detect; robot 0.05 mm / 0.01°, 10 stations)\n",
        accuracy_table(summarise(img, ("setup", "kind")), ("setup", "kind")),
        "\n### Median error of every method on the image-based sets (rot / trans)\n",
        method_table(summarise(img, ("setup",))),
        "\nOpenCV again on only the views cellctl kept (its checks drop mis-paired views):\n",
        kept_table(summarise(img, ("setup",))),
        "\n## Real data: ETH ASL robot arm + SR300 (no truth: leave-one-out prediction)\n",
        eth_table(eth),
        "\n" + section(real, cmd + " (its real-data section alone: .venv/bin/python -m bench.handeye_real)") + "\n",
        "\n## Kinematic-error robot (UR5e model, links 1 mm / joint zeros 0.05°, 12 stations, both setups, and "
        "eye-in-hand with a poorly calibrated camera)\n",
        "The recorded poses are the nominal arm's, the camera sees the perturbed arm's (millimetres, "
        "pose-dependent). cellctl fits the stated-noise model; when its residuals reject it (χ² outside the "
        "band of calibration.handeye.error_model) it fits the other error models and keeps the one that predicts "
        "held-out stations significantly best. 'plain refinement' = X, Z fitted to the pixels with the recorded "
        "poses taken as exact (bench/handeye_common.py, independent of cellctl's solver); 'truth' = the true X "
        "and Z predicting each station through its recorded pose.\n",
        kinematic_table(kin),
        "\n## N-point: 9 marks, camera tilted 1.5°, 0.1 px + 0.02 mm noise\n",
        npt,
        f"\nTotal run time {time.time() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU; load average "
        f"{load0[0]:.1f} at the start, {os.getloadavg()[0]:.1f} at the end (2-core machine shared with other jobs; "
        "OPENBLAS_NUM_THREADS=1). Times are indicative only; ratios are from the same run.\n",
    ]
    md = "\n".join(parts) + special_rows()
    print(md)
    if a.out:
        Path(a.out).write_text(md)


SPECIAL = Path(__file__).parent / "results" / "handeye_special.md"


def special_rows() -> str:
    """The beyond-6-DOF rows (4-DOF, tool centre, measured frame) from ``bench/handeye_special.py``'s
    latest results, so this table carries every hand-eye target; they are measured by that bench."""
    text = SPECIAL.read_text() if SPECIAL.exists() else ""
    head = "## Beyond 6-DOF AX=XB"
    if head not in text:
        return ""
    section = head + text.split(head, 1)[1].split("\n\n\n", 1)[0]
    return ("\n" + section.rstrip() + "\n\nThese rows are `bench/handeye_special.py`'s (its latest run, "
            "`bench/results/handeye_special.md`), copied here when this bench writes its table.\n")


if __name__ == "__main__":
    main()
