"""Calibrations beyond 6-DOF AX=XB (issue 16): 4-DOF hand-eye, tool centre, measured-frame hand-eye.

Virtual-cell data with truth (``calibration.synthetic``: the SCARA cell, the tool centre and the 6-DOF
stations), a 1920x1200 camera (f = 1900 px), an 8x6 chessboard (25 mm), pixel noise 0.05 px,
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
- Eye-to-hand 4-DOF mapping over 20 more seeds at 14 and 28 stations: the ratio's spread and the
  calibration's own part of the map error against its reported 1σ.
- Tool centre on rendered frames: the fixed-camera virtual cell, jog-to-mark's turn step in process
  (9 detected marks, 7 angles over 180° at 2 marks). Peer: OpenCV's plain centroid of the spot.
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
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import cpu_model  # noqa: E402
from calibration import geometry as g  # noqa: E402
from calibration.camera_model import CameraModel  # noqa: E402
from calibration.detect import (  # noqa: E402
    detect,
    find_spot,
)
from calibration.geometry import invert, make_transform, transform_error  # noqa: E402
from calibration.handeye import (  # noqa: E402
    DEFAULT_TARGET_Z_SIGMA_MM,
    RobotNoise,
    calibrate_handeye_dof4,
    calibrate_handeye_measured,
    fit_tool_centre,
    make_stations4,
)
from calibration.measure import map_handeye  # noqa: E402
from calibration.npoint import fit_npoint  # noqa: E402
from calibration.synthetic import (  # noqa: E402
    perturb_pose,
    simulate_handeye,
    simulate_scara,
    simulate_tool_centre,
)
from calibration.targets import Chessboard  # noqa: E402
from drivers.sim.scene import BUILTIN_SCENE, load_scene  # noqa: E402
from drivers.sim.tool_feature import draw_tool_feature  # noqa: E402
from drivers.sim.world import SimWorld  # noqa: E402

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958.0], [0, 1900.0, 603.0], [0, 0, 1]]),
                  np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
BOARD = Chessboard(8, 6, 25.0)
SEEDS = [0, 1, 2, 3, 4]
FIXED_SCENE = BUILTIN_SCENE.with_name("virtual-cell-fixed-camera.yaml")


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


def tcp_rendered_rows() -> list[dict[str, Any]]:
    """The tool centre on rendered frames of the fixed-camera virtual cell, as jog-to-mark's turn step
    does it: the N-point map from the plate's 3x3 marks (detected; the robot's reported flange, the
    disk put on each mark), then 7 angles over 180° at 2 marks; the disk found by
    ``calibration.detect.tool_spot``. Each seed draws its own offset (15-40 mm, any direction). Peer: the same
    fit with the spot as OpenCV's plain centroid of the thresholded region (``cv2.moments``)."""
    rows = []
    base = load_scene(FIXED_SCENE)
    target = base.targets[0].parsed()
    pts = target.points()
    R_down = g.rotvec_to_matrix([np.pi, 0.0, 0.0])
    for seed in SEEDS:
        rng = np.random.default_rng([seed, 16])
        r_mm, phi = rng.uniform(15.0, 40.0), rng.uniform(-np.pi, np.pi)
        feature = base.tool_feature.model_copy(  # type: ignore[union-attr]
            update={"offset_mm": (r_mm * np.cos(phi), r_mm * np.sin(phi), 150.0)})
        world = SimWorld(base.model_copy(update={"seed": seed, "tool_feature": feature}))
        frng = np.random.default_rng(seed)

        def grab(w: SimWorld = world, f: Any = feature, r: np.random.Generator = frng) -> np.ndarray:
            T_cam_tool = g.invert(w.T_base_cam()) @ w.T_base_tool_true
            return draw_tool_feature(w.render(), w.camera_model, T_cam_tool, f, w.scene.camera.imaging, r)

        det = detect(grab(), target, "marks")
        T_bt = world.T_base_target(base.targets[0].name)
        offset_m = np.asarray(feature.offset_mm) * 1e-3
        chosen = [r * target.cols + c for r in (0, 3, 6) for c in (0, 3, 6)]
        uv_of = {int(i): det.uv[k] for k, i in enumerate(det.ids)}
        uv, xy, poses = [], [], {}
        for mid in chosen:
            p = g.transform_points(T_bt, pts.xyz_m[list(pts.ids).index(mid)])[0]
            world.place_tool(g.make_transform(R_down, p - R_down @ offset_m))
            T = world.T_base_tool_reported()
            uv.append(uv_of[mid])
            xy.append(T[:2, 3] * 1e3)
            poses[mid] = T
        npm = fit_npoint(np.array(uv), np.array(xy))
        ours, peer = [], []
        for mid in (24, 21):
            T_mark = poses[mid]
            for ang in np.linspace(-90.0, 90.0, 7):
                Tc = T_mark.copy()
                Tc[:3, :3] = g.rotvec_to_matrix([0.0, 0.0, np.radians(ang)]) @ T_mark[:3, :3]
                world.place_tool(Tc)
                T = world.T_base_tool_reported()
                img = grab()
                s = find_spot(img)
                M = T[:3, :3] @ T_mark[:3, :3].T
                rz = float(np.degrees(np.arctan2(M[1, 0], M[0, 0])))
                ours.append([s.u_px, s.v_px, T[0, 3] * 1e3, T[1, 3] * 1e3, rz])
                _, binary = cv2.threshold(img, 249, 255, cv2.THRESH_BINARY)
                m = cv2.moments(binary, binaryImage=True)
                peer.append([m["m10"] / m["m00"], m["m01"] / m["m00"], T[0, 3] * 1e3, T[1, 3] * 1e3, rz])
        truth = R_down[:2, :2] @ np.asarray(feature.offset_mm[:2])
        out = {}
        for name, rows_ in (("ours", np.array(ours)), ("peer", np.array(peer))):
            res = fit_tool_centre(rows_[:, 0:2], rows_[:, 2:4], rows_[:, 4], npm)
            out[name] = (float(np.linalg.norm(res.offset_mm - truth)), res.sigma_offset_mm, res.rms_mm)
        rows.append({"seed": seed, "radius_mm": r_mm, "model": npm.model, "ours": out["ours"], "peer": out["peer"]})
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


