"""The splined stereographic model on the real sets (issue 39 item 2), beside fisheye4 in the same run.

Per set: the full solve's RMS (per corner and per coordinate, unweighted), the split-half projection
difference (even / odd views, over the cells the full set covered, as bench/intrinsics_real.py) and
the selection's 2-fold cross-validation (``cross_validate``), for ``splined`` and ``fisheye4``.
GoPro (35 views, below the splined model's 40-view rule) runs the splined model with the rule off
(``check=False``, the coarsest grid) to see whether a richer lens closes its halves' gap, and every
model with per-view outlier rejection (``drop_outliers``: views whose RMS is > 3x the median out).

``--sets gopro-views``: leave-one-view-out influence on GoPro and the halves without the influential views.

``--sets renders-warp [--seeds 300-319]``: what decides each held-out render set against mrcal (issue 39,
session 14). The renders of ``bench/intrinsics_real.py`` (``run_render``: the real-defects scene, 12 views of a
flat 9x6 board, opencv5 truth), our corners only; per seed: our corners' RMS error against the true
corners, and the projection difference to the true lens of cellctl's opencv5 solve flat, with the board
warp, and as ``--board-warp auto`` chooses (cross-validation), beside mrcal's opencv5 solve flat and
with its warp on the same corners.

``--sets fisheye-fair``: the fisheye RMS counted like with like. mrcal's published splined solve
(``tests/data/mrcal_samyang12mm_fisheye_corners/splined-0.cameramodel``, with its optimisation inputs)
has its residuals evaluated by mrcal itself (``bench/mrcal_peer.py`` ``residuals``) and counted four
ways (weighted by its ``2^-level`` weights or not, per coordinate or per corner); ours the same four
ways, for our splined solve as the product runs it (grid from the data, flat), with the board warp,
and in mrcal's configuration (its 30x20 grid over 170 deg, the warp, its level weights).

``--sets fisheye-gap``: where the splined RMS gap to mrcal comes from (session 15). mrcal's published solve
(its intrinsics, board poses and warp, decoded from the ``.cameramodel``'s optimisation inputs without mrcal)
is evaluated by *our* model and residuals, then our solver is started there: with no regularisation it can
only go down (the same model, data and weights), with our curvature term and with the prior it moves to
what those cost. The product's own solves (its grid and mrcal's, regularisers on and off) follow.

``--sets renders-bias [--seeds 303,306]``: our corners' error against the truth on the renders, split into
the part that repeats when the same pose is rendered again with new noise (bias) and the part that does not.

Run: ``.venv/bin/python bench/intrinsics_splined.py --sets fisheye,gopro,gopro-views`` (CPU-seconds per row are
printed; the machine's load decides the wall time).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.intrinsics_heldout import scene_camera_and_imaging  # noqa: E402
from bench.intrinsics_real import (  # noqa: E402
    HALVES,
    fisheye_set,
    image_set,
    mrcal_calibrate,
    mrcal_diff,
    peer,
    require_mrcal,
    write_cameramodel,
)
from calibration.detect import detect  # noqa: E402
from calibration.intrinsics import (  # noqa: E402
    calibrate,
    covered_points,
    cross_validate,
    projection_difference,
    select_by_cross_validation,
)
from calibration.intrinsics.splined_solver import calibrate_splined  # noqa: E402
from calibration.splined import SplineLayout  # noqa: E402
from calibration.synthetic import plan_views  # noqa: E402
from calibration.targets import Chessboard  # noqa: E402
from drivers.sim.imaging import PlanarObject, render  # noqa: E402


def weighted_rms_per_coordinate(full: Any, levels: list[np.ndarray]) -> float:
    """mrcal's figure on our residuals: RMS per coordinate of the residuals weighted ``2^-level``
    (mrgingham's decimation level of each corner), points beyond 5 robust sigma out (mrcal's outliers)."""
    used = [(v, lv) for v, lv in zip(full.views, levels, strict=True) if v.used]
    r = np.vstack([v.residuals_px * (2.0 ** -lv)[:, None] for v, lv in used])
    sig = 1.4826 * np.median(np.abs(r))
    keep = np.linalg.norm(r, axis=1) <= 5 * sig
    return float(np.sqrt(np.mean(r[keep] ** 2)))


def _row(name: str, model: str, dets: list[Any], board: Any, size: tuple[int, int], pts: np.ndarray,
         levels: list[np.ndarray] | None = None, **kw: Any) -> dict[str, Any]:
    t0 = time.process_time()
    if model == "splined*":
        full = calibrate_splined(dets, board, image_size=size, check=False)
        d = full.camera.dist
        lay = SplineLayout(int(d[0]), int(d[1]), float(d[2]))
        halves = [calibrate_splined(dets[h], board, image_size=size, layout=lay, check=False).camera for h in HALVES]
        cv = None
    else:
        full = calibrate(dets, board, model, image_size=size, **kw)
        cv = cross_validate(dets, board, model, 2, image_size=size, full=full, repeats=1, **kw)
    # the split-half over the set's covered cells; cross_validate's one partition (repeats=1) is the same
    # even/odd halves as mrcal's here (every view used), over the full solve's covered cells
    split = (projection_difference(halves[0], halves[1], pts)["rms_px"] if cv is None
             else cv["projection_difference_rms_px"])
    row = {"set": name, "model": model + (" drop_outliers" if kw.get("drop_outliers") else ""),
           "grid": "x".join(str(int(v)) for v in full.camera.dist[:2]) + f" fov {full.camera.dist[2]:.0f}"
           if full.camera.model == "splined" else "",
           "views": sum(v.used for v in full.views), "rms_corner_px": full.rms_px,
           "rms_coord_px": full.rms_px / np.sqrt(2), "split_px": split,
           "rms_coord_weighted_px": None if levels is None else weighted_rms_per_coordinate(full, levels),
           "cv_px": None if cv is None else cv["projection_difference_rms_px"],
           "expected_px": None if cv is None else cv["expected_from_uncertainty_px"],
           "reported_px": full.uncertainty["projection_rms_px"], "cpu_s": time.process_time() - t0}
    print(row, flush=True)
    return row


def gopro_views() -> None:
    """Leave-one-view-out influence on GoPro (division): how far the camera moves over the covered
    cells when one view is left out; then the halves (even / odd as numbered in the full set) without
    the views over 5x and over 3.5x the median influence."""
    s = image_set("udacity_gopro_wide_8x6", 8, 6)
    dets = s.corners["ours"]
    pts = covered_points(calibrate(dets, s.board, "opencv8", image_size=s.size))
    full = calibrate(dets, s.board, "division", image_size=s.size, jackknife=False)
    cells = covered_points(full)
    infl = np.array([projection_difference(calibrate(dets[:k] + dets[k + 1:], s.board, "division", image_size=s.size,
                                                     jackknife=False).camera, full.camera, cells)["rms_px"]
                     for k in range(len(dets))])
    med = float(np.median(infl))
    print({"median_influence_px": med, "top": [(dets[i].image, round(float(infl[i]), 3), round(float(infl[i]) / med, 1))
                                               for i in np.argsort(-infl)[:6]]}, flush=True)
    for factor in (5.0, 3.5):
        drop = {dets[i].image for i in range(len(dets)) if infl[i] > factor * med}
        for model in ("division", "fisheye4"):
            h = [calibrate([d for i, d in enumerate(dets) if i % 2 == p and d.image not in drop], s.board, model,
                           image_size=s.size, jackknife=False).camera for p in (0, 1)]
            print({"dropped": sorted(drop), "model": model,
                   "split_px": projection_difference(h[0], h[1], pts)["rms_px"]}, flush=True)


MRCAL_SPLINED = ROOT / "tests" / "data" / "mrcal_samyang12mm_fisheye_corners" / "splined-0.cameramodel"


def four_ways(residuals: list[np.ndarray], weights: list[np.ndarray]) -> dict[str, float]:
    """RMS of residuals (px) weighted (``weights`` times the error) or not, per coordinate or per corner."""
    r = np.vstack(residuals)
    rw = r * np.concatenate(weights)[:, None]
    return {"weighted_per_coordinate": float(np.sqrt(np.mean(rw**2))),
            "weighted_per_corner": float(np.sqrt(np.mean(np.sum(rw**2, axis=1)))),
            "unweighted_per_coordinate": float(np.sqrt(np.mean(r**2))),
            "unweighted_per_corner": float(np.sqrt(np.mean(np.sum(r**2, axis=1))))}


def fisheye_fair() -> None:
    s = fisheye_set()
    dets = s.corners["mrcal"]
    assert s.levels is not None
    lw = [2.0 ** -lv.astype(float) for lv in s.levels]
    ref = peer({"op": "residuals", "model": str(MRCAL_SPLINED)})
    print({"tool": "mrcal (published solve, its residuals)", **ref}, flush=True)
    configs: list[tuple[str, dict[str, Any]]] = [
        ("splined, grid from the data, flat (the product)", {}),
        ("splined, grid from the data, warp", {"board_warp": True}),
        ("splined, grid from the data, warp, level weights", {"board_warp": True, "point_weights": lw}),
        ("splined 30x20 fov 170, warp, level weights (mrcal's configuration)",
         {"board_warp": True, "layout": SplineLayout(30, 20, 170.0), "point_weights": lw}),
    ]
    for name, kw in configs:
        t0 = time.process_time()
        res = calibrate_splined(dets, s.board, image_size=s.size, **kw)
        used = [(v, w) for v, w in zip(res.views, lw, strict=True) if v.used]
        d = res.camera.dist
        print({"tool": "cellctl " + name, "grid": f"{int(d[0])}x{int(d[1])} fov {d[2]:.0f}",
               "warp_mm": None if res.board_warp is None else res.board_warp["height_mm"],
               **four_ways([v.residuals_px for v, _ in used], [w for _, w in used]),
               "cpu_s": round(time.process_time() - t0, 1)}, flush=True)


def mrcal_published_solve() -> dict[str, Any]:
    """mrcal's published splined solve (``MRCAL_SPLINED``): its lens model name, intrinsics and the optimisation
    inputs (numpy arrays), decoded from the file (a Python dict; ``optimization_inputs`` is base85 of a
    compressed ``.npz``) without mrcal."""
    import ast
    import base64
    import io

    text = MRCAL_SPLINED.read_text()
    d = ast.literal_eval("\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#")))
    oi = np.load(io.BytesIO(base64.b85decode(d["optimization_inputs"])), allow_pickle=False)
    return {"lensmodel": d["lensmodel"], "intrinsics": np.asarray(d["intrinsics"], dtype=np.float64),
            **{k: oi[k] for k in ("frames_rt_toref", "calobject_warp", "observations_board")}}


def fisheye_gap() -> None:
    """Our residuals at mrcal's published splined solution, then our solver started there (module docstring)."""
    from scipy.spatial.transform import Rotation

    from calibration.intrinsics import splined_problem as ss
    from calibration.intrinsics.views import collect_views, warp_basis

    s = fisheye_set()
    dets = s.corners["mrcal"]
    assert s.levels is not None
    lw = [2.0 ** -lv.astype(float) for lv in s.levels]
    m = mrcal_published_solve()
    assert m["lensmodel"] == "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=30_Ny=20_fov_x_deg=170"
    views, _, _ = collect_views(dets, s.board, s.size)
    X = np.vstack([v.X for v in views])
    prob = ss._Problem(SplineLayout(30, 20, 170.0), X, np.vstack([v.uv for v in views]),
                       np.concatenate([np.full(len(v.X), k) for k, v in enumerate(views)]), len(views),
                       warp_basis(s.board, X))
    i = m["intrinsics"]
    ctrl = i[4:].reshape(20, 30, 2)                      # mrcal: (Ny, Nx, xy); ours: all x, then all y
    x0 = np.concatenate([i[:4], ctrl[..., 0].ravel(), ctrl[..., 1].ravel()])
    fr = m["frames_rt_toref"][[v.index for v in views]]
    R0, t0 = Rotation.from_rotvec(fr[:, :3]).as_matrix(), fr[:, 3:].copy()
    w = np.concatenate([lw[v.index] for v in views])
    prob.sigma_px = 0.6
    prob.wp = np.asarray(m["calobject_warp"], dtype=np.float64).copy()
    prob.c0 = x0[4:].copy()                               # a prior, where on, pulls to mrcal's own solution

    def wrms(x: np.ndarray, R: np.ndarray, t: np.ndarray) -> float:
        return float(np.sqrt(np.mean((prob.obs_residuals(x, R, t).reshape(-1, 2) * w[:, None]) ** 2)))

    obs = m["observations_board"].reshape(-1, 3)
    print({"at mrcal's solution": "its points", "points": int(np.sum(obs[:, 2] > 0)), "ours": len(w),
           "weighted_per_coordinate (our model)": round(wrms(x0, R0, t0), 5)}, flush=True)

    def regularise(prior_px: float, share: float, gauge: float) -> None:
        """The solver's regularisation constants for this study (restored after it)."""
        for k, v in (("PRIOR_PX", prior_px), ("REG_SHARE", share), ("GAUGE_WEIGHT", gauge)):
            setattr(ss, k, v)

    saved = ss.PRIOR_PX, ss.REG_SHARE, ss.GAUGE_WEIGHT
    try:
        for name, prior, share in (("no regularisation", 1e9, 1e-12),
                                   ("our curvature term (REG_SHARE)", 1e9, ss.REG_SHARE)):
            regularise(prior, share, 1e-9)
            prob.wp = np.asarray(m["calobject_warp"], dtype=np.float64).copy()
            c0 = time.process_time()
            x, R, t, it = prob.solve(x0.copy(), R0, t0, w, 60)
            print({"our solver from mrcal's solution": name, "weighted_per_coordinate": round(wrms(x, R, t), 5),
                   "iterations": it, "cpu_s": round(time.process_time() - c0, 1)}, flush=True)
    finally:
        regularise(*saved)
    configs: list[tuple[str, dict[str, Any], tuple[float, float]]] = [
            ("product grid, no regularisation", {}, (1e9, 1e-12)),
            ("mrcal's grid (30x20, fov 170), no regularisation", {"layout": SplineLayout(30, 20, 170.0)}, (1e9, 1e-12)),
            ("mrcal's grid, curvature only", {"layout": SplineLayout(30, 20, 170.0)}, (1e9, saved[1]))]
    for name, kw, reg in configs:
        regularise(reg[0], reg[1], saved[2])
        try:
            c0 = time.process_time()
            res = calibrate_splined(dets, s.board, image_size=s.size, board_warp=True, point_weights=lw, **kw)
        finally:
            regularise(*saved)
        used = [(v, wv) for v, wv in zip(res.views, lw, strict=True) if v.used]
        print({"cellctl": name, **four_ways([v.residuals_px for v, _ in used], [wv for _, wv in used]),
               "cpu_s": round(time.process_time() - c0, 1)}, flush=True)


