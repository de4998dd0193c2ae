"""Detection benchmark (issue 3): our detectors against OpenCV's on rendered images with known truth.

Images are 1280x960, rendered by ``drivers.sim.imaging.renderer`` (geometric error < 0.013 px) from a seed:
three camera models (opencv5, opencv8 rational, division), tilts 0-50°, the target filling
10-80% of the image, noise 0.5-3 grey levels, blur 0.3-1.2 px, uneven light. Truth is
``camera.project(transform_points(T_cam_target, target.points().xyz_m))``; for circle marks the
true imaged-ellipse centre adds ``calibration.detect.conic.circle_centre_bias_px``.

OpenCV's results carry no target-frame ids; they are scored under the grid symmetry (half or
quarter turn) that fits the truth best, which can only favour OpenCV.

    .venv/bin/python bench/detection.py [--quick] [--seed N] [--out bench/results/detection.md]

Prints the markdown tables and writes them to ``--out``.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.camera_model import CameraModel  # noqa: E402
from calibration.detect import (  # noqa: E402
    circle_centre_bias_px,
    detect,
)
from calibration.detect.circle_grid import blob_detector  # noqa: E402
from calibration.detect.circle_plate import conic_centres, detect_circle_plate, fit_ellipses_direct  # noqa: E402
from calibration.geometry import make_transform, rotvec_to_matrix, transform_points  # noqa: E402
from calibration.targets import Charuco, Chessboard, CircleGrid, CirclePlate, PlanarTarget  # noqa: E402
from drivers.sim.imaging import Imaging, PlanarObject, render  # noqa: E402

FloatArray = NDArray[np.float64]
T = TypeVar("T")
W, H = 1280, 960


def cameras() -> list[CameraModel]:
    return [
        CameraModel("opencv5", W, H, np.array([[1400.0, 0, 643.2], [0, 1400.0, 478.9], [0, 0, 1]]),
                    np.array([-0.15, 0.12, 0.0004, -0.0002, 0.0])),
        CameraModel("opencv8", W, H, np.array([[1050.0, 0, 636.5], [0, 1052.0, 483.1], [0, 0, 1]]),
                    np.array([0.2, -0.1, 0.0, 0.0, 0.0, 0.45, -0.05, 0.05])),
        CameraModel("division", W, H, np.array([[1800.0, 0, 640.7], [0, 1800.0, 480.2], [0, 0, 1]]),
                    np.array([-0.25])),
    ]


@dataclass
class Scene:
    camera: CameraModel
    T: FloatArray
    imaging: Imaging
    tilt_deg: float


DEFECTS = {"on": False}


def make_scene(target: PlanarTarget, rng: np.random.Generator, cams: list[CameraModel],
               tilt_deg: float | None = None, noise: float | None = None, blur: float | None = None) -> Scene:
    cam = cams[int(rng.integers(len(cams)))]
    tilt = float(rng.uniform(0, 50)) if tilt_deg is None else tilt_deg
    x0, y0, x1, y1 = target.extent_m()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]])
    fill = float(rng.uniform(0.10, 0.80))
    z = cam.fx * np.sqrt((x1 - x0) * (y1 - y0) * np.cos(np.deg2rad(tilt)) / (fill * W * H))
    d = np.deg2rad(rng.uniform(0, 360))
    R = rotvec_to_matrix([0, 0, rng.uniform(0, 2 * np.pi)]) @ rotvec_to_matrix(
        np.deg2rad(tilt) * np.array([np.cos(d), np.sin(d), 0.0]))
    T = np.eye(4)
    for _ in range(60):
        sx, sy = rng.uniform(-0.35, 0.35, 2) * np.array([W, H]) / cam.fx * z
        T = make_transform(R, np.array([sx, sy, z]) - R @ centre)
        uv = cam.project(transform_points(T, corners))
        if np.all(np.isfinite(uv)) and np.all((uv > 8) & (uv < np.array([W - 9, H - 9]))):
            break
        z *= 1.02
    imaging = Imaging(noise_sigma=float(rng.choice([0.5, 1.0, 2.0, 3.0])) if noise is None else noise,
                      blur_sigma_px=float(rng.choice([0.3, 0.7, 1.2])) if blur is None else blur,
                      light_gradient=float(rng.uniform(0.0, 0.5)))
    if DEFECTS["on"]:  # the virtual camera's defects on top (issue 15): the same seeds, harder images
        imaging = replace(imaging, vignetting=0.25, gamma=1.1, jpeg_quality=int(rng.choice([85, 92, 97])),
                          gain_dn_per_e=0.5, read_noise_dn=1.0, focus_distance_m=float(z) * 0.9,
                          defocus_sigma_px_per_diopter=0.6)
    return Scene(cam, T, imaging, tilt)


def grid_symmetries(rows: int, cols: int) -> list[Callable[[FloatArray], FloatArray]]:
    """Orderings of a (rows*cols, 2) grid result that a symmetric pattern cannot tell apart."""
    flips = [(1, 1), (-1, -1), (-1, 1), (1, -1)]

    def make(fr: int, fc: int, transpose: bool) -> Callable[[FloatArray], FloatArray]:
        def f(a: FloatArray) -> FloatArray:
            g = a.reshape(rows, cols, 2)
            if transpose:
                g = g.transpose(1, 0, 2)
            return g[::fr, ::fc].reshape(-1, 2)
        return f

    return [make(fr, fc, t) for t in ((False, True) if rows == cols else (False,)) for fr, fc in flips]


def best_error(pred: FloatArray, truth: FloatArray, rows: int, cols: int) -> FloatArray:
    errs = [np.hypot(*(s(pred) - truth).T) for s in grid_symmetries(rows, cols)]
    return min(errs, key=lambda e: float(np.mean(e**2)))


@dataclass
class Stat:
    name: str
    n: int = 0
    found: int = 0
    wrong: int = 0
    errors: list[float] = field(default_factory=list)
    times: list[float] = field(default_factory=list)
    note: str = ""
    sigmas: list[float] = field(default_factory=list)
    """Our detections' own per-point 1-sigma (px per axis, ``Detection.uv_sigma_px``)."""

    def add(self, found: bool, err: FloatArray | None, dt: float, wrong: bool = False,
            sigma: FloatArray | None = None) -> None:
        self.n += 1
        self.times.append(dt)
        if found and err is not None:
            self.found += 1
            self.errors.extend(err.tolist())
            self.wrong += int(wrong)
            if sigma is not None:
                self.sigmas.extend(np.asarray(sigma, dtype=np.float64).tolist())

    def merge(self, other: Stat) -> None:
        self.n += other.n
        self.found += other.found
        self.wrong += other.wrong
        self.errors += other.errors
        self.times += other.times
        self.sigmas += other.sigmas

    def row(self) -> str:
        e = np.asarray(self.errors)
        rms = f"{np.sqrt(np.mean(e**2)):.4f}" if e.size else "-"
        mx = f"{e.max():.4f}" if e.size else "-"
        t = f"{1e3 * np.median(self.times):.0f}" if self.times else "-"
        sg = np.asarray(self.sigmas)
        # errors are 2-D lengths, sigmas per axis: compare RMS length with sqrt(2) x RMS sigma
        honesty = (f"{np.sqrt(np.mean(e**2)) / (np.sqrt(2) * np.sqrt(np.mean(sg**2))):.2f}"
                   if sg.size and e.size and np.all(np.isfinite(sg)) else "-")
        return (f"| {self.name} | {self.n} | {100 * self.found / max(self.n, 1):.1f}% | {self.wrong} | "
                f"{rms} | {mx} | {honesty} | {t} | {self.note} |")