@dataclass
class _MapErrors:
    """Per mapped corner (mm, base-frame x/y): the solved calibration's error against the true point,
    the true calibration's, solved vs true on the same pixels, and the solved one's reported 1σ (and
    that of ``he_alt``, when given)."""

    est: list[float] = field(default_factory=list)
    true: list[float] = field(default_factory=list)
    calib: list[float] = field(default_factory=list)
    sigma: list[float] = field(default_factory=list)
    sigma_alt: list[float] = field(default_factory=list)


def _map_against_truth(he: dict[str, Any], truth: dict[str, Any], detections: list[Any], points_base: list[Any],
                       poses: list[Any], step: int, he_alt: dict[str, Any] | None = None) -> _MapErrors:
    """Map every ``step``-th corner of each station onto the target plane through ``he`` and through
    ``truth`` (the station's robot pose: eye-in-hand; None: eye-to-hand), with no pixel noise in the 1σ."""
    m = _MapErrors()
    for pose, det, P in zip(poses, detections, points_base, strict=True):
        for j in range(0, len(P), step):
            z = P[j, 2] * 1e3
            a = map_handeye(he, det.uv[j], CAM, z, pose, pixel_sigma_px=0.0)
            b = map_handeye(truth, det.uv[j], CAM, z, pose, with_uncertainty=False).xyz_mm
            m.est.append(float(np.linalg.norm(a.xyz_mm[:2] - P[j, :2] * 1e3)))
            m.true.append(float(np.linalg.norm(b[:2] - P[j, :2] * 1e3)))
            m.calib.append(float(np.linalg.norm(a.xyz_mm[:2] - b[:2])))
            m.sigma.append(float(np.hypot(a.sigma_mm[0], a.sigma_mm[1])))
            if he_alt is not None:
                c = map_handeye(he_alt, det.uv[j], CAM, z, pose, pixel_sigma_px=0.0).sigma_mm
                m.sigma_alt.append(float(np.hypot(c[0], c[1])))
    return m


