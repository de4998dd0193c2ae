"""The scene's tool feature: parsed strictly, drawn by the sim camera where the camera model puts it,
reported in the truth, absent from scenes that do not ask for it."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import yaml

from calibration import geometry as g
from calibration.detect import SpotNotFound, detect, find_spot
from calibration.targets import target_from_dict
from drivers.camera.sim import SimCamera, SimCameraSettings
from drivers.sim.scene import BUILTIN_SCENE, SceneError, load_scene, scene_from_dict
from drivers.sim.world import forget_worlds, world_for

SCENE = BUILTIN_SCENE.with_name("virtual-cell-fixed-camera.yaml")
R_DOWN = g.rotvec_to_matrix([np.pi, 0.0, 0.0])


@pytest.fixture(autouse=True)
def fresh_worlds() -> Iterator[None]:
    forget_worlds()
    yield
    forget_worlds()


def test_the_option_is_strict_and_off_in_the_builtin_scene() -> None:
    assert load_scene().tool_feature is None
    data = yaml.safe_load(SCENE.read_text())
    assert scene_from_dict(data).tool_feature is not None
    data["tool_feature"]["colour"] = "red"
    with pytest.raises(SceneError, match="tool_feature.colour: unknown key"):
        scene_from_dict(data)
    data["tool_feature"].pop("colour")
    data["tool_feature"]["diameter_mm"] = -1
    with pytest.raises(SceneError, match="tool_feature.diameter_mm"):
        scene_from_dict(data)


def test_the_disk_is_drawn_where_the_camera_model_projects_it() -> None:
    cam = SimCamera("cam0", SimCameraSettings(scene=str(SCENE)))
    cam.open()
    world = world_for(str(SCENE))
    offset_m = np.array(world.scene.tool_feature.offset_mm) * 1e-3  # type: ignore[union-attr]
    errors = []
    for k, angle in enumerate(np.linspace(-150.0, 150.0, 6)):
        feature_at = np.array([0.47 + 0.01 * k, -0.03 + 0.008 * k, 0.001])
        R = g.rotvec_to_matrix([0.0, 0.0, np.radians(angle)]) @ R_DOWN
        world.place_tool(g.make_transform(R, feature_at - R @ offset_m))
        spot = find_spot(cam.grab().pixels)
        T_base_feature = np.array(world.truth()["tool_feature"]["T_base_feature"])
        assert np.allclose(T_base_feature[:3, 3], feature_at, atol=1e-9)
        uv = world.camera_model.project(g.transform_points(g.invert(world.T_base_cam()), T_base_feature[:3, 3]))[0]
        errors.append([spot.u_px - uv[0], spot.v_px - uv[1]])
    rms = float(np.sqrt(np.mean(np.square(errors))))
    assert rms < 0.06, errors  # sub-pixel: blur 0.5 px, noise 1 DN, 8-bit rounding
    assert spot.radius_px == pytest.approx(4.0e-3 * 1400 / 0.459, rel=0.03)  # 8 mm at 0.46 m, f 1400 px


def test_out_of_view_nothing_is_drawn_and_the_plate_is_seen() -> None:
    cam = SimCamera("cam0", SimCameraSettings(scene=str(SCENE)))
    cam.open()
    frame = cam.grab()  # home: the feature is outside the view
    with pytest.raises(SpotNotFound):
        find_spot(frame.pixels)
    plate = world_for(str(SCENE)).scene.targets[0]
    assert detect(frame.pixels, target_from_dict(plate.target), "home").found
