"""Virtual-cell data with truth for the calibrations beyond 6-DOF AX=XB (tests and
``bench/handeye_special.py``): a SCARA-style cell (tool turning about base z only), a tool-centre
set (a feature on the tool turned about z under a fixed camera) and measured target frames.

Robot noise follows ``calibration.handeye``'s stated model: the recorded ``T_base_tool`` differs
from the true one by ``Exp(w)`` (base frame) and ``v``, ``w ~ N(0, σ_r²)``, ``v ~ N(0, σ_t²)`` per
axis. Metres and radians inside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.camera_model import CameraModel
from calibration.geometry import exp_so3, invert, make_transform
from calibration.handeye import RobotNoise
from calibration.observations import Detection
from calibration.targets import Target

Mat4 = NDArray[np.float64]


def perturb_pose(G: Mat4, rng: np.random.Generator, noise: RobotNoise) -> Mat4:
    """A recorded pose: ``G`` with the stated robot noise applied (base frame)."""
    w = rng.normal(0.0, np.radians(noise.sigma_deg), 3)
    v = rng.normal(0.0, noise.sigma_mm * 1e-3, 3)
    return make_transform(exp_so3(w) @ G[:3, :3], G[:3, 3] + v)


@dataclass
class ScaraSet:
    setup: str
    camera: CameraModel
    target: Target
    X_true: Mat4
    Z_true: Mat4
    target_z_mm: float
    """The height --target-z-mm states: target origin z (eye-to-hand: at the first pose), base frame."""
    G_true: list[Mat4]
    G_recorded: list[Mat4]
    detections: list[Detection]
    points_base_true: list[NDArray[np.float64]]
    """Per station: the target points in the base frame (truth), for mapping checks."""


def simulate_scara(setup: str, n_stations: int, rng: np.random.Generator, *, camera: CameraModel, target: Target,
                   robot_noise: RobotNoise | None = None, pixel_sigma_px: float = 0.05,
                   tool_down: bool = True, camera_tilt_deg: float = 3.0) -> ScaraSet:
    """A SCARA-style cell: the tool turns about base z (random ±100°) and moves in x/y/z.

    Eye-in-hand: camera on the tool looking down at a level target on the table (origin 12 mm high).
    Eye-to-hand: camera 0.8 m above the table looking down at a target carried under the flange.
    ``tool_down``: the tool z axis points down (a UR picking top-down); else up (a SCARA's).
    """
    noise = robot_noise or RobotNoise(0.02, 0.01)
    R0 = exp_so3([np.pi, 0.0, 0.0]) if tool_down else np.eye(3)
    tilt = exp_so3(np.radians(camera_tilt_deg) * np.array([0.6, -0.8, 0.0]))
    tp = target.points()
    centre = tp.xyz_m.mean(axis=0)
    face_down = exp_so3([np.pi, 0.0, 0.0])  # target frame z into the target: a face-up target has z down
    if setup == "eye-in-hand":
        # camera optical axis (z) along the tool z axis when the tool points down
        X = make_transform((R0.T @ face_down) @ tilt @ exp_so3([0.0, 0.0, 0.4]), R0.T @ np.array([0.045, -0.03, 0.09]))
        Z = make_transform(exp_so3([0.0, 0.0, 0.3]) @ face_down, [0.45, 0.02, 0.012])
        z_mm = 12.0
    elif setup == "eye-to-hand":
        X = make_transform(face_down @ tilt @ exp_so3([0.0, 0.0, -0.7]), [0.45, 0.0, 0.80])
        Z = make_transform(R0.T @ exp_so3([0.0, 0.0, 0.25]) @ face_down, R0.T @ np.array([0.02, -0.015, -0.06]))
        z_mm = float("nan")
    else:
        raise ValueError(f"setup must be eye-in-hand or eye-to-hand, got {setup!r}")
    G_true: list[Mat4] = []
    while len(G_true) < n_stations:
        th = np.radians(rng.uniform(-100.0, 100.0))
        R = exp_so3([0.0, 0.0, th]) @ R0
        if setup == "eye-in-hand":
            cam_pos = Z[:3, :3] @ centre + Z[:3, 3] + np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05),
                                                                rng.uniform(0.32, 0.45)])
            G = make_transform(R, cam_pos - R @ X[:3, 3])
            C = invert(X) @ invert(G) @ Z
        else:
            xy = np.array([0.45 + rng.uniform(-0.08, 0.08), rng.uniform(-0.08, 0.08), rng.uniform(0.1, 0.25)])
            G = make_transform(R, xy - R @ Z[:3, 3])
            C = invert(X) @ G @ Z
        uv = camera.project(tp.xyz_m @ C[:3, :3].T + C[:3, 3])
        if np.all(np.isfinite(uv)) and np.all((uv > 20) & (uv < np.array(camera.size) - 21)):
            G_true.append(G)
    if setup == "eye-to-hand":
        z_mm = float(1e3 * (G_true[0] @ Z)[2, 3])
    G_rec, dets, pts = [], [], []
    for k, G in enumerate(G_true):
        G_rec.append(perturb_pose(G, rng, noise))
        C = invert(X) @ invert(G) @ Z if setup == "eye-in-hand" else invert(X) @ G @ Z
        uv = camera.project(tp.xyz_m @ C[:3, :3].T + C[:3, 3]) + rng.normal(0.0, pixel_sigma_px, (len(tp.ids), 2))
        dets.append(Detection(f"station{k:02d}.png", True, tp.ids.copy(), uv, image_size=camera.size))
        T_base_target = Z if setup == "eye-in-hand" else G @ Z
        pts.append(tp.xyz_m @ T_base_target[:3, :3].T + T_base_target[:3, 3])
    return ScaraSet(setup, camera, target, X, Z, z_mm, G_true, G_rec, dets, pts)


@dataclass
class ToolCentreSet:
    offset_mm: NDArray[np.float64]
    uv_px: NDArray[np.float64]
    flange_mm: NDArray[np.float64]
    rz_deg: NDArray[np.float64]
    npoint_uv_px: NDArray[np.float64]
    npoint_xy_mm: NDArray[np.float64]


def simulate_tool_centre(rng: np.random.Generator, camera: CameraModel, *, n_angles: int = 7,
                         flange_mm: tuple[tuple[float, float], ...] = ((450.0, 50.0), (490.0, 20.0)),
                         arc_deg: float = 180.0, pixel_sigma_px: float = 0.05,
                         offset_mm: tuple[float, float] = (32.5, -18.0)) -> ToolCentreSet:
    """A fixed camera 0.5 m above the table (``calibration.synthetic.simulate_npoint``'s cell, whose
    noisy jog-to-mark pairs come with it) sees a feature ``offset_mm`` from the flange axis while the
    tool turns to ``n_angles`` angles over ``arc_deg`` at each flange position."""
    from calibration.synthetic.npoint import simulate_npoint

    seed = int(rng.integers(1 << 31))
    np_uv, np_xy, _ = simulate_npoint(np.random.default_rng(seed), camera)
    # the same camera pose again (same seed), to project the feature through it
    sub = np.random.default_rng(seed)
    a = sub.uniform(0, 2 * np.pi)
    tilt = exp_so3(np.radians(1.5) * np.array([np.cos(a), np.sin(a), 0.0]))
    yaw = exp_so3([0.0, 0.0, sub.uniform(-0.3, 0.3)])
    R_base_cam = yaw @ tilt @ np.diag([1.0, -1.0, -1.0])
    centre = np.array([0.45, 0.05, 0.0])
    T_base_cam = make_transform(R_base_cam, centre - R_base_cam @ np.array([0.0, 0.0, 0.5]))
    T_cam_base = invert(T_base_cam)
    o = np.array(offset_mm)
    uv, fl, rz = [], [], []
    for f in flange_mm:
        start = rng.uniform(-180.0, 180.0)
        for ang in start + np.linspace(0.0, arc_deg, n_angles):
            c, s = np.cos(np.radians(ang)), np.sin(np.radians(ang))
            p = np.array(f) + np.array([c * o[0] - s * o[1], s * o[0] + c * o[1]])
            P = np.array([p[0] * 1e-3, p[1] * 1e-3, 0.0])
            uv.append(camera.project((T_cam_base[:3, :3] @ P + T_cam_base[:3, 3])[None])[0])
            fl.append(f)
            rz.append((ang + 180.0) % 360.0 - 180.0)
    uv_arr = np.array(uv) + rng.normal(0.0, pixel_sigma_px, (len(uv), 2))
    return ToolCentreSet(o, uv_arr, np.array(fl, dtype=np.float64), np.array(rz), np_uv, np_xy)


def write_example(kind: str, folder: str, seed: int = 0) -> dict[str, str]:
    """Write a virtual data set for the command line into ``folder`` and return its files.

    ``scara``: an eye-in-hand SCARA-style cell, 14 stations (``poses.csv``, ``detections.json``,
    ``cam.json``, ``board.yaml``; the target origin is 12 mm above the base). ``tcp``: a fixed
    camera's jog-to-mark pairs (``pairs.csv``) and the tool turned to 7 angles at 2 flange
    positions (``rot.csv``); the true offset is (32.5, -18.0) mm.
    """
    import json
    from pathlib import Path

    from calibration.geometry import transform_to_ur_pose
    from calibration.io import write_pairs_csv, write_poses_csv
    from calibration.targets import Chessboard

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    cam = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 958.0], [0, 1900.0, 603.0], [0, 0, 1]]),
                      np.array([-0.1, 0.05, 0.0, 0.0, 0.0]))
    rng = np.random.default_rng(seed)
    if kind == "scara":
        board = Chessboard(8, 6, 25.0)
        s = simulate_scara("eye-in-hand", 14, rng, camera=cam, target=board)
        names = [d.image for d in s.detections]
        write_poses_csv(out / "poses.csv", names, np.array([transform_to_ur_pose(g) for g in s.G_recorded]))
        (out / "detections.json").write_text(json.dumps([d.to_json() for d in s.detections]))
        (out / "cam.json").write_text(json.dumps(cam.to_dict()))
        (out / "board.yaml").write_text("type: chessboard\ncols: 8\nrows: 6\nsquare_mm: 25.0\n")
        (out / "truth.json").write_text(json.dumps({"T_tool_cam": s.X_true.tolist(), "T_base_target":
                                                    s.Z_true.tolist(), "target_z_mm": s.target_z_mm}))
        return {k: str(out / k) for k in ("poses.csv", "detections.json", "cam.json", "board.yaml", "truth.json")}
    if kind == "tcp":
        t = simulate_tool_centre(rng, cam)
        write_pairs_csv(out / "pairs.csv", t.npoint_uv_px, t.npoint_xy_mm)
        rows = ["u_px,v_px,x_mm,y_mm,rz_deg"] + [
            f"{u:.4f},{v:.4f},{x:.3f},{y:.3f},{r:.3f}"
            for (u, v), (x, y), r in zip(t.uv_px, t.flange_mm, t.rz_deg, strict=True)]
        (out / "rot.csv").write_text("\n".join(rows) + "\n")
        (out / "cam.json").write_text(json.dumps(cam.to_dict()))
        return {k: str(out / k) for k in ("pairs.csv", "rot.csv", "cam.json")}
    raise ValueError(f"unknown example {kind!r}: scara or tcp")