def e2h_spread_rows(n_stations: tuple[int, ...] = (14, 28), n_seeds: int = 20) -> list[dict[str, Any]]:
    """Eye-to-hand 4-DOF over more seeds: the mapping ratio's spread, and the calibration's own part
    of the map error (estimate vs true calibration on the same pixels) against its reported 1σ."""
    rows = []
    noise = RobotNoise(0.02, 0.01)
    for n in n_stations:
        for seed in range(100, 100 + n_seeds):
            s = simulate_scara("eye-to-hand", n, np.random.default_rng(seed), camera=CAM, target=BOARD,
                               robot_noise=noise)
            he = calibrate_handeye_dof4("eye-to-hand", s.G_recorded, s.detections, CAM, BOARD, s.target_z_mm, noise,
                                        leave_one_out=False).to_json()
            truth = {**he, "T_base_cam": s.X_true.tolist()}
            # the same covariance without the stated 0.1 mm of the target height (exact in these data):
            # what the stations themselves determine
            cov = np.array(he["uncertainty"]["covariance"])
            cov[3:, 3:] -= (DEFAULT_TARGET_Z_SIGMA_MM * 1e-3) ** 2 * np.diag([0.0, 0.0, 1.0])
            he_st = {**he, "uncertainty": {**he["uncertainty"], "covariance": cov.tolist()}}
            m = _map_against_truth(he, truth, s.detections, s.points_base_true, [None] * len(s.detections), 4,
                                   he_alt=he_st)
            rows.append({"n": n, "seed": seed, "ratio": _rms(m.est) / _rms(m.true), "pix": _rms(m.true),
                         "calib": _rms(m.calib), "calib_sigma": _rms(m.sigma), "calib_sigma_st": _rms(m.sigma_alt)})
    return rows


HELDOUT_SEEDS = range(200, 220)
HELDOUT_TAIL = (" Another sample shows the tail: seeds 400-419 at 28 stations eye-to-hand (6-station held-out "
                "sets, tests/calibration/test_handeye_dof4_budget.py's `_heldout`) gave median 1.08x, worst 1.58x "
                "(1 of 20 over 1.5x), as a 19-of-20 design allows.")
HELDOUT_HEADING = "## 4-DOF on held-out sets: mapping against the true calibration (issue 26 item 4)"


def dof4_heldout_rows(n_stations: tuple[int, ...] = (14, 28), seeds: range = HELDOUT_SEEDS,
                      n_heldout: int = 10) -> list[dict[str, Any]]:
    """Issue 26 item 4: solve on one SCARA set, then map a *held-out* set (same cell, same X and Z,
    its own poses and images, ``n_heldout`` stations) onto the target plane through the solved and
    through the *true* calibration, with the held-out set's recorded (noisy) robot poses; the ratio
    of the two RMS errors (mm, base-frame x/y against the true points). Also the calibration's own
    part (solved vs true on the same pixels) against its reported 1σ on the plane."""
    rows = []
    noise = RobotNoise(0.02, 0.01)
    for setup in ("eye-in-hand", "eye-to-hand"):
        name = "T_tool_cam" if setup == "eye-in-hand" else "T_base_cam"
        for n in n_stations:
            for seed in seeds:
                s = simulate_scara(setup, n, np.random.default_rng(seed), camera=CAM, target=BOARD, robot_noise=noise)
                ho = simulate_scara(setup, n_heldout, np.random.default_rng([seed, 26]), camera=CAM, target=BOARD,
                                    robot_noise=noise)
                t0 = time.perf_counter()
                res = calibrate_handeye_dof4(setup, s.G_recorded, s.detections, CAM, BOARD, s.target_z_mm, noise,
                                             leave_one_out=False)
                dt = time.perf_counter() - t0
                he = res.to_json()
                truth = {**he, name: s.X_true.tolist()}
                poses = list(ho.G_recorded) if setup == "eye-in-hand" else [None] * len(ho.detections)
                m = _map_against_truth(he, truth, ho.detections, ho.points_base_true, poses, 2)
                rot, xy, zz = _err(res.X, s.X_true)
                rows.append({"setup": setup, "n": n, "seed": seed, "ratio": _rms(m.est) / _rms(m.true),
                             "map": _rms(m.est), "map_true": _rms(m.true), "calib": _rms(m.calib),
                             "calib_sigma": _rms(m.sigma),
                             "rot": rot, "xy": xy, "z": zz, "time_s": dt,
                             "codes": sorted({q["code"] for q in he["verdict"]["problems"]}),
                             "pred_ratio": he["mapping_budget"]["predicted_ratio_to_true_calibration"],
                             "pred_calib": he["mapping_budget"]["calibration_part_mm"],
                             "ask": he["mapping_budget"]["stations_for_1.5x_in_19_of_20"]})
    return rows


