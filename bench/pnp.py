"""PnP benchmark (issue 16): RPnP (ours, Li, Xu, Xie 2012) against OpenCV's SQPnP, EPnP and IPPE.

Data with truth, generated point by point: a 1920x1200 camera (f = 1900 px, mild opencv5
distortion) sees N target points (N = 6, 12, 50) of a planar target (points on a 0.3 x 0.2 m plate)
or a 3D target (points in a 0.3 m cube) at 0.5, 1 and 2 m, tilted up to ~35°, with Gaussian pixel
noise of 0.1, 0.5 and 1 px; several seeds. Every solver gets the same undistorted normalized
points; "raw" is the solver alone, "+LM" its candidates refined on pixels through the camera model
(``calibration.pose.methods``, the refinement every cellctl pose uses). Errors against truth:
rotation angle (deg) and translation distance (mm) of ``T_cam_target``. Times are per call on the
same points, median; RPnP is Python/numpy, OpenCV's solvers are C++.

The seed paper's experiment (the space-robot paper quotes RPnP at 1.35 mm / 0.40° within 2 m):
its camera and target are not given in full, so we state ours: a 2448x2048 camera with f = 3500 px
(a 12 mm lens on 3.45 µm pixels), a 3D target of 20 marks in 0.4 x 0.4 x 0.2 m, 0.5-2 m away,
0.2 px detection noise; mean and maximum error of RPnP+LM over the draws.

    .venv/bin/python bench/pnp.py [--quick] [--out bench/results/pnp.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # fair, quiet timing on a shared 2-core machine
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.camera_model import CameraModel  # noqa: E402
from calibration.pose import (  # noqa: E402
    PoseEstimationError,
    candidates,
    estimate_pose_by,
)

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 961.0], [0, 1900.0, 598.0], [0, 0, 1]]),
                  np.array([-0.08, 0.05, 0.0002, -0.0001, 0.0]))
SEED_CAM = CameraModel("opencv5", 2448, 2048, np.array([[3500.0, 0, 1224.0], [0, 3500.0, 1024.0], [0, 0, 1]]),
                       np.zeros(5))
SOLVERS = ("rpnp", "sqpnp", "epnp", "ippe")
PAPER_MM, PAPER_DEG = 1.35, 0.40


def _draw(rng: np.random.Generator, cam: CameraModel, n: int, planar: bool, distance_m: float,
          size_m: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray] | None:
    X = rng.uniform(-0.5, 0.5, (n, 3)) * np.array(size_m)
    if planar:
        X[:, 2] = 0.0
    tilt = np.radians(rng.uniform(0.0, 35.0))
    phi = rng.uniform(0, 2 * np.pi)
    R = (Rotation.from_rotvec([0, 0, rng.uniform(-np.pi, np.pi)])
         * Rotation.from_rotvec(tilt * np.array([np.cos(phi), np.sin(phi), 0.0]))).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [rng.uniform(-0.05, 0.05) * distance_m, rng.uniform(-0.04, 0.04) * distance_m, distance_m]
    uv = cam.project(X @ R.T + T[:3, 3])
    if not (np.all(np.isfinite(uv)) and np.all((uv > 5) & (uv < np.array(cam.size) - 6))):
        return None
    return X, T


def _errors(T_est: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(T_est[:3, :3].T @ T[:3, :3]).as_rotvec()))
    return float(ang), float(1e3 * np.linalg.norm(T_est[:3, 3] - T[:3, 3]))


def _time_ms(fn: Any, reps: int = 3) -> float:
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - t0) / reps * 1e3


def run_grid(seeds: list[int], trials: int) -> dict[tuple[Any, ...], dict[str, list[tuple[float, float]]]]:
    out: dict[tuple[Any, ...], dict[str, list[tuple[float, float]]]] = defaultdict(lambda: defaultdict(list))
    for planar in (True, False):
        for dist in (0.5, 1.0, 2.0):
            for n in (6, 12, 50):
                for sigma in (0.1, 0.5, 1.0):
                    key = ("planar" if planar else "3D", dist, n, sigma)
                    for seed in seeds:
                        rng = np.random.default_rng([seed, int(planar), int(dist * 10), n, int(sigma * 10)])
                        done = 0
                        while done < trials:
                            drawn = _draw(rng, CAM, n, planar, dist, (0.3, 0.2 if planar else 0.3, 0.3))
                            if drawn is None:
                                continue
                            X, T = drawn
                            uv = CAM.project(X @ T[:3, :3].T + T[:3, 3]) + rng.normal(0, sigma, (n, 2))
                            done += 1
                            for m in SOLVERS:
                                if m == "ippe" and not planar:
                                    continue
                                for raw in (True, False):
                                    name = f"{m}{'' if raw else '+LM'}"
                                    try:
                                        res = estimate_pose_by(CAM, X, uv, m, raw=raw)
                                        out[key][name].append(_errors(res.T_cam_target, T))
                                    except PoseEstimationError:
                                        out[key][name].append((180.0, 1e6))
    return out


def timings() -> dict[str, dict[str, float]]:
    """Median per-call time (ms) of each solver alone and with the refinement, 3D and planar, 12 points."""
    rng = np.random.default_rng(99)
    res: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for planar in (True, False):
        for _ in range(30):
            drawn = _draw(rng, CAM, 12, planar, 1.0, (0.3, 0.3, 0.3))
            if drawn is None:
                continue
            X, T = drawn
            uv = CAM.project(X @ T[:3, :3].T + T[:3, 3]) + rng.normal(0, 0.5, (12, 2))
            xy = CAM.undistort_normalized(CAM.pixels_to_normalized(uv))
            for m in SOLVERS:
                if m == "ippe" and not planar:
                    continue
                res[m]["raw"].append(_time_ms(lambda m=m, X=X, xy=xy, p=planar: candidates(m, X, xy, p)))
                res[m]["+LM"].append(_time_ms(lambda m=m, X=X, uv=uv: estimate_pose_by(CAM, X, uv, m)))
    return {m: {k: float(np.median(v)) for k, v in d.items()} for m, d in res.items()}


def seed_experiment(seeds: list[int], trials: int, sigma_px: float = 0.2) -> dict[str, Any]:
    errs: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for seed in seeds:
        rng = np.random.default_rng([seed, 2012, int(sigma_px * 10)])
        done = 0
        while done < trials:
            drawn = _draw(rng, SEED_CAM, 20, False, rng.uniform(0.5, 2.0), (0.4, 0.4, 0.2))
            if drawn is None:
                continue
            X, T = drawn
            uv = SEED_CAM.project(X @ T[:3, :3].T + T[:3, 3]) + rng.normal(0, sigma_px, (20, 2))
            done += 1
            for m, raw in (("rpnp", True), ("rpnp", False), ("sqpnp", False)):
                res = estimate_pose_by(SEED_CAM, X, uv, m, raw=raw)
                errs[f"{m}{'' if raw else '+LM'}"].append(_errors(res.T_cam_target, T))
    return {k: np.array(v) for k, v in errs.items()}


def _med(v: list[tuple[float, float]], k: int) -> float:
    return float(np.median(np.array(v)[:, k]))


def report(grid: dict[tuple[Any, ...], dict[str, list[tuple[float, float]]]], times: dict[str, dict[str, float]],
           seed: dict[str, Any], seeds: list[int], trials: int, seed_1px: dict[str, Any] | None = None) -> str:
    lines = ["# PnP benchmark (issue 16): RPnP (ours) vs OpenCV's SQPnP, EPnP, IPPE", "",
             (__doc__ or "").split("\n\n")[1].replace("\n", " "), "",
             f"Seeds {seeds}, {trials} draws per seed and row. A failure is an error > 5° (or no pose).", ""]
    ratios_t, ratios_r = [], []
    for d in grid.values():
        ratios_t.append(_med(d["rpnp+LM"], 1) / max(_med(d["sqpnp+LM"], 1), 1e-12))
        ratios_r.append(_med(d["rpnp+LM"], 0) / max(_med(d["sqpnp+LM"], 0), 1e-12))
    worst_t, worst_r = max(ratios_t), max(ratios_r)
    ok = worst_t <= 1.1 and worst_r <= 1.1
    s_rp = seed["rpnp+LM"]
    mean_mm, mean_deg = float(np.mean(s_rp[:, 1])), float(np.mean(s_rp[:, 0]))
    seed_ok = mean_mm * 5 <= PAPER_MM and mean_deg * 5 <= PAPER_DEG
    lines += ["## Targets", "",
              f"- RPnP+LM / SQPnP+LM, median error per row, worst row: translation {worst_t:.3f}, rotation "
              f"{worst_r:.3f} (target ≤ 1.1): **{'met' if ok else 'MISSED'}**; median over rows "
              f"{np.median(ratios_t):.3f} / {np.median(ratios_r):.3f}.",
              f"- seed experiment (3D target, 0.5-2 m): RPnP+LM mean error {mean_mm:.3f} mm / {mean_deg:.4f}° "
              f"next to the paper's {PAPER_MM} mm / {PAPER_DEG}°: {PAPER_MM / mean_mm:.1f}x / "
              f"{PAPER_DEG / mean_deg:.1f}x better (target ≥ 5x): **{'met' if seed_ok else 'MISSED'}**.", ""]
    lines += ["## Seed paper's experiment (3D target of 20 marks, 0.5-2 m, 0.2 px, f = 3500 px)", "",
              "| method | draws | mean mm | median mm | max mm | mean ° | median ° | max ° |",
              "|---|---|---|---|---|---|---|---|"]
    for m, e in seed.items():
        lines.append(f"| {m} | {len(e)} | {np.mean(e[:, 1]):.3f} | {np.median(e[:, 1]):.3f} | {np.max(e[:, 1]):.3f} | "
                     f"{np.mean(e[:, 0]):.4f} | {np.median(e[:, 0]):.4f} | {np.max(e[:, 0]):.4f} |")
    lines.append(f"| paper (RPnP, its own set-up) | | {PAPER_MM} | | | {PAPER_DEG} | | |")
    if seed_1px is not None:
        for m, e in seed_1px.items():
            lines.append(f"| {m}, 1 px noise (context) | {len(e)} | {np.mean(e[:, 1]):.3f} | "
                         f"{np.median(e[:, 1]):.3f} | {np.max(e[:, 1]):.3f} | {np.mean(e[:, 0]):.4f} | "
                         f"{np.median(e[:, 0]):.4f} | "
                         f"{np.max(e[:, 0]):.4f} |")
        lines.append("\nThe paper does not state its camera, target or noise; the target is judged at our stated "
                     "0.2 px. At 1 px (a poor detector) the errors grow about fivefold, as the rows above show.")
    lines += ["", "## Summary over all rows, per target type", "",
              "| target | method | median rot ° | median trans mm | 95 % trans mm | failures |",
              "|---|---|---|---|---|---|"]
    for typ in ("planar", "3D"):
        pooled: dict[str, list[tuple[float, float]]] = defaultdict(list)
        for key, d in grid.items():
            if key[0] == typ:
                for m, v in d.items():
                    pooled[m] += v
        for m, v in pooled.items():
            a = np.array(v)
            lines.append(f"| {typ} | {m} | {np.median(a[:, 0]):.4f} | {np.median(a[:, 1]):.3f} | "
                         f"{np.percentile(a[:, 1], 95):.2f} | {np.mean(a[:, 0] > 5.0) * 100:.1f} % |")
    lines += ["", "## Time per call (12 points, median ms; OpenCV's solvers are C++, RPnP Python)", "",
              "| method | raw ms | +LM ms |", "|---|---|---|"]
    for m, tm in times.items():
        lines.append(f"| {m} | {tm['raw']:.3f} | {tm['+LM']:.2f} |")
    ratio = times["rpnp"]["raw"] / times["sqpnp"]["raw"]
    lines.append(f"\nRPnP raw / SQPnP raw time: {ratio:.1f}x; with the refinement (which dominates) "
                 f"{times['rpnp']['+LM'] / times['sqpnp']['+LM']:.2f}x.")
    lines += ["", "## Per row: median translation error (mm) and rotation error (°)", "",
              "| target | dist m | n | noise px | rpnp | rpnp+LM | sqpnp | sqpnp+LM | epnp | epnp+LM | ippe+LM | "
              "ratio rpnp+LM/sqpnp+LM (t / r) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, d in grid.items():
        def cell(m: str, d: dict[str, list[tuple[float, float]]] = d) -> str:
            return f"{_med(d[m], 1):.2f} / {_med(d[m], 0):.3f}" if m in d else "—"
        rt = _med(d["rpnp+LM"], 1) / max(_med(d["sqpnp+LM"], 1), 1e-12)
        rr = _med(d["rpnp+LM"], 0) / max(_med(d["sqpnp+LM"], 0), 1e-12)
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {key[3]} | {cell('rpnp')} | {cell('rpnp+LM')} | "
                     f"{cell('sqpnp')} | {cell('sqpnp+LM')} | {cell('epnp')} | {cell('epnp+LM')} | "
                     f"{cell('ippe+LM')} | {rt:.3f} / {rr:.3f} |")
    lines += ["", "    .venv/bin/python bench/pnp.py"]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed, few draws (a smoke run)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "pnp.md"))
    args = ap.parse_args()
    seeds, trials = ([0], 3) if args.quick else ([0, 1, 2], 6)
    t0 = time.perf_counter()
    grid = run_grid(seeds, trials)
    times = timings()
    seed = seed_experiment(seeds if not args.quick else [0], 10 if args.quick else 60)
    seed_1px = seed_experiment(seeds if not args.quick else [0], 10 if args.quick else 60, sigma_px=1.0)
    text = report(grid, times, seed, seeds, trials, seed_1px)
    Path(args.out).write_text(text)
    print(text)
    print(f"bench/pnp.py: {time.perf_counter() - t0:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
