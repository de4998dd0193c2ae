"""Real-data hand-eye table (issue 26 item 6): leave-one-out prediction of the held-out station on
each real set in the repository, scored the way the mapping predicts (pixels).

For every method, each station in turn is left out, the method is fitted on the others, and the
held-out station's target points are predicted from its recorded robot pose through the camera
the method ends with (the jointly refined one when it refines the intrinsics) and its systematic
robot correction when it has one — what ``cellctl map`` does with he.json. The figure is the pixel
RMS over every held-out point (and the RMS target-position miss, mm).

Methods: cellctl's default (``error_model="auto"``), each selectable error model forced
(``calibration.handeye.ERROR_MODELS``), the plain joint reprojection refinement with the
intrinsics fixed (bench/handeye_common.py, written independently of cellctl's solver) and
OpenCV's five ``cv2.calibrateHandEye`` closed forms (Z the mean of the per-station target poses).

Real sets: the ETH ASL robot arm + SR300 (tests/data/handeye_ethz_robot_arm_sr300, SOURCE.txt).

Run: ``.venv/bin/python -m bench.handeye_real [--step 60] [--update bench/results/handeye.md]``;
prints the section, and with ``--update`` replaces it in the file (between its two markers), so the
table can be refreshed without the whole hand-eye bench (bench/handeye.py writes the same section).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Final

import numpy as np

from bench.handeye_common import loo_px, peer_fit, plain_refinement
from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3, invert, make_transform, quaternion_to_matrix
from calibration.handeye import (
    ERROR_MODELS,
    OPENCV_METHODS,
    RobotNoise,
    Station,
    calibrate_handeye,
    find_outlier_stations,
    make_stations,
)
from calibration.observations import Detection
from calibration.targets import Chessboard, Target

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "handeye_ethz_robot_arm_sr300"


@dataclass
class RealSet:
    """A real hand-eye set as the solvers take it: recorded robot poses, detections, camera, target."""

    name: str
    setup: str
    G: list[np.ndarray]
    detections: list[Detection]
    camera: CameraModel
    target: Target
    noise: RobotNoise
    sigma_px: float | None
    note: str


def _slerp_pose(t: np.ndarray, rows: np.ndarray) -> list[np.ndarray]:
    from scipy.spatial.transform import Rotation, Slerp

    ts = rows[:, 0]
    sl = Slerp(ts, Rotation.from_quat(rows[:, 4:8]))
    pos = np.column_stack([np.interp(t, ts, rows[:, k]) for k in (1, 2, 3)])
    R = sl(t).as_matrix()
    return [make_transform(R[k], pos[k]) for k in range(len(t))]


def eth_set(step: int = 60) -> RealSet | None:
    """ETH ASL robot arm + SR300: every ``step``-th camera sample, the robot pose SLERPed at camera
    time - 0.02 s (the published offset); each measured camera pose turned into detections of a
    6x6 grid (pitch 40 mm) through the SR300 IR model (the set has poses, no images)."""
    robot_f = DATA / "robot_arm_complete_bag_color_and_ir_base_link_sr300_hinge.csv"
    cam_f = DATA / "robot_arm_complete_bag_color_and_ir_target_ir.csv"
    if not (robot_f.is_file() and cam_f.is_file()):
        return None
    rob = np.loadtxt(robot_f, delimiter=",")
    cam = np.loadtxt(cam_f, delimiter=",")
    dt = -0.02  # the published time offset (robot_t = cam_t + dt), SOURCE.txt
    sel = cam[::step]
    sel = sel[(sel[:, 0] + dt > rob[0, 0]) & (sel[:, 0] + dt < rob[-1, 0])]
    G = _slerp_pose(sel[:, 0] + dt, rob)
    sr300 = CameraModel("opencv5", 640, 480, np.array([[471.845, 0, 316.850], [0, 471.686, 237.389], [0, 0, 1]]),
                        np.array([-0.15024, -0.00326, -0.00126, -0.00042, 0.0]))
    grid = Chessboard(6, 6, 40.0)
    tp = grid.points()
    dets = []
    for k, r in enumerate(sel):
        C = invert(make_transform(quaternion_to_matrix(r[4:8]), r[1:4]))
        uv = sr300.project(tp.xyz_m @ C[:3, :3].T + C[:3, 3])
        dets.append(Detection(f"t{k:03d}", bool(np.all(np.isfinite(uv))), tp.ids.copy(), uv, image_size=(640, 480)))
    return RealSet("ETH ASL arm + SR300", "eye-in-hand", G, dets, sr300, grid, RobotNoise(0.5, 0.1), 0.3,
                   f"every {step}th camera sample of 1703, robot pose SLERPed at camera time - 0.02 s; "
                   "pixel σ 0.3 px and robot σ 0.5 mm / 0.1° stated")


def real_sets(step: int = 60) -> list[RealSet]:
    """Every real hand-eye set in the repository."""
    return [s for s in (eth_set(step),) if s is not None]


def _cellctl(rs: RealSet, model: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    res = calibrate_handeye(rs.setup, rs.G, rs.detections, rs.camera, rs.target, rs.noise, sigma_px=rs.sigma_px,
                            leave_one_out=True, error_model=model)
    loo = res.loo
    return {"px": float(loo["prediction_rms_px"]), "mm": float(loo["position_mm"]["rms"]),
            "chosen": res.error_model.get("chosen"), "stations": [p["image"] for p in res.stations],
            "problems": [p.code for p in res.problems], "intrinsics_refined": res.intrinsics_refined,
            "cpu_s": time.perf_counter() - t0}


def evaluate(rs: RealSet) -> dict[str, Any]:
    """Leave-one-out px / mm of every method on ``rs`` (module docstring)."""
    rows: dict[str, dict[str, Any]] = {"default": _cellctl(rs, "auto")}
    for m in ERROR_MODELS:
        rows[m] = _cellctl(rs, m)
    used = set(rows["default"]["stations"])
    stations, _ = make_stations(rs.G, rs.detections, rs.camera, rs.target)
    st: list[Station] = [s for s in stations if s.image in used]  # the stations cellctl kept, for every peer
    fits: dict[str, Callable[..., Any]] = {"plain refinement (intrinsics fixed)":
                                           partial(plain_refinement, rs.setup, camera=rs.camera)}
    for m in OPENCV_METHODS:
        fits[f"OpenCV {m}"] = peer_fit(rs.setup, m)
    for name, fit in fits.items():
        t0 = time.perf_counter()
        rows[name] = {**loo_px(rs.setup, st, rs.camera, fit), "cpu_s": time.perf_counter() - t0}
    return {"set": rs, "n": len(st), "n_total": len(rs.detections), "rows": rows, "outlier": outlier_check(rs)}


def outlier_check(rs: RealSet, k: int = 5, seed: int = 1) -> dict[str, Any]:
    """Station ``k``'s recorded pose moved 12 mm / 1.9° (random directions) — the real UR5e outlier of
    issue 26: does the screw-invariant check (``find_outlier_stations``) flag it, and the consensus
    check of the solution (``calibration.handeye.consensus``)? Without leave-one-out (flags only),
    and on the clean set for the false flags."""
    rng = np.random.default_rng(seed)
    axis, d = rng.normal(size=3), rng.normal(size=3)
    G = [g.copy() for g in rs.G]
    G[k] = make_transform(exp_so3(np.radians(1.9) * axis / np.linalg.norm(axis)) @ G[k][:3, :3],
                          G[k][:3, 3] + 0.012 * d / np.linalg.norm(d))
    out: dict[str, Any] = {}
    for name, poses in (("clean", rs.G), ("moved", G)):
        stations, _ = make_stations(poses, rs.detections, rs.camera, rs.target)
        screw, _ = find_outlier_stations(rs.setup, [s.G for s in stations], [s.C for s in stations])
        res = calibrate_handeye(rs.setup, poses, rs.detections, rs.camera, rs.target, rs.noise, sigma_px=rs.sigma_px,
                                leave_one_out=False, error_model="fixed_prior")
        px = np.array([p["consensus_rms_px"] for p in res.stations])
        names = [p["image"] for p in res.stations]
        moved = rs.detections[k].image
        out[name] = {"screw": [stations[i].image for i in screw],
                     "consensus": [p["image"] for p in res.stations if p["off_consensus"]],
                     "ratio": float(px[names.index(moved)] / np.median(px)) if moved in names else float("nan"),
                     "max_other": float(max(r for n, r in zip(names, px / np.median(px), strict=True) if n != moved))}
    out["image"] = rs.detections[k].image
    return out


def table(results: list[dict[str, Any]]) -> str:
    """The markdown table (one block per set) and the verdict default ≤ plain refinement."""
    out = ["| set | method | LOO prediction RMS px | LOO target position RMS mm | ratio to plain refinement (px) |",
           "|---|---|---|---|---|"]
    verdicts = []
    for r in results:
        rows = r["rows"]
        plain = rows["plain refinement (intrinsics fixed)"]["px"]
        for name, v in rows.items():
            label = name
            if name == "default":
                label = f"**cellctl default** (chose {v['chosen']})"
            elif name in ERROR_MODELS:
                label = f"cellctl, error model {name}"
            out.append(f"| {r['set'].name} | {label} | {v['px']:.2f} | {v['mm']:.2f} | {v['px'] / plain:.2f} |")
        d = rows["default"]["px"]
        o = r.get("outlier")
        if o is not None:
            m, c = o["moved"], o["clean"]
            verdicts.append(
                f"{r['set'].name}, station {o['image']} moved 12 mm / 1.9°: the screw-invariant check flags "
                f"{m['screw'] or 'nothing'}, the consensus check {m['consensus'] or 'nothing'} (its miss "
                f"{m['ratio']:.1f}x the median station's, the others ≤ {m['max_other']:.1f}x; threshold 5x). "
                "On the clean set: screw "
                f"{c['screw'] or 'nothing'}, consensus {c['consensus'] or 'nothing'} (largest {c['max_other']:.1f}x).")
        verdicts.append(f"{r['set'].name}: {r['n']} of {r['n_total']} stations ({r['set'].note}); default "
                        f"{d:.2f} px vs plain refinement {plain:.2f} px = {d / plain:.2f}x: "
                        f"**{'met' if d <= plain else 'MISSED'}** (target ≤ 1).")
    return "\n".join(out) + "\n\n" + "\n".join(f"- {v}" for v in verdicts) + "\n"


BEGIN: Final = "<!-- real-data table: bench/handeye_real.py -->"
END: Final = "<!-- end of the real-data table -->"


def section(results: list[dict[str, Any]], cmd: str) -> str:
    """The markdown section of bench/results/handeye.md, between its markers."""
    return "\n".join([
        BEGIN,
        "## Real data: leave-one-out prediction of the held-out station, every method (issue 26 item 6)\n",
        f"Command: `{cmd}`. Each station in turn is left out, the method is fitted on the others, and the held-out "
        "station's target points are predicted from its recorded robot pose the way `cellctl map` maps: through "
        "the camera the method ends with and its systematic robot correction when it has one. Figure: pixel RMS "
        "over every held-out point (and the RMS target-position miss). 'plain refinement' = X, Z fitted to the "
        "pixels with the recorded robot poses exact and the intrinsics fixed (bench/handeye_common.py); OpenCV = "
        "`cv2.calibrateHandEye`'s five closed forms, Z the mean of the per-station target poses.\n",
        table(results),
        findings(results),
        END,
    ])


def findings(results: list[dict[str, Any]]) -> str:
    """What the table says, in words (issue 26)."""
    out = ["Findings (issue 26):\n"]
    for r in results:
        rows = r["rows"]
        best_cv = min((k for k in rows if k.startswith("OpenCV")), key=lambda k: rows[k]["px"])
        out.append(
            f"- {r['set'].name}: the default chose {rows['default']['chosen']} at {rows['default']['px']:.2f} px; "
            f"without the systematic position correction the same data predict at "
            f"{rows['plain_reprojection']['px']:.2f} px (plain_reprojection) / {rows['fixed_prior']['px']:.2f} px "
            f"(fixed_prior): the correction is what wins. Best OpenCV closed form: {best_cv} "
            f"{rows[best_cv]['px']:.2f} px. The intrinsics were held fixed here (the SR300's published "
            f"calibration, no verdict), so the mapping's camera is the given one.")
    out.append(
        "- Scored as the mapping predicts: since issue 26 every mapping (`POST /map`, the pick poses, the PLC "
        "answers through `cellctl.mapping.active_mapping`, and `cellctl map`) goes through the camera he.json was "
        "solved with, not the active camera calibration or `--camera`. On the virtual cell with a camera file "
        "1 % off in fx and the intrinsics refined jointly, the stale camera maps the image edge 1.7–2.3 mm away "
        "from the truth, the hand-eye's own camera < 0.3 mm (tests/cellctl/test_handeye_own_camera.py).")
    out.append(
        "- Only one real hand-eye set is in the repository (the UR5e ChArUco and the second arm of issue 26 are "
        "not), so the 'every real set' target is checked on one set.")
    return "\n".join(out) + "\n"


def default_vs_plain(results: list[dict[str, Any]]) -> tuple[float, str]:
    """The worst ratio default / plain refinement (px) over the real sets, and the figures in words."""
    ratios = [(r["rows"]["default"]["px"] / r["rows"]["plain refinement (intrinsics fixed)"]["px"], r)
              for r in results]
    worst = max(q for q, _ in ratios)
    said = "; ".join(f"{r['set'].name} {r['rows']['default']['px']:.2f} vs "
                     f"{r['rows']['plain refinement (intrinsics fixed)']['px']:.2f} px" for _, r in ratios)
    return worst, said


def replace_section(path: Path, text: str) -> None:
    """Put ``text`` (a section with its markers) in place of the old one in ``path``, or append it."""
    md = path.read_text()
    if BEGIN in md and END in md:
        md = md[: md.index(BEGIN)] + text + md[md.index(END) + len(END):]
    else:
        md = md.rstrip("\n") + "\n\n" + text + "\n"
    path.write_text(md)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--step", type=int, default=60, help="ETH: every STEP-th camera sample (default 60: 28 stations)")
    ap.add_argument("--update", help="replace the section in this markdown file (bench/results/handeye.md)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    results = [evaluate(s) for s in real_sets(args.step)]
    cmd = f".venv/bin/python -m bench.handeye_real --step {args.step}" + (f" --update {args.update}"
                                                                         if args.update else "")
    text = section(results, cmd).replace(END, f"Run time {time.perf_counter() - t0:.0f} s wall (load average "
                                           f"{os.getloadavg()[0]:.1f}, 2 cores shared).\n{END}")
    print(text)
    if args.update:
        replace_section(Path(args.update), text)


if __name__ == "__main__":
    main()