def renders_bias(seeds: list[int], n_views: int = 8, reps: int = 4) -> None:
    """Per render seed: our corners' error against the truth over ``reps`` renders of each of the first
    ``n_views`` poses (new noise each time): total, the repeating part (bias) and the rest (noise), px RMS
    per coordinate; and how much of the bias the corner's sub-pixel phase explains (first harmonic)."""
    board, size = Chessboard(9, 6, 20.0), (960, 720)
    tp = board.points()
    truth, imaging = scene_camera_and_imaging(size)
    for seed in seeds:
        poses = plan_views(truth, board, 12, np.random.default_rng(seed), fill=0.6, margin_px=6, whole_outline=True)
        means, noise2, phase = [], [], []
        for T in poses[:n_views]:
            true_uv = truth.project(tp.xyz_m @ T[:3, :3].T + T[:3, 3])
            errs = []
            for r in range(reps):
                g = render(truth, [PlanarObject(T, board.reflectance)], imaging, np.random.default_rng(10_000 + r),
                           supersample=32)
                d = detect(g, board, "v")
                if d.found:
                    e = np.full((len(tp.ids), 2), np.nan)
                    e[d.ids] = d.uv - true_uv[d.ids]
                    errs.append(e)
            if len(errs) < 2:
                continue
            E = np.array(errs)
            mu = np.nanmean(E, axis=0)
            means.append(mu)
            noise2.append(np.nanmean((E - mu) ** 2) * len(E) / (len(E) - 1) / len(E))   # noise left in the mean
            phase.append(true_uv)
        mu_all = np.concatenate(means)
        ok = np.all(np.isfinite(mu_all), axis=1)
        mu_all, uv = mu_all[ok], np.concatenate(phase)[ok]
        n2 = float(np.mean(noise2))
        bias = float(np.sqrt(max(np.mean(mu_all**2) - n2, 0.0)))
        left = []
        for a in (0, 1):
            A = np.column_stack([np.sin(2 * np.pi * uv[:, a]), np.cos(2 * np.pi * uv[:, a]), np.ones(len(uv))])
            beta, *_ = np.linalg.lstsq(A, mu_all[:, a], rcond=None)
            left.append(mu_all[:, a] - A @ beta)
        print({"seed": seed, "corners": int(ok.sum()), "renders per pose": reps,
               "noise_rms_px": round(float(np.sqrt(n2 * reps)), 5), "bias_rms_px": round(bias, 5),
               "bias_after_pixel_phase_px": round(float(np.sqrt(max(float(np.mean(np.square(left))) - n2, 0.0))), 5)},
              flush=True)