HEADER = ("| detector | images | detected | wrong order | RMS err (px) | max err (px) | err / own σ | median ms/image "
          "| note |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |")


def timed(fn: Callable[..., T], *args: object) -> tuple[T, float]:
    t0 = time.perf_counter()
    r = fn(*args)
    return r, time.perf_counter() - t0


def _cv_chess_sb(img: NDArray[np.uint8], size: tuple[int, int], flags: int) -> FloatArray | None:
    ok, c = cv2.findChessboardCornersSB(img, size, flags=flags)
    return np.asarray(c, dtype=np.float64).reshape(-1, 2) if ok else None


def _cv_chess_classic(img: NDArray[np.uint8], size: tuple[int, int]) -> FloatArray | None:
    ok, c = cv2.findChessboardCorners(img, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    c = cv2.cornerSubPix(img, c, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001))
    return np.asarray(c, dtype=np.float64).reshape(-1, 2)


def _cv_circles(img: NDArray[np.uint8], cols: int, rows: int, asym: bool) -> FloatArray | None:
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if asym else cv2.CALIB_CB_SYMMETRIC_GRID
    ok, c = cv2.findCirclesGrid(img, (cols, rows), flags=flags, blobDetector=blob_detector(W * H, cols * rows))
    return np.asarray(c, dtype=np.float64).reshape(-1, 2) if ok else None


