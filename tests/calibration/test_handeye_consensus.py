"""Stations far off the consensus (issue 26 item 3): a robot pose recorded 12 mm / 1.9° off.

On a synthetic set that follows the stated noise, the screw-invariant check already leaves such a
station out. On a real arm with millimetre, pose-dependent error it did not (its threshold is 8x
the median station's score, and a real arm's median is high): the real ETH arm in tests/data with
one station moved is the case. The consensus check of the solution flags it there, and leaves it
out when a calibration without it cannot predict it either.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3, invert, make_transform, quaternion_to_matrix
from calibration.handeye import RobotNoise, calibrate_handeye, transform_error_deg_mm
from calibration.handeye.consensus import CONSENSUS_FACTOR, confirmed_by_held_out, off_consensus
from calibration.observations import Detection
from calibration.synthetic import simulate_handeye
from calibration.targets import Chessboard

CAM = CameraModel("opencv5", 1600, 1200, np.array([[1700.0, 0, 800], [0, 1700.0, 600], [0, 0, 1]]),
                  np.array([-0.08, 0.04, 0.0, 0.0, 0.0]))
BOARD = Chessboard(8, 6, 30.0)
ETH = Path(__file__).resolve().parents[1] / "data" / "handeye_ethz_robot_arm_sr300"
MOVED = 5


def _moved(G: list[np.ndarray], k: int, seed: int) -> list[np.ndarray]:
    """``G`` with station ``k``'s recorded pose 12 mm and 1.9° off (random directions)."""
    rng = np.random.default_rng(seed)
    axis, d = rng.normal(size=3), rng.normal(size=3)
    out = [g.copy() for g in G]
    out[k] = make_transform(exp_so3(np.radians(1.9) * axis / np.linalg.norm(axis)) @ G[k][:3, :3],
                            G[k][:3, 3] + 0.012 * d / np.linalg.norm(d))
    return out


def _eth(step: int) -> tuple[list[np.ndarray], list[Detection], CameraModel, Chessboard]:
    """The real ETH arm + SR300 (as bench/handeye_real.py builds it): every ``step``-th camera pose,
    the robot pose interpolated at camera time - 0.02 s, detections of a 6x6 grid through the SR300."""
    from scipy.spatial.transform import Rotation, Slerp

    rob = np.loadtxt(ETH / "robot_arm_complete_bag_color_and_ir_base_link_sr300_hinge.csv", delimiter=",")
    cam = np.loadtxt(ETH / "robot_arm_complete_bag_color_and_ir_target_ir.csv", delimiter=",")
    sel = cam[::step]
    t = sel[:, 0] - 0.02
    sel, t = sel[(t > rob[0, 0]) & (t < rob[-1, 0])], t[(t > rob[0, 0]) & (t < rob[-1, 0])]
    R = Slerp(rob[:, 0], Rotation.from_quat(rob[:, 4:8]))(t).as_matrix()
    pos = np.column_stack([np.interp(t, rob[:, 0], rob[:, k]) for k in (1, 2, 3)])
    sr300 = CameraModel("opencv5", 640, 480, np.array([[471.845, 0, 316.850], [0, 471.686, 237.389], [0, 0, 1]]),
                        np.array([-0.15024, -0.00326, -0.00126, -0.00042, 0.0]))
    grid = Chessboard(6, 6, 40.0)
    tp = grid.points()
    dets = []
    for k, r in enumerate(sel):
        C = invert(make_transform(quaternion_to_matrix(r[4:8]), r[1:4]))
        dets.append(Detection(f"t{k:03d}", True, tp.ids.copy(), sr300.project(tp.xyz_m @ C[:3, :3].T + C[:3, 3]),
                              image_size=(640, 480)))
    return [make_transform(R[k], pos[k]) for k in range(len(t))], dets, sr300, grid


def test_the_thresholds() -> None:
    def miss(px: float, deg: float = 1.0, mm: float = 10.0) -> dict[str, float]:
        return {"rms_px": px, "rot_deg": deg, "trans_mm": mm}

    base = [miss(1.0 + 0.1 * k) for k in range(10)]
    assert off_consensus(base) == []
    far = [*base, miss(CONSENSUS_FACTOR * 1.6)]  # the median is 1.5 px
    assert off_consensus(far) == [10]
    # far in pixels, but below both floors (0.3°, 3 mm): not worth a warning
    assert off_consensus([*base, miss(50.0, 0.1, 1.0)]) == []
    loo = [{"rms_px": 1.0} for _ in range(10)] + [{"rms_px": 20.0}]
    assert confirmed_by_held_out([10], loo) == [10]
    assert confirmed_by_held_out([10], [{"rms_px": 1.0} for _ in range(11)]) == []


def test_a_moved_station_in_a_synthetic_set_is_left_out() -> None:
    sim = simulate_handeye("eye-in-hand", 12, np.random.default_rng(3), camera=CAM, target=BOARD,
                           robot_noise=RobotNoise(0.05, 0.01))
    G = _moved(sim.G_recorded, MOVED, 3)
    res = calibrate_handeye("eye-in-hand", G, sim.detections, CAM, BOARD, leave_one_out=False)
    moved = sim.detections[MOVED].image
    assert moved not in [p["image"] for p in res.stations]
    assert {"pose_outlier", "station_off_consensus"} & {p.code for p in res.problems}
    rot, trans = transform_error_deg_mm(res.X, sim.X_true)
    assert rot < 0.05 and trans < 0.5


def test_a_moved_station_on_the_real_arm_is_flagged() -> None:
    G, dets, cam, grid = _eth(120)
    noise = RobotNoise(0.5, 0.1)
    clean = calibrate_handeye("eye-in-hand", G, dets, cam, grid, noise, sigma_px=0.3, leave_one_out=False,
                              error_model="fixed_prior")
    assert not any(p["off_consensus"] for p in clean.stations)
    assert "station_off_consensus" not in {p.code for p in clean.problems}
    res = calibrate_handeye("eye-in-hand", _moved(G, MOVED, 1), dets, cam, grid, noise, sigma_px=0.3,
                            leave_one_out=False, error_model="fixed_prior")
    flagged = [p["image"] for p in res.stations if p["off_consensus"]]
    assert flagged == [dets[MOVED].image]
    msg = [p.message for p in res.problems if p.code == "station_off_consensus"]
    assert len(msg) == 1 and dets[MOVED].image in msg[0] and "no leave-one-out run to confirm" in msg[0]


def test_held_out_prediction_confirms_and_the_station_is_left_out() -> None:
    G, dets, cam, grid = _eth(150)
    res = calibrate_handeye("eye-in-hand", _moved(G, MOVED, 1), dets, cam, grid, RobotNoise(0.5, 0.1), sigma_px=0.3,
                            leave_one_out=True, error_model="fixed_prior")
    assert dets[MOVED].image not in [p["image"] for p in res.stations]
    msg = [p.message for p in res.problems if p.code == "station_off_consensus"]
    assert len(msg) == 1 and "left out of the solution" in msg[0]
    assert len(res.loo["per_pose"]) == len(G) - 1  # the quality figure is that of the solution without it
    # the consensus figures are those of the solution without it: every remaining station within the spread
    misses = [p["consensus_rms_px"] for p in res.stations]
    assert not any(p["off_consensus"] for p in res.stations) and max(misses) < 5 * float(np.median(misses))
