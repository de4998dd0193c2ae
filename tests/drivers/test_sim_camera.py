"""The simulated camera with the scene's imaging defects: off by default, seeded, and usable."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration import geometry as g
from calibration.detect import detect
from drivers.camera.sim import SimCamera, SimCameraSettings
from drivers.sim.imaging import Imaging, PlanarObject, render_scene, vignetting_factor
from drivers.sim.scene import BUILTIN_SCENE, ImagingSpec, SceneError, load_scene, scene_from_dict
from drivers.sim.world import SimWorld, forget_worlds, part_mask

DEFECTS_SCENE = BUILTIN_SCENE.with_name("virtual-cell-real-defects.yaml")
NEW_DEFECTS = ("vignetting", "focus_distance_m", "defocus_sigma_px_per_diopter", "motion_blur_px",
               "gain_dn_per_e", "read_noise_dn", "gamma", "jpeg_quality")


@pytest.fixture(autouse=True)
def fresh_worlds() -> Iterator[None]:
    forget_worlds()
    yield
    forget_worlds()


def test_defects_are_off_by_default_and_in_the_builtin_scene() -> None:
    """The built-in cell renders as before: every new option at its 'off' value."""
    spec = load_scene().camera.imaging
    off = Imaging()
    for name in NEW_DEFECTS:
        assert getattr(spec, name) == getattr(off, name) == getattr(ImagingSpec(), name), name


def test_the_real_defects_scene_turns_each_defect_on() -> None:
    spec = load_scene(DEFECTS_SCENE).camera.imaging
    for name in NEW_DEFECTS:
        assert getattr(spec, name) != getattr(ImagingSpec(), name), name
    assert load_scene(DEFECTS_SCENE).robot.kinematic_error is not None


def _frames(scene_path: Path, seed: int, n: int = 3) -> list[np.ndarray]:
    scene = load_scene(scene_path).model_copy(update={"seed": seed})
    world = SimWorld(scene)
    home = g.ur_pose_to_transform(scene.robot.home)
    frames = []
    for k in range(n):
        T = home.copy()
        T[0, 3] += 0.004 * k
        world.place_tool(T)
        frames.append(world.render())
    return frames


def test_defect_frames_are_deterministic_per_seed() -> None:
    a = _frames(DEFECTS_SCENE, 3)
    b = _frames(DEFECTS_SCENE, 3)
    c = _frames(DEFECTS_SCENE, 4)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not any(np.array_equal(x, y) for x, y in zip(a, c, strict=True))


def test_sim_camera_grabs_defect_frames_by_scene_and_seed() -> None:
    cam = SimCamera("cam0", SimCameraSettings(scene=str(DEFECTS_SCENE), seed=5))
    cam.open()
    first = cam.grab().pixels
    cam.close()
    forget_worlds()
    again = SimCamera("cam0", SimCameraSettings(scene=str(DEFECTS_SCENE), seed=5))
    again.open()
    assert np.array_equal(again.grab().pixels, first)
    assert first.shape == (960, 1280) and first.dtype == np.uint8


def test_defect_frame_is_darker_at_the_corners_as_configured() -> None:
    """Vignetting (30 %), the light gradient and gamma 2.2 on the table's flat grey: a corner's
    median against a table patch nearer the centre is what the model predicts."""
    img = _frames(DEFECTS_SCENE, 1, n=1)[0].astype(float)
    im = load_scene(DEFECTS_SCENE).camera.imaging
    vig = vignetting_factor(1280, 960, im.vignetting)

    def linear_gain(u: int, v: int) -> float:
        return float(vig[v, u]) * (1.0 + im.light_gradient * (u / 1279 - 0.5))

    patch = np.median(img[460:500, 980:1020])  # table only (between the parts)
    for (v0, u0) in ((920, 1240), (0, 1240)):
        corner = np.median(img[v0 : v0 + 40, u0 : u0 + 40])
        expected = (linear_gain(u0 + 20, v0 + 20) / linear_gain(1000, 480)) ** (1 / im.gamma)
        assert corner / patch == pytest.approx(expected, abs=0.02)
        assert corner / patch < 0.9


def test_the_plate_is_found_in_a_defect_frame_near_its_projection() -> None:
    """The benches can use it: every mark detected, within a fraction of a pixel of the truth."""
    scene = load_scene(DEFECTS_SCENE)
    world = SimWorld(scene)
    img = world.render()
    plate = scene.targets[0]
    det = detect(img, plate.parsed())
    assert det.found, det.reason
    truth_T = g.invert(world.T_base_cam()) @ world.T_base_target(plate.name)
    points = plate.parsed().points()
    truth = world.camera_model.project(g.transform_points(truth_T, points.xyz_m))
    row = {int(i): k for k, i in enumerate(points.ids)}
    err = np.linalg.norm(det.uv - truth[[row[int(i)] for i in det.ids]], axis=1)
    assert det.ids.size == points.ids.size
    assert np.median(err) < 0.05, f"median {np.median(err):.3f} px"


def test_a_bad_defect_setting_is_refused_with_its_key_path(tmp_path: Path) -> None:
    data = yaml.safe_load(DEFECTS_SCENE.read_text())
    data["camera"]["imaging"]["vignetting"] = 1.5
    with pytest.raises(SceneError, match=r"camera\.imaging\.vignetting"):
        scene_from_dict(data, "bad.yaml")
    data["camera"]["imaging"]["vignetting"] = 0.2
    data["camera"]["imaging"]["jpeg_quality"] = 0
    with pytest.raises(SceneError, match=r"camera\.imaging\.jpeg_quality"):
        scene_from_dict(data, "bad.yaml")


def test_parts_as_their_own_planes_render_as_painted_on_the_table() -> None:
    """The world hands each part to the renderer as a bounded plane in the table's frame; the
    image (and depth) is exactly that of one table plane with the parts painted on it."""
    scene = load_scene()
    world = SimWorld(scene)

    def painted(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = np.full(x.shape, scene.table.reflectance)
        sx, sy = scene.table.size_m
        out[(np.abs(x) > sx / 2) | (np.abs(y) > sy / 2)] = np.nan
        for part in scene.parts:
            inside = part_mask(part.outline_mm, part.holes_mm, part.x_mm, part.y_mm, part.angle_deg, x, y)
            out[inside] = part.reflectance
        return out

    home = g.ur_pose_to_transform(scene.robot.home)
    seen = 0
    for rotvec, shift in (([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), ([0.1, -0.15, 0.3], [0.12, -0.03, 0.02])):
        world.place_tool(home @ g.make_transform(g.rotvec_to_matrix(rotvec), shift))
        objs = world.planar_objects()
        T_cam_table = g.invert(world.T_base_cam()) @ g.make_transform(np.eye(3), [0.0, 0.0, scene.table.z_m])
        reference = [objs[0], PlanarObject(T_cam_table, painted)]
        a, da = render_scene(world.camera_model, objs, 0.45, 4)
        b, db = render_scene(world.camera_model, reference, 0.45, 4)
        assert np.array_equal(a, b) and np.array_equal(da, db)
        seen += int(np.sum(np.isin(a, [p.reflectance for p in scene.parts])))
    assert seen > 1000  # the parts are in view