def bench_chessboard(n: int, seed: int, cams: list[CameraModel], fixed: bool) -> list[Stat]:
    board = Chessboard(9, 6, 25.0)
    tag = " (noise 2, blur 0.7)" if fixed else " (mixed)"
    ours = Stat("ours: SB + own saddle refinement" + tag)
    sb, sb_acc = Stat("OpenCV findChessboardCornersSB" + tag), Stat("OpenCV findChessboardCornersSB ACCURACY" + tag)
    classic = Stat("OpenCV findChessboardCorners + cornerSubPix 11x11" + tag)
    for i in range(n):
        rng = np.random.default_rng([seed, 1, i, int(fixed)])
        sc = make_scene(board, rng, cams, noise=2.0 if fixed else None, blur=0.7 if fixed else None)
        img = render(sc.camera, [PlanarObject(sc.T, board.reflectance)], sc.imaging, rng)
        truth = sc.camera.project(transform_points(sc.T, board.points().xyz_m))
        det, dt = timed(detect, img, board)
        if det.found:
            e = np.hypot(*(det.uv - truth[det.ids]).T)
            ours.add(True, e, dt, wrong=bool(e.max() > 1.0), sigma=det.uv_sigma_px)
        else:
            ours.add(False, None, dt)
        runs = ((sb, timed(_cv_chess_sb, img, (9, 6), 0)),
                (sb_acc, timed(_cv_chess_sb, img, (9, 6), cv2.CALIB_CB_ACCURACY)),
                (classic, timed(_cv_chess_classic, img, (9, 6))))
        for stat, (r, dt) in runs:
            e = None if r is None else best_error(r, truth, 6, 9)
            stat.add(r is not None, e, dt, wrong=e is not None and bool(e.max() > 1.0))
    return [ours, sb, sb_acc, classic]


@dataclass
class PlateExtra:
    ell_err: list[float] = field(default_factory=list)
    ell_err_conic: list[float] = field(default_factory=list)
    corr_by_model: dict[str, list[float]] = field(default_factory=dict)
    ell_by_model: dict[str, list[float]] = field(default_factory=dict)
    bias_err: list[float] = field(default_factory=list)
    true_bias: list[float] = field(default_factory=list)
    raw_err: list[float] = field(default_factory=list)
    detect_only_times: list[float] = field(default_factory=list)


