"""Fiducial marks measured in rendered frames of the production scene: a still camera reads ~0, a bump
reads its size in mm and degrees, and the re-solve finds the bumped camera's true pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration import geometry as g
from calibration.drift.fiducials import FiducialError, find_marks, measure, predict_px, resolve
from drivers.sim.camera_fault import Fault
from drivers.sim.scene import BUILTIN_SCENES, load_scene
from drivers.sim.world import SimWorld


@pytest.fixture(scope="module")
def world() -> SimWorld:
    w = SimWorld(load_scene(BUILTIN_SCENES["production"]))
    w.place_tool(g.ur_pose_to_transform([0.45, -0.30, 0.25, math.pi, 0.0, 0.0]))  # the arm out of view
    return w


def _seen(world: SimWorld, fault: Fault) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    world.camera_fault.set(Fault())
    T_cal = world.T_base_cam()  # the calibration: the camera's pose before the bump
    world.camera_fault.set(fault)
    X = np.array([[m.x_mm, m.y_mm, m.z_mm] for m in world.scene.fiducials]) * 1e-3
    uv = find_marks(world.render(), predict_px(world.camera_model, T_cal, X), 40.0, 5.6)
    return T_cal, X, uv


def test_a_still_camera_reads_near_zero(world: SimWorld) -> None:
    T_cal, X, uv = _seen(world, Fault())
    m = measure(world.camera_model, T_cal, uv, X)
    assert m.seen == 6 and m.drift_px < 0.05 and m.drift_mm < 0.02 and m.drift_deg < 0.01, m
    assert m.sigma_mm < 0.02


@pytest.mark.parametrize(("fault", "mm", "deg"), [
    (Fault((0.3, 0.0, 0.0)), 0.3, 0.0),
    (Fault((0.0, -0.5, 0.0)), 0.5, 0.0),
    (Fault(rot_deg=(0.0, 0.0, 0.05)), None, 0.05),
    (Fault(rot_deg=(0.05, 0.0, 0.0)), None, 0.05),
])
def test_a_bump_reads_its_size_and_the_resolve_finds_the_true_pose(world: SimWorld, fault: Fault,
                                                                    mm: float | None, deg: float) -> None:
    T_cal, X, uv = _seen(world, fault)
    m = measure(world.camera_model, T_cal, uv, X)
    assert m.seen == 6
    if mm is not None:
        assert abs(m.drift_mm - mm) < 0.03, m
    else:
        assert m.drift_mm > 0.1, m  # a turn of 0.05 deg moves the table's points by 0.2-0.45 mm
    assert abs(m.drift_deg - deg) < 0.01, m
    r = resolve(world.camera_model, T_cal, uv, X)
    rot, trans = g.transform_error(r.T_base_cam, world.T_base_cam())
    assert trans * 1e3 < 0.1 and math.degrees(rot) < 0.005 and r.rms_px < 0.1, (trans, rot, r)
    world.camera_fault.set(Fault())


def test_too_few_fiducials_are_said(world: SimWorld) -> None:
    T_cal, X, uv = _seen(world, Fault())
    uv[:4] = np.nan
    with pytest.raises(FiducialError, match="2 of 6 fiducials seen"):
        measure(world.camera_model, T_cal, uv, X)
    with pytest.raises(FiducialError, match="needs 4"):
        resolve(world.camera_model, T_cal, uv, X)