def renders_warp(seeds: list[int]) -> None:
    """Per render seed (as ``bench/intrinsics_real.run_render``): our corners' error against the truth
    and each solve's projection difference to the true lens over the covered cells (module docstring)."""
    require_mrcal()
    board, size = Chessboard(9, 6, 20.0), (960, 720)
    tp = board.points()
    for seed in seeds:
        truth, imaging = scene_camera_and_imaging(size)
        rng = np.random.default_rng(seed)
        poses = plan_views(truth, board, 12, rng, fill=0.6, margin_px=6, whole_outline=True)
        imgs = [render(truth, [PlanarObject(T, board.reflectance)], imaging, rng, supersample=32) for T in poses]
        found = [(T, d) for T, d in zip(poses, (detect(g, board, f"v{k:02d}") for k, g in enumerate(imgs)),
                                        strict=True) if d.found]
        dets = [d for _, d in found]
        err = np.vstack([d.uv - truth.project(tp.xyz_m[d.ids] @ T[:3, :3].T + T[:3, 3]) for T, d in found])
        pts = covered_points(calibrate(dets, board, "opencv5"))
        row: dict[str, Any] = {"seed": seed, "views": len(dets), "corner_rms_px": float(np.sqrt(np.mean(err**2)))}
        for name, warp in (("cellctl flat", False), ("cellctl warp", True)):
            cam = calibrate(dets, board, "opencv5", board_warp=warp).camera
            row[name] = projection_difference(cam, truth, pts)["rms_px"]
        chosen, info = select_by_cross_validation(dets, board, [("opencv5", False), ("opencv5", True)])
        row["cellctl auto"] = projection_difference(chosen.camera, truth, pts)["rms_px"]
        row["auto chose warp"] = info["chosen"]["board_warp"]
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            tf = write_cameramodel(truth, work / "truth.cameramodel")
            for name, warp in (("mrcal flat", False), ("mrcal warp", True)):
                mf, _ = mrcal_calibrate(dets, board, size, "LENSMODEL_OPENCV5", float(truth.K[0, 0]), work, warp)
                row[name] = mrcal_diff(mf, tf, pts)
        print(row, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="fisheye,gopro")
    ap.add_argument("--seeds", default="300-319", help="render seeds for --sets renders-warp: A-B or A,B,...")
    args = ap.parse_args()
    rows = []
    for name in args.sets.split(","):
        if name == "renders-warp":
            a, _, b = args.seeds.partition("-")
            renders_warp(list(range(int(a), int(b) + 1)) if b else [int(v) for v in args.seeds.split(",")])
            continue
        if name == "gopro-views":
            gopro_views()
            continue
        if name == "fisheye-fair":
            fisheye_fair()
            continue
        if name == "fisheye-gap":
            fisheye_gap()
            continue
        if name == "renders-bias":
            renders_bias([int(v) for v in args.seeds.split(",")] if "-" not in args.seeds else [303, 306])
            continue
        if name == "fisheye":
            s = fisheye_set()
            dets = s.corners["mrcal"]
            models: list[tuple[str, dict[str, Any]]] = [("fisheye4", {}), ("splined", {})]
        elif name == "gopro":
            s = image_set("udacity_gopro_wide_8x6", 8, 6)
            dets = s.corners["ours"]
            models = [("division", {}), ("splined*", {}), ("division", {"drop_outliers": True})]
        else:
            raise SystemExit(f"unknown set {name!r}; use fisheye, fisheye-fair, fisheye-gap, gopro, gopro-views, "
                           "renders-warp, renders-bias")
        pts = covered_points(calibrate(dets, s.board, "opencv8", image_size=s.size))
        for model, kw in models:
            try:
                rows.append(_row(s.name, model, dets, s.board, s.size, pts, s.levels, **kw))
            except Exception as exc:  # noqa: BLE001 - a failure is a row
                print({"set": s.name, "model": model, "failed": str(exc)}, flush=True)


if __name__ == "__main__":
    main()