def exact_ellipse_centres(camera: CameraModel, T: FloatArray, centres_m: FloatArray, radius_m: float,
                          n: int = 256) -> FloatArray:
    """True imaged-ellipse centres: each mark's rim projected through the full lens model (n points)
    and fitted with the same direct ellipse fit. Unlike ``calibration.detect.conic`` (lens distortion applied
    to the centres only) this keeps distortion's effect on the mark's shape."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = centres_m[:, None, :] + radius_m * np.stack([np.cos(t), np.sin(t), 0 * t], axis=1)[None]
    uv = camera.project(transform_points(T, rim.reshape(-1, 3))).reshape(len(centres_m), n, 2)
    q, _ = fit_ellipses_direct(uv[..., 0], uv[..., 1], np.ones((len(centres_m), n)))
    return conic_centres(q)


def bench_plate(n: int, seed: int, cams: list[CameraModel], tilt: float | None, label: str
                ) -> tuple[list[Stat], PlateExtra]:
    plate = CirclePlate(7, 7, 12.5, 6.25)
    ours = Stat(f"ours: circle_plate, bias-corrected uv {label}")
    raw = Stat(f"ours: raw ellipse centres vs image of centre {label}")
    cv = Stat(f"OpenCV findCirclesGrid 7x7 {label}")
    extra = PlateExtra()
    xyz = plate.points().xyz_m
    for i in range(n):
        rng = np.random.default_rng([seed, 2, i, int(tilt or 0)])
        sc = make_scene(plate, rng, cams, tilt_deg=tilt)
        img = render(sc.camera, [PlanarObject(sc.T, plate.reflectance)], sc.imaging, rng)
        truth = sc.camera.project(transform_points(sc.T, xyz))
        bias_conic = circle_centre_bias_px(sc.camera, sc.T, xyz, plate.radius_m)
        bias = exact_ellipse_centres(sc.camera, sc.T, xyz, plate.radius_m) - truth
        det, dt = timed(detect, img, plate)
        _, dt_core = timed(detect_circle_plate, img, plate)
        extra.detect_only_times.append(dt_core)
        if det.found:
            ids = det.ids
            e = np.hypot(*(det.uv - truth[ids]).T)
            ell = det.uv_ellipse
            assert ell is not None
            ours.add(True, e, dt, wrong=bool(e.max() > 1.0), sigma=det.uv_sigma_px)
            raw.add(True, np.hypot(*(ell - truth[ids]).T), dt)
            e_ell = np.hypot(*(ell - (truth + bias)[ids]).T)
            extra.ell_err.extend(e_ell.tolist())
            extra.ell_err_conic.extend(np.hypot(*(ell - (truth + bias_conic)[ids]).T).tolist())
            extra.corr_by_model.setdefault(sc.camera.model, []).extend(e.tolist())
            extra.ell_by_model.setdefault(sc.camera.model, []).extend(e_ell.tolist())
            extra.bias_err.extend(np.hypot(*((ell - det.uv) - bias[ids]).T).tolist())
            extra.true_bias.extend(np.hypot(*bias.T).tolist())
        else:
            ours.add(False, None, dt)
            raw.add(False, None, dt)
            print(f"  plate image {i} not found: {det.reason}", file=sys.stderr)
        r, dt = timed(_cv_circles, img, 7, 7, False)
        e = None if r is None else best_error(r, truth, 7, 7)
        cv.add(r is not None, e, dt, wrong=e is not None and bool(e.max() > 1.0))
    return [ours, raw, cv], extra


def bench_grid(n: int, seed: int, cams: list[CameraModel], grid: CircleGrid) -> list[Stat]:
    kind = "asymmetric" if grid.asymmetric else "symmetric"
    ours = Stat(f"ours: circle_grid {kind} {grid.cols}x{grid.rows} (OpenCV + bias correction)")
    cv = Stat(f"OpenCV findCirclesGrid {kind} {grid.cols}x{grid.rows}")
    xyz = grid.points().xyz_m
    for i in range(n):
        rng = np.random.default_rng([seed, 3, i, int(grid.asymmetric)])
        sc = make_scene(grid, rng, cams)
        img = render(sc.camera, [PlanarObject(sc.T, grid.reflectance)], sc.imaging, rng)
        truth = sc.camera.project(transform_points(sc.T, xyz))
        det, dt = timed(detect, img, grid)
        if det.found:
            e = np.hypot(*(det.uv - truth[det.ids]).T)
            if not grid.asymmetric:  # a symmetric grid is ours up to its half turn (ids i <-> N-1-i)
                e_turn = np.hypot(*(det.uv - truth[len(truth) - 1 - det.ids]).T)
                e = min(e, e_turn, key=lambda x: float(np.mean(x**2)))
            ours.add(True, e, dt, wrong=bool(e.max() > 1.0), sigma=det.uv_sigma_px)
        else:
            ours.add(False, None, dt)
        r, dt = timed(_cv_circles, img, grid.cols, grid.rows, grid.asymmetric)
        if r is not None:
            rr = np.asarray(r)
            e = best_error(rr, truth, grid.rows, grid.cols) if not grid.asymmetric else \
                min(np.hypot(*(rr - truth).T), np.hypot(*(rr[::-1] - truth).T), key=lambda x: float(np.mean(x**2)))
            cv.add(True, e, dt, wrong=bool(e.max() > 1.0))
        else:
            cv.add(False, None, dt)
    return [ours, cv]


def bench_charuco(n: int, seed: int, cams: list[CameraModel]) -> list[Stat]:
    board = Charuco(8, 6, 25.0, 18.0, "DICT_5X5_100")
    ours = Stat("ours = OpenCV CharucoDetector (8x6, DICT_5X5_100)")
    xyz = board.points().xyz_m
    for i in range(n):
        rng = np.random.default_rng([seed, 4, i])
        sc = make_scene(board, rng, cams)
        img = render(sc.camera, [PlanarObject(sc.T, board.reflectance)], sc.imaging, rng)
        truth = sc.camera.project(transform_points(sc.T, xyz))
        det, dt = timed(detect, img, board)
        if det.found:
            e = np.hypot(*(det.uv - truth[det.ids]).T)
            ours.add(True, e, dt, wrong=bool(e.max() > 1.0), sigma=det.uv_sigma_px)
        else:
            ours.add(False, None, dt)
    ours.note = "partial boards count as found (>= 4 corners)"
    return [ours]


def rms(v: list[float]) -> float:
    a = np.asarray(v)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--quick", action="store_true", help="a quarter of the images (a smoke run)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--seeds", type=int, default=1, help="repeat every set with seeds seed, seed+1, ...")
    ap.add_argument("--defects", action="store_true",
                    help="add the virtual camera's defects (vignetting, shot + read noise, JPEG, gamma, defocus)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "detection.md"))
    args = ap.parse_args(argv)
    DEFECTS["on"] = args.defects
    seeds = [args.seed + k for k in range(args.seeds)]

    def stats_over_seeds(fn: Callable[..., list[Stat]], *a: object) -> list[Stat]:
        out = fn(*a[:1], seeds[0], *a[1:])
        for sd in seeds[1:]:
            for s0, s1 in zip(out, fn(*a[:1], sd, *a[1:]), strict=True):
                s0.merge(s1)
        return out

    def plate_over_seeds(*a: object) -> tuple[list[Stat], PlateExtra]:
        out, ex = bench_plate(a[0], seeds[0], *a[1:])  # type: ignore[arg-type]
        for sd in seeds[1:]:
            o2, e2 = bench_plate(a[0], sd, *a[1:])  # type: ignore[arg-type]
            for s0, s1 in zip(out, o2, strict=True):
                s0.merge(s1)
            for f in ("ell_err", "ell_err_conic", "bias_err", "true_bias", "raw_err", "detect_only_times"):
                getattr(ex, f).extend(getattr(e2, f))
            for f in ("corr_by_model", "ell_by_model"):
                for m, v in getattr(e2, f).items():
                    getattr(ex, f).setdefault(m, []).extend(v)
        return out, ex

    k = 4 if args.quick else 1
    cams = cameras()
    counts = {"chess_fixed": 24 // k, "chess_mixed": 24 // k, "plate_mixed": 60 // k, "plate_45": 24 // k,
              "plate_45_pinhole": 12 // k, "grid_sym": 24 // k, "grid_asym": 20 // k, "charuco": 24 // k}
    t_start = time.perf_counter()
    sections: list[str] = []
    total = sum(counts.values()) * len(seeds)
    print(f"rendering and detecting {total} images of {W}x{H} (seed {args.seed})...", file=sys.stderr)

    chess = stats_over_seeds(bench_chessboard, counts["chess_fixed"], cams, True)
    chess += stats_over_seeds(bench_chessboard, counts["chess_mixed"], cams, False)
    print("  chessboard done", file=sys.stderr)
    plate, pextra = plate_over_seeds(counts["plate_mixed"], cams, None, "(mixed, tilt 0-50°)")
    plate45, p45 = plate_over_seeds(counts["plate_45"], cams, 45.0, "(tilt 45°)")
    pinhole = [CameraModel("opencv5", W, H, np.array([[1600.0, 0, 640], [0, 1600.0, 480], [0, 0, 1]]))]
    plate45p, p45p = plate_over_seeds(counts["plate_45_pinhole"], pinhole, 45.0,
                                      "(tilt 45°, distortion-free camera)")
    print("  circle plate done", file=sys.stderr)
    grids = stats_over_seeds(bench_grid, counts["grid_sym"], cams, CircleGrid(7, 6, 20.0, 10.0))
    grids += stats_over_seeds(bench_grid, counts["grid_asym"], cams, CircleGrid(4, 11, 15.0, 10.0, asymmetric=True))
    print("  circle grids done", file=sys.stderr)
    charuco = stats_over_seeds(bench_charuco, counts["charuco"], cams)
    elapsed = time.perf_counter() - t_start

    def table(title: str, stats: list[Stat]) -> str:
        return f"### {title}\n\n{HEADER}\n" + "\n".join(s.row() for s in stats) + "\n"

    sections.append(table("Chessboard 9x6", chess))
    sections.append(table("Circle plate 7x7 (HALCON-style; OpenCV has no plate detector, findCirclesGrid "
                          "is the nearest peer)", plate + plate45 + plate45p))
    sections.append(table("Circle grids", grids))
    sections.append(table("ChArUco", charuco))

    # ---- targets of issue 3
    fixed = chess[:4]
    ours_fixed = rms(fixed[0].errors)
    best_cv = min((rms(s.errors), s.name) for s in fixed[1:] if s.errors)
    no_saddle = rms(fixed[2].errors)
    all_plates = plate + plate45 + plate45p
    found_rate = sum(s.found for s in all_plates[::3]) / max(sum(s.n for s in all_plates[::3]), 1)
    wrong = sum(s.wrong for s in all_plates[::3])
    ell_all = rms(pextra.ell_err + p45.ell_err + p45p.ell_err)
    ell_conic = rms(pextra.ell_err_conic + p45.ell_err_conic + p45p.ell_err_conic)
    by_model: dict[str, list[float]] = {}
    for ex in (pextra, p45, p45p):
        for m, v in ex.ell_by_model.items():
            by_model.setdefault(m, []).extend(v)
    ell_models = ", ".join(f"{m} {rms(v):.4f}" for m, v in sorted(by_model.items()))
    corr45_models = ", ".join(f"{m} {rms(v):.4f}" for m, v in sorted(p45.corr_by_model.items()))
    corr45 = rms(plate45[0].errors)
    corr45p = rms(plate45p[0].errors)
    bias45 = rms(p45.bias_err)
    bias45p = rms(p45p.bias_err)
    true45 = rms(p45.true_bias)
    t_ours = float(np.median(pextra.detect_only_times + p45.detect_only_times + p45p.detect_only_times))
    t_ours_q = float(np.median(plate[0].times + plate45[0].times + plate45p[0].times))
    t_cv = float(np.median(plate[2].times + plate45[2].times + plate45p[2].times))

    def verdict(ok: bool) -> str:
        return "met" if ok else "**missed**"

    lines = [
        "### Issue 3 targets",
        "",
        "| target | measured | verdict |",
        "| --- | --- | --- |",
        f"| chessboard RMS at noise 2, blur 0.7 no worse than OpenCV's best | ours {ours_fixed:.4f} px vs "
        f"{best_cv[1].replace(' (noise 2, blur 0.7)', '')} {best_cv[0]:.4f} px (ratio {ours_fixed / best_cv[0]:.2f}); "
        f"OpenCV SB with ACCURACY {no_saddle:.4f} px | "
        f"{verdict(ours_fixed <= best_cv[0] * 1.0001)} |",
        f"| circle_plate mark RMS <= 0.02 px without perspective bias (raw ellipse centre vs true "
        f"imaged-ellipse centre = direct fit to the projected rim, all plate images) | {ell_all:.4f} px "
        f"(by camera: {ell_models}); against calibration.detect.conic's first-order bias instead: {ell_conic:.4f} px "
        f"| {verdict(ell_all <= 0.02)} |",
        f"| bias-corrected centres within 0.01 px of truth at 45° tilt | RMS(uv - truth) {corr45:.4f} px with "
        f"lens distortion (by camera: {corr45_models}), {corr45p:.4f} px distortion-free; "
        f"RMS(estimated - true bias) {bias45:.4f} / "
        f"{bias45p:.4f} px (true bias RMS {true45:.4f} px) | {verdict(max(corr45, corr45p) <= 0.01)} |",
        f"| circle_plate detection rate 100%, zero wrongly ordered | {100 * found_rate:.1f}%, {wrong} wrongly "
        f"ordered | {verdict(found_rate == 1.0 and wrong == 0)} |",
        f"| time per image within 2x of findCirclesGrid | plate detector {1e3 * t_ours:.0f} ms "
        f"({1e3 * t_ours_q:.0f} ms with quality figures) vs findCirclesGrid {1e3 * t_cv:.0f} ms: ratio "
        f"{t_ours / t_cv:.2f} ({t_ours_q / t_cv:.2f}) | {verdict(t_ours <= 2 * t_cv)} |",
        "",
    ]
    notes = [
        "Notes:",
        "- The true imaged-ellipse centre is a direct ellipse fit to the mark's rim projected through the full "
        "lens model. `calibration.detect.conic.circle_centre_bias_px` applies lens distortion to the centres only "
        "(first order); against it our raw centres seem "
        f"{ell_conic:.4f} px off: that difference is distortion bending the marks, not detection error.",
        "- OpenCV's rows carry the perspective bias of circle centres (no correction); our circle_grid rows are "
        "the same OpenCV centres corrected with the plate detector's bias model.",
        "- Chessboard: `findChessboardCornersSB` with `CALIB_CB_ACCURACY` is no more accurate after our saddle "
        "refinement than without, at four times the time, so we run it without; our time is dominated by SB.",
    ]
    if max(corr45, corr45p) > 0.01:
        notes.append(
            "- Missed: bias-corrected centres at 45° stay within 0.01 px on the distortion-free camera and on the "
            "moderate lenses, not on the strongly distorted rational (opencv8) lens. Without a calibrated camera "
            "the correction models the plate-to-image mapping around each mark from its neighbours (homography + "
            "quadratic); that lens bends the mapping more than a quadratic over a pitch or two follows. A solver "
            "that knows the lens can recompute the bias from `uv_ellipse` with the lens model inside its loop "
            "(projecting each mark's rim, as this benchmark's truth does).")
    lines += notes + [""]
    sections.insert(0, "\n".join(lines))
    flags = (", --quick" if args.quick else "") + (", --defects" if args.defects else "")
    head = (f"## Detection benchmark (bench/detection.py, seeds {seeds[0]}-{seeds[-1]}{flags})\n\n"
            f"{total} rendered {W}x{H} images; cameras opencv5 (f 1400), opencv8 rational (f 1050), division "
            f"(f 1800, kappa -0.25); tilt 0-50° (or fixed), target filling 10-80% of the image, noise 0.5-3 "
            f"grey levels, blur 0.3-1.2 px, light gradient 0-50%"
            + ("; with --defects also vignetting 25%, shot noise (0.5 DN/e-) + read noise 1 DN, JPEG 85-97, "
               "gamma 1.1, defocus away from a focus plane 10% in front of the target" if args.defects else "")
            + ". 'err / own σ' = RMS error length over sqrt(2) x RMS of our detections' own per-point σ "
            "(Detection.uv_sigma_px; 1 = honest). Errors against the rendered truth; OpenCV "
            f"scored under its best grid symmetry. Wrong order: a found result with any point > 1 px off "
            f"(its errors still count in RMS/max). "
            f"Times are medians on a shared 2-core machine ({platform.processor() or platform.machine()}, "
            f"OpenCV {cv2.__version__}), single-threaded Python; whole run {elapsed:.0f} s.\n")
    text = head + "\n" + "\n".join(sections)
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