def dof4_heldout_table(rows: list[dict[str, Any]], median_target: float = 1.2,
                       worst_target: float = 1.5) -> list[str]:
    """The held-out section: per setup and station count, median and worst ratio against the targets."""
    L = ["", HELDOUT_HEADING, "",
         f"Seeds {rows[0]['seed']}-{rows[-1]['seed']} ({len({x['seed'] for x in rows})} per row), "
         "robot noise 0.02 mm / 0.01° per axis, pixel noise 0.05 px, the target height exact (as "
         "`--target-z-mm` states it). Each seed: "
         "solve on its stations, then map every second corner of a held-out set of 10 stations (the same cell, "
         "its own poses and images) onto the target plane through the solved calibration and through the "
         "TRUE calibration, both with the held-out set's recorded robot poses. 'ratio' = RMS map error of the "
         "solved ÷ that of the true calibration. 'calibration part' = solved vs true on the same pixels; "
         "'its 1σ' = the solver's reported uncertainty propagated to the plane (`map_handeye`). Targets: "
         f"median ≤ {median_target}x, worst ≤ {worst_target}x.", "",
         "| setup | stations | seeds | median ratio | worst ratio | target | true calib map mm (RMS) | "
         "solved map mm (RMS) | calibration part mm (RMS) | its 1σ mm (RMS) | actual/reported | rot ° (worst) | "
         "x/y mm (worst) | s (median) | solver's predicted part mm (RMS) / ratio (median) | warned | stations it asks "
         "for (median) |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for setup in ("eye-in-hand", "eye-to-hand"):
        for n in sorted({x["n"] for x in rows}):
            r = [x for x in rows if x["setup"] == setup and x["n"] == n]
            if not r:
                continue
            ratio = np.array([x["ratio"] for x in r])
            med, worst = float(np.median(ratio)), float(ratio.max())
            ok = med <= median_target and worst <= worst_target
            verdict = "met" if ok else "**MISSED** (" + ", ".join(
                ([f"median {med:.2f}"] if med > median_target else []) +
                ([f"worst {worst:.2f}, {int(np.sum(ratio > worst_target))} of {len(r)} seeds over"]
                 if worst > worst_target else [])) + ")"
            cal, sig = _rms([x["calib"] for x in r]), _rms([x["calib_sigma"] for x in r])
            L.append(f"| {setup} | {n} | {len(r)} | {med:.2f} | {worst:.2f} | {verdict} | "
                     f"{_rms([x['map_true'] for x in r]):.4f} | {_rms([x['map'] for x in r]):.4f} | {cal:.4f} | "
                     f"{sig:.4f} | {cal / sig:.2f} | {max(x['rot'] for x in r):.4f} | {max(x['xy'] for x in r):.3f} | "
                     f"{np.median([x['time_s'] for x in r]):.1f} | {_rms([x['pred_calib'] for x in r]):.4f} / "
                     f"{np.median([x['pred_ratio'] for x in r]):.2f} | "
                     f"{sum('stations_limit_mapping' in x['codes'] for x in r)} of {len(r)} | "
                     f"{np.median([x['ask'] for x in r]):.0f} |")
    L += ["", _heldout_note(rows)]
    return L


def _heldout_note(rows: list[dict[str, Any]]) -> str:
    """Why a row misses, in the measured figures: the calibration part against the solver's prediction."""
    out = []
    for setup in ("eye-in-hand", "eye-to-hand"):
        for n in sorted({x["n"] for x in rows}):
            r = [x for x in rows if x["setup"] == setup and x["n"] == n]
            if not r:
                continue
            cal, pred = _rms([x["calib"] for x in r]), _rms([x["pred_calib"] for x in r])
            warned = sum("stations_limit_mapping" in x["codes"] for x in r)
            out.append(f"{setup}, {n} stations: calibration part {cal:.4f} mm RMS, the solver predicted "
                       f"{pred:.4f} ({cal / pred:.2f}x), warned on {warned} of {len(r)}")
    return ("**Why a row misses, and what the result says.** The true calibration's map error is what any "
            "calibration has: pixel noise (and eye-in-hand the robot's pose noise at capture, which dominates "
            "and hides the estimate's error). The solved calibration adds its own error, the robot's pose noise "
            "through the stations; the solver predicts it from its covariance without the target-height prior "
            "(`mapping_budget`, calibration/handeye/dof4_budget.py) and the prediction is what the held-out sets "
            "measure: " + "; ".join(out) + ". The maximum-likelihood solve is at what the stations hold, so no "
            "cost or weighting does better on these data; the ratio is the data's and falls as 1/sqrt(stations). "
            "A fixed camera (eye-to-hand) sees the pixel noise alone at 0.8 m, so its ratio is the most "
            "sensitive. The result now says so: `stations_limit_mapping` (a warning) when the predicted ratio "
            "is over 1.2x, with the stations for 1.2x and for 1.5x in 19 of 20 captures "
            "(`mapping_budget.stations_for_1.5x_in_19_of_20`); the worst of 20 seeds is a 95th-percentile event, "
            "which at 14 stations needs about twice the stations the median does." + HELDOUT_TAIL +
            " What 4-DOF data cannot "
            "determine at all (the camera's height along the turning axis, fixed by `target_z_mm`, and the "
            "tool's own z offset) and what to add is in `fixed_by_constraint.not_determined_by_data`; here the "
            "height is exact, so the table is the x/y and rotation part only.")


def splice_section(text: str, heading: str, section: list[str]) -> str:
    """Replace the section under ``heading`` (up to the next '## ') in ``text``, or insert it before
    '## Rows for bench/results/handeye.md' (else at the end)."""
    body = "\n".join(section).strip("\n") + "\n"
    if heading in text:
        start = text.index(heading)
        nxt = text.find("\n## ", start + len(heading))
        return text[:start] + body + ("" if nxt < 0 else "\n" + text[nxt + 1:])
    anchor = text.find("## Rows for bench/results/handeye.md")
    if anchor < 0:
        return text.rstrip("\n") + "\n\n" + body
    return text[:anchor] + body + "\n" + text[anchor:]


def _spread_note(rows: list[dict[str, Any]]) -> str:
    out = []
    for n in sorted({x["n"] for x in rows}):
        r = [x for x in rows if x["n"] == n]
        cal, sst = _rms([x["calib"] for x in r]), _rms([x["calib_sigma_st"] for x in r])
        over = sum(x["ratio"] > 1.5 for x in r)
        out.append(f"{n} stations: over 1.5x on {over} of {len(r)} more seeds, the calibration part "
                   f"{cal:.4f} mm RMS against the {sst:.4f} mm its covariance gives from the stations alone "
                   f"(actual/predicted {cal / sst:.2f})")
    return (" Over more seeds (table below): " + "; ".join(out) + ". The estimate's error is what its own "
            "information matrix predicts: the maximum-likelihood solve with the stated robot noise is at what "
            "14 stations hold, so no estimator does markedly better on these data; the miss is the data's "
            "(robot noise through 14 stations), not a bias to fix. More stations meet it.")


def e2h_spread_table(rows: list[dict[str, Any]]) -> list[str]:
    L = ["", "## Eye-to-hand 4-DOF mapping: the ratio's spread over 20 more seeds (100-119)", "",
         "The true calibration's map error is pixel noise alone; the estimate adds its own error (estimate vs "
         "true calibration on the same pixels, 'calibration part'), driven by the robot's pose noise through the "
         "stations. If the calibration part matches the solver's own reported 1σ (propagated to the plane), the "
         "solver is at the information the data hold, and only more stations lower it.", "",
         "| stations | seeds | median ratio | worst ratio | seeds over 1.5x | pixel-noise map mm (true calib) | "
         "calibration part mm (RMS) | its reported 1σ mm | actual/reported | reported 1σ without the target-height "
         "prior mm | actual/that |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for n in sorted({x["n"] for x in rows}):
        r = [x for x in rows if x["n"] == n]
        ratio = np.array([x["ratio"] for x in r])
        cal, sig = _rms([x["calib"] for x in r]), _rms([x["calib_sigma"] for x in r])
        sst = _rms([x["calib_sigma_st"] for x in r])
        L.append(f"| {n} | {len(r)} | {np.median(ratio):.2f} | {ratio.max():.2f} | {int(np.sum(ratio > 1.5))} | "
                 f"{_rms([x['pix'] for x in r]):.4f} | {cal:.4f} | {sig:.4f} | {cal / sig:.2f} | {sst:.4f} | "
                 f"{cal / sst:.2f} |")
    return L


def handeye_md_rows(d4: list[dict[str, Any]], tc: list[dict[str, Any]], me: list[dict[str, Any]],
                    tr: list[dict[str, Any]]) -> str:
    """The issue-16 rows in ``bench/results/handeye.md``'s terms (a section to append there)."""
    L = ["## Beyond 6-DOF AX=XB (issue 16; from bench/handeye_special.py, same run as its own table)", "",
         "| calibration | setup | data (seeds 0-4) | cellctl, worst seed | peer on the same data (median) | target | |",
         "|---|---|---|---|---|---|---|"]
    for setup in ("eye-in-hand", "eye-to-hand"):
        r = [x for x in d4 if x["setup"] == setup]
        rot, xy = max(x["err"][0] for x in r), max(x["err"][1] for x in r)
        ratio = max(x["map"] / x["map_true"] for x in r)
        tsai = [x["cv"]["TSAI"] for x in r]
        ok = rot <= 0.05 and xy <= 0.2 and ratio <= 1.5
        L.append(f"| 4-DOF (`--dof 4`) | {setup} | 14 stations, 0.02 mm / 0.01°, 0.05 px | {rot:.4f}° / "
                 f"x/y {xy:.3f} mm / map {ratio:.2f}x the true calibration's | "
                 f"OpenCV TSAI {np.median([t[0] for t in tsai]):.3g}° / "
                 f"x/y {np.median([t[1] for t in tsai]):.3g} mm (no 4-DOF model) | ≤ 0.05°, ≤ 0.2 mm, ≤ 1.5x | "
                 f"{'met' if ok else '**MISSED**'} |")
    worst = max(x["err"] for x in tc)
    L.append(f"| tool centre (`calib tcp`) | fixed camera | 7 angles x 2 flange positions, 0.05 px | {worst:.4f} mm | "
             f"free circle per position {np.median([x['free_err'] for x in tc]):.4f} mm | ≤ 0.05 mm | "
             f"{'met' if worst <= 0.05 else '**MISSED**'} |")
    worst = max(x["ours"][0] for x in tr)
    verdict = "met" if worst <= 0.05 else "**MISSED**"
    L.append(f"| tool centre (jog-to-mark's turn) | fixed camera, rendered | 7 angles x 2 marks, the map from 9 "
             f"detected marks | {worst:.4f} mm | OpenCV centroid of the thresholded spot "
             f"{np.median([x['peer'][0] for x in tr]):.4f} mm | ≤ 0.05 mm | {verdict} |")
    for setup in ("eye-in-hand", "eye-to-hand"):
        r = [x for x in me if x["setup"] == setup and x["n"] == 3]
        wr, wt = max(x["rot"] for x in r), max(x["trans"] for x in r)
        L.append(f"| measured frame (`--T-base-target` / `--T-tool-target`) | {setup} | 3 stations, 0.03 mm / 0.005° "
                 f"robot and tracker | {wr:.4f}° / {wt:.3f} mm | OpenCV TSAI without the frame "
                 f"{np.median([x['cv_rot'] for x in r]):.4f}° / {np.median([x['cv_trans'] for x in r]):.3f} mm | "
                 f"≤ 0.03°, ≤ 0.2 mm | {'met' if wr <= 0.03 and wt <= 0.2 else '**MISSED**'} |")
    return "\n".join(L) + "\n"


def _rms(v: list[float]) -> float:
    return float(np.sqrt(np.nanmean(np.square(v))))


def report(d4: list[dict[str, Any]], tc: list[dict[str, Any]], me: list[dict[str, Any]],
           spread: list[dict[str, Any]], tr: list[dict[str, Any]]) -> str:
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
    worst_tr = max(x["ours"][0] for x in tr)
    L.append(f"- tool centre on rendered frames (fixed-camera virtual cell, 7 angles at 2 marks, the map from 9 "
             f"detected marks), worst of {len(tr)} seeds: {worst_tr:.4f} mm (≤ 0.05): "
             f"**{'met' if worst_tr <= 0.05 else 'MISSED'}**.")
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
                    + _spread_note(spread) if setup == "eye-to-hand" else "see the per-seed rows."))
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
    L += ["", "## Tool centre on rendered frames (per seed)", "",
          "The fixed-camera virtual cell (`drivers/sim/scenes/virtual-cell-fixed-camera.yaml`: blur 0.5 px, noise 1 "
          "DN, robot 0.02 mm / 0.005°), as jog-to-mark's turn does it; each seed its own offset. Peer: OpenCV's "
          "plain centroid of the thresholded spot (`cv2.moments`), the same fit.", "",
          "| seed | offset radius mm | map model | error mm | reported 1σ mm | rms mm | peer error mm | "
          "peer rms mm |", "|---|---|---|---|---|---|---|---|"]
    for x in tr:
        o, q = x["ours"], x["peer"]
        L.append(f"| {x['seed']} | {x['radius_mm']:.1f} | {x['model']} | {o[0]:.4f} | {o[1]:.4f} | {o[2]:.4f} | "
                 f"{q[0]:.4f} | {q[2]:.4f} |")
    honesty = _rms([x["ours"][0] for x in tr]) / _rms([x["ours"][1] for x in tr])
    L.append(f"\nactual/reported (RMS over seeds): {honesty:.2f}"
             "; the saturated, ringed spot is easy for a plain centroid too, and the map's own error (similarity "
             "or homography from 9 marks without lens correction) dominates the residual.")
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
    L += e2h_spread_table(spread)
    L += ["", "## Rows for bench/results/handeye.md", "",
          "`bench/handeye.py` writes that file; these rows (printed at the end of this bench's output too) "
          "are meant to be appended to it:", "", handeye_md_rows(d4, tc, me, tr)]
    L += ["", "    .venv/bin/python bench/handeye_special.py"]
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "handeye_special.md"))
    ap.add_argument("--heldout-only", action="store_true",
                    help="run only the 4-DOF held-out section (issue 26 item 4) and replace it in --out")
    args = ap.parse_args()
    t0, c0 = time.perf_counter(), time.process_time()
    if args.heldout_only:
        sec = dof4_heldout_table(dof4_heldout_rows())
        wall, cpu_s = time.perf_counter() - t0, time.process_time() - c0
        sec += ["", f"    .venv/bin/python bench/handeye_special.py --heldout-only  ({wall:.0f} s wall, {cpu_s:.0f} s "
                    f"CPU, load average {os.getloadavg()[0]:.1f}, {cpu_model()})"]
        out = Path(args.out)
        out.write_text(splice_section(out.read_text() if out.exists() else "", HELDOUT_HEADING, sec))
        print("\n".join(sec))
        return
    d4, tc, me = dof4_rows(), tcp_rows(), measured_rows()
    tr = tcp_rendered_rows()
    text = report(d4, tc, me, e2h_spread_rows(), tr)
    text = splice_section(text, HELDOUT_HEADING, dof4_heldout_table(dof4_heldout_rows()))
    cpu = cpu_model()
    text += (f"\nRun: {time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU, load average "
             f"{os.getloadavg()[0]:.1f} at the end, {cpu} (the per-seed 's' column is wall time).\n")
    Path(args.out).write_text(text)
    print(text)
    print("---- rows to append to bench/results/handeye.md ----")
    print(handeye_md_rows(d4, tc, me, tr))
    print(f"bench/handeye_special.py: {time.perf_counter() - t0:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
