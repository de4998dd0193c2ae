"""Calibrations beyond 6-DOF AX=XB (issue 16): 4-DOF hand-eye, tool centre, measured-frame hand-eye.

Virtual-cell data with truth (``calibration.handeye_special_sim``, ``calibration.handeye``'s
simulator), a 1920x1200 camera (f = 1900 px), an 8x6 chessboard (25 mm), pixel noise 0.05 px,
seeds 0-4.

- 4-DOF: a SCARA-style cell, 14 stations, robot noise 0.02 mm / 0.01° per axis, the tool turning
  ±100° about base z; eye-in-hand (camera on a downward tool, 0.32-0.45 m above a level target)
  and eye-to-hand (camera 0.8 m above, target under the flange). Errors of ``T_tool_cam`` /
  ``T_base_cam``; "map" = RMS distance on the target plane between each station's observed target
  pixels mapped with the result (through the recorded robot pose, eye-in-hand) and the true
  points, next to the same with the *true* calibration. Peer: OpenCV's ``calibrateHandEye``
  (TSAI, PARK) on the same stations — it has no 4-DOF model.
- Tool centre: 7 angles over 180° at 2 flange positions under a fixed camera 0.5 m above the
  table, the N-point map fitted from 9 noisy jog-to-mark pairs. Peer: the classic free circle
  fit (Kåsa) per position with the offset read from the circle centre.
- Measured frame: 1, 3 and 6 stations, robot and tracker 0.03 mm / 0.005° per axis. Peer:
  OpenCV's ``calibrateHandEye`` (TSAI) on the same stations without the measured frame.

    .venv/bin/python bench/handeye_special.py [--out bench/results/handeye_special.md]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.camera_model import CameraModel  # noqa: E402
from calibration.geometry import invert, make_transform, transform_error  # noqa: E402
from calibration.handeye import RobotNoise, simulate_handeye  # noqa: E402
from calibration.handeye_dof4 import calibrate_handeye_dof4, make_stations4  # noqa: E402
from calibration.handeye_measured import calibrate_handeye_measured  # noqa: E402
from calibration.handeye_special_sim import perturb_pose, simulate_scara, simulate_tool_centre  # noqa: E402
from calibration.npoint import fit_npoint  # noqa: E402
from calibration.pixel_to_robot import map_handeye  # noqa: E402
from calibration.targets import Chessboard  # noqa: E402
from calibration.tcp import fit_tool_centre  # noqa: E402

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958.0], [0, 1900.0, 603.0], [0, 0, 1]]),
                  np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(8, 6, 25.0)
SEEDS = [0, 1, 2, 3, 4]


def _opencv(setup: str, G: list[np.ndarray], C: list[np.ndarray], method: int) -> np.ndarray:
    H = [g if setup == "eye-in-hand" else invert(g) for g in G]
    R, t = cv2.calibrateHandEye([h[:3, :3] for h in H], [h[:3, 3] for h in H], [c[:3, :3] for c in C],
                                [c[:3, 3] for c in C], method=method)
    return make_transform(np.asarray(R), np.asarray(t).ravel())


def _err(X: np.ndarray, X_true: np.ndarray) -> tuple[float, float, float]:
    rot, _ = transform_error(X, X_true)
    d = (X[:3, 3] - X_true[:3, 3]) * 1e3
    return float(np.degrees(rot)), float(np.hypot(d[0], d[1])), float(abs(d[2]))


def dof4_rows() -> list[dict[str, Any]]:
    rows = []
    noise = RobotNoise(0.02, 0.01)
    for setup in ("eye-in-hand", "eye-to-hand"):
        for seed in SEEDS:
            s = simulate_scara(setup, 14, np.random.default_rng(seed), camera=CAM, target=BOARD, robot_noise=noise)
            t0 = time.perf_counter()
            res = calibrate_handeye_dof4(setup, s.G_recorded, s.detections, CAM, BOARD, s.target_z_mm, noise,
                                         leave_one_out=False)
            dt = time.perf_counter() - t0
            he = res.to_json()
            truth = dict(he)
            truth["T_tool_cam" if setup == "eye-in-hand" else "T_base_cam"] = s.X_true.tolist()
            e_est, e_true = [], []
            for G, det, P in zip(s.G_recorded, s.detections, s.points_base_true, strict=True):
                pose = G if setup == "eye-in-hand" else None
                for j in range(len(P)):
                    z = P[j, 2] * 1e3
                    a = map_handeye(he, det.uv[j], CAM, z, pose, with_uncertainty=False).xyz_mm
                    b = map_handeye(truth, det.uv[j], CAM, z, pose, with_uncertainty=False).xyz_mm
                    e_est.append(np.linalg.norm(a[:2] - P[j, :2] * 1e3))
                    e_true.append(np.linalg.norm(b[:2] - P[j, :2] * 1e3))
            st, _ = make_stations4(s.G_recorded, s.detections, CAM, BOARD)
            cv = {}
            for name, flag in (("TSAI", cv2.CALIB_HAND_EYE_TSAI), ("PARK", cv2.CALIB_HAND_EYE_PARK)):
                try:
                    cv[name] = _err(_opencv(setup, [x.G for x in st], [x.C for x in st], flag), s.X_true)
                except cv2.error:
                    cv[name] = (float("nan"),) * 3
            rows.append({"setup": setup, "seed": seed, "err": _err(res.X, s.X_true),
                         "sig_rot": he["uncertainty"]["rot_deg"], "sig_trans": he["uncertainty"]["trans_mm"],
                         "map": float(np.sqrt(np.mean(np.square(e_est)))),
                         "map_true": float(np.sqrt(np.mean(np.square(e_true)))), "cv": cv, "time_s": dt})
    return rows


def tcp_rows() -> list[dict[str, Any]]:
    rows = []
    for seed in SEEDS:
        s = simulate_tool_centre(np.random.default_rng(seed), CAM)
        npm = fit_npoint(s.npoint_uv_px, s.npoint_xy_mm, "homography", CAM)
        res = fit_tool_centre(s.uv_px, s.flange_mm, s.rz_deg, npm)
        # classic peer: a free circle per position, offset = mean of Rz(-rz) (p - centre)
        p = npm.map(s.uv_px)
        offs = []
        for pos in res.positions:
            sel = np.all(np.isclose(s.flange_mm, pos["flange_mm"]), axis=1)
            c = np.array(pos["free_circle"]["centre_mm"])
            for q, rz in zip(p[sel], s.rz_deg[sel], strict=True):
                a = np.radians(-rz)
                offs.append(np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ (q - c))
        free = np.mean(offs, axis=0)
        rows.append({"seed": seed, "err": float(np.linalg.norm(res.offset_mm - s.offset_mm)),
                     "sigma": res.sigma_offset_mm, "rms": res.rms_mm,
                     "free_err": float(np.linalg.norm(free - s.offset_mm))})
    return rows


def measured_rows() -> list[dict[str, Any]]:
    rows = []
    noise = RobotNoise(0.03, 0.005)
    for setup in ("eye-in-hand", "eye-to-hand"):
        for n in (1, 3, 6):
            for seed in SEEDS:
                rng = np.random.default_rng([seed, n])
                s = simulate_handeye(setup, n, rng, camera=CAM, target=BOARD, robot_noise=noise)
                Zm = perturb_pose(s.Z_true, rng, noise)
                res = calibrate_handeye_measured(setup, s.G_recorded, s.detections, CAM, BOARD, Zm, noise, noise)
                js = res.to_json()
                cv_err: tuple[float, float, float] = (float("nan"),) * 3
                if n >= 3:
                    st, _ = make_stations4(s.G_recorded, s.detections, CAM, BOARD)
                    cv_err = _err(_opencv(setup, [x.G for x in st], [x.C for x in st], cv2.CALIB_HAND_EYE_TSAI),
                                  s.X_true)
                e = _err(res.X, s.X_true)
                rows.append({"setup": setup, "n": n, "seed": seed, "rot": e[0],
                             "trans": float(1e3 * np.linalg.norm(res.X[:3, 3] - s.X_true[:3, 3])),
                             "sig_rot": js["uncertainty"]["rot_deg"], "sig_trans": js["uncertainty"]["trans_mm"],
                             "cv_rot": cv_err[0], "cv_trans": float(np.hypot(cv_err[1], cv_err[2]))})
    return rows


def _rms(v: list[float]) -> float:
    return float(np.sqrt(np.nanmean(np.square(v))))


def report(d4: list[dict[str, Any]], tc: list[dict[str, Any]], me: list[dict[str, Any]]) -> str:
    L = ["# Calibrations beyond 6-DOF AX=XB (issue 16): 4-DOF hand-eye, tool centre, measured frame", "",
         (__doc__ or "").split("\n\n")[1].replace("\n", " "), "", "## Targets", ""]
    for setup in ("eye-in-hand", "eye-to-hand"):
        r = [x for x in d4 if x["setup"] == setup]
        worst_rot = max(x["err"][0] for x in r)
        worst_xy = max(x["err"][1] for x in r)
        worst_map = max(x["map"] / x["map_true"] for x in r)
        ok = worst_rot <= 0.05 and worst_xy <= 0.2 and worst_map <= 1.5
        L.append(f"- 4-DOF {setup} (14 stations, 0.02 mm / 0.01°), worst of {len(r)} seeds: rotation "
                 f"{worst_rot:.4f}° (≤ 0.05), x/y {worst_xy:.3f} mm (≤ 0.2), mapped points / true calibration's "
                 f"{worst_map:.2f}x (≤ 1.5): **{'met' if ok else 'MISSED'}**.")
    worst_tcp = max(x["err"] for x in tc)
    L.append(f"- tool centre (7 angles at 2 positions, 0.05 px), worst of {len(tc)} seeds: offset error "
             f"{worst_tcp:.4f} mm (≤ 0.05): **{'met' if worst_tcp <= 0.05 else 'MISSED'}**.")
    m3 = [x for x in me if x["n"] == 3]
    wr, wt = max(x["rot"] for x in m3), max(x["trans"] for x in m3)
    L.append(f"- measured frame, 3 stations (0.03 mm / 0.005° robot and tracker), worst of {len(m3)} runs (both "
             f"setups): {wr:.4f}° (≤ 0.03), {wt:.3f} mm (≤ 0.2): "
             f"**{'met' if wr <= 0.03 and wt <= 0.2 else 'MISSED'}**.")
    for setup in ("eye-in-hand", "eye-to-hand"):
        miss = [x for x in d4 if x["setup"] == setup and x["map"] / x["map_true"] > 1.5]
        if not miss:
            continue
        r = [x for x in d4 if x["setup"] == setup]
        L.append(f"- why the {setup} mapping ratio misses on {len(miss)} of {len(r)} seeds (median ratio "
                 f"{np.median([x['map'] / x['map_true'] for x in r]):.2f}x): "
                 + ("a fixed camera maps without any robot pose, so the true calibration's error is the pixel noise "
                    f"alone ({np.median([x['map_true'] for x in r]) * 1e3:.0f} µm RMS); the estimate's own error "
                    f"(x/y up to {max(x['err'][1] for x in r):.3f} mm, within its reported 1σ of "
                    f"{np.median([x['sig_trans'] for x in r]):.2f} mm) adds to it 1:1. Eye-in-hand both carry the "
                    "robot's pose noise, which hides the estimate's error. More stations lower it (σ ~ 1/√n)."
                    if setup == "eye-to-hand" else "see the per-seed rows."))
    L += ["", "## 4-DOF hand-eye (per seed)", "",
          "| setup | seed | rot ° | x/y mm | z mm | reported 1σ ° / mm | map mm | true calib map mm | ratio | "
          "OpenCV TSAI ° / x/y mm / z mm | OpenCV PARK ° / x/y mm / z mm | s |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in d4:
        e, t, p = x["err"], x["cv"]["TSAI"], x["cv"]["PARK"]
        L.append(f"| {x['setup']} | {x['seed']} | {e[0]:.4f} | {e[1]:.3f} | {e[2]:.3f} | {x['sig_rot']:.4f} / "
                 f"{x['sig_trans']:.3f} | {x['map']:.4f} | {x['map_true']:.4f} | {x['map'] / x['map_true']:.2f} | "
                 f"{t[0]:.3g} / {t[1]:.3g} / {t[2]:.3g} | {p[0]:.3g} / {p[1]:.3g} / {p[2]:.3g} | {x['time_s']:.1f} |")
    L += ["", "The 4-DOF z error is what `--target-z-mm` (here exact) leaves; OpenCV's closed forms have no "
          "4-DOF model, so the translation along the turning axis is undetermined for them.", "",
          "## Tool centre (per seed)", "",
          "| seed | offset error mm | reported 1σ mm | rms mm | free-circle peer error mm |",
          "|---|---|---|---|---|"]
    for x in tc:
        L.append(f"| {x['seed']} | {x['err']:.4f} | {x['sigma']:.4f} | {x['rms']:.4f} | {x['free_err']:.4f} |")
    L.append(f"\nactual/reported (RMS over seeds): {_rms([x['err'] for x in tc]) / _rms([x['sigma'] for x in tc]):.2f}")
    L += ["", "## Measured-frame hand-eye (RMS over seeds)", "",
          "| setup | stations | rot ° | trans mm | reported 1σ ° / mm | actual/reported rot / trans | "
          "OpenCV TSAI (no frame) ° / mm |", "|---|---|---|---|---|---|---|"]
    for setup in ("eye-in-hand", "eye-to-hand"):
        for n in (1, 3, 6):
            r = [x for x in me if x["setup"] == setup and x["n"] == n]
            rr, rt = _rms([x["rot"] for x in r]), _rms([x["trans"] for x in r])
            sr, s_t = _rms([x["sig_rot"] for x in r]), _rms([x["sig_trans"] for x in r])
            cv = ("—" if n < 3 else f"{_rms([x['cv_rot'] for x in r]):.4f} / {_rms([x['cv_trans'] for x in r]):.3f}")
            L.append(f"| {setup} | {n} | {rr:.4f} | {rt:.3f} | {sr:.4f} / {s_t:.3f} | {rr / sr:.2f} / {rt / s_t:.2f} "
                     f"| {cv} |")
    L += ["", "    .venv/bin/python bench/handeye_special.py"]
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "handeye_special.md"))
    args = ap.parse_args()
    t0 = time.perf_counter()
    text = report(dof4_rows(), tcp_rows(), measured_rows())
    Path(args.out).write_text(text)
    print(text)
    print(f"bench/handeye_special.py: {time.perf_counter() - t0:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
