"""A pick's position 1-sigma (``uncertainty.sigma_mm``) carries the match's own pixel 1-sigma.

The mapping propagates the match's ``sigma_px`` (rim-refined or not) through the local mm/px scale on top
of the calibration's own uncertainty, for a hand-eye and an N-point map alike (``ActiveMapping.map``); a
blurred, low-contrast match of a part so reports a larger ``sigma_mm`` than a sharp one, and neither less
than the calibration alone. In process on the virtual cell with its true calibration (cheap)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from calibration import geometry as g
from calibration.camera_model import CameraModel
from calibration.npoint import fit_npoint
from calibration.synthetic.npoint import simulate_npoint
from cellctl.config import default_config_text
from cellctl.mapping import ActiveMapping, active_mapping
from cellctl.pick.candidate import candidate, search_params
from cellctl.pick.model import teach
from cellctl.pick.recipe import Recipe
from cellctl.services import Services
from drivers.sim.world import world_for
from tests.support.truth import calibrated_services
from vision.recognize import recognize

SEED = 11
HE = {"setup": "eye-in-hand", "T_base_target": np.eye(4).tolist(),
      "uncertainty": {"covariance": (np.eye(6) * 1e-10).tolist()}, "pixel_sigma_px": 0.05,
      "robot_noise": {"sigma_mm": 0.02, "sigma_deg": 0.005}}


@pytest.fixture()
def services(tmp_path: Path) -> Iterator[Services]:
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp_path / "cell.db")}
    data["cameras"]["cam0"]["settings"]["seed"] = SEED
    data["robots"]["robot0"]["settings"]["seed"] = SEED
    with calibrated_services(data, SEED) as svc:
        yield svc


def _blurred(image: np.ndarray) -> np.ndarray:
    """The same picture out of focus, at a quarter of its contrast, with sensor noise."""
    soft = cv2.GaussianBlur(image, (0, 0), 2.5).astype(np.float64)
    noise = np.random.default_rng(0).normal(0.0, 4.0, image.shape)
    return np.asarray(np.clip(128.0 + 0.3 * (soft - 128.0) + noise, 0, 255), dtype=np.uint8)


def test_a_blurred_match_reports_a_larger_sigma_mm_than_a_sharp_one(services: Services) -> None:
    world = world_for(None, SEED)
    part = world.scene.parts[0]
    uv = world.camera_model.project(g.transform_points(g.invert(world.T_base_cam()),
                                                       [part.x_mm * 1e-3, part.y_mm * 1e-3, 0.0]))[0]
    sharp = world.render()
    model = teach(sharp, (uv[0] - 100, uv[1] - 100, 200, 200), mode="shape", name="bracket")
    recipe = Recipe(name="bracket", models=[model.to_dict()], plane_z_mm=0.0, grasp_z_mm=5.0,
                    approach_height_mm=40.0)
    params = dataclasses.replace(search_params(recipe), timeout_s=None)  # (not the 1 s budget, under load)
    robot = services.cell.robot("robot0").ensure_open()
    T_capture = robot.state().T_base_tool
    mapping = active_mapping(services, "cam0", "robot0")
    found = {}
    for name, image in (("sharp", sharp), ("blurred", _blurred(sharp))):
        matches = recognize(recipe.part_models(), image, params).matches
        assert matches, name
        found[name] = candidate(mapping, recipe, matches[0], T_capture, 0.0, robot)
    s_sharp, s_blur = (found[k].match.sigma_px for k in ("sharp", "blurred"))
    assert math.isfinite(s_sharp) and s_blur > 5 * s_sharp, (s_sharp, s_blur)
    for c in found.values():
        # the calibration alone (no pixel noise): the floor neither may go below
        cal = mapping.map(np.array([c.match.u_px, c.match.v_px]), 0.0, T_capture, pixel_sigma_px=0.0).sigma_mm
        assert c.sigma_mm[0] >= cal[0] and c.sigma_mm[1] >= cal[1]
        # exactly the match's pixel sigma propagated, as the mapping does it
        own = mapping.map(np.array([c.match.u_px, c.match.v_px]), 0.0, T_capture,
                          pixel_sigma_px=c.match.sigma_px).sigma_mm
        assert c.sigma_mm == pytest.approx([float(x) for x in own], rel=1e-9)
    assert found["blurred"].sigma_mm[0] > found["sharp"].sigma_mm[0] * 1.05
    assert found["blurred"].sigma_mm[1] > found["sharp"].sigma_mm[1] * 1.05
    assert found["blurred"].sigma_mm[2] == pytest.approx(found["sharp"].sigma_mm[2], rel=0.05)
    # the answer shows the pixel 1-sigma it carried, for a plain (not rim-refined) model too
    for c in found.values():
        answer = c.as_json()
        assert "refine" not in answer and answer["sigma_px"] == pytest.approx(c.match.sigma_px, rel=1e-12)


def _local_scale(mapping: ActiveMapping, uv: np.ndarray, T: np.ndarray | None) -> np.ndarray:
    """d(x, y)/d(u, v) at ``uv`` (mm/px, 2x2), by central differences of the mapped point."""
    def xy(p: np.ndarray) -> np.ndarray:
        return np.asarray(mapping.map(p, 0.0, T, with_uncertainty=False).xyz_mm[:2])
    return np.stack([(xy(uv + d) - xy(uv - d)) / 2.0 for d in (np.array([1.0, 0.0]), np.array([0.0, 1.0]))], axis=1)


def _mappings() -> list[tuple[ActiveMapping, np.ndarray, np.ndarray | None]]:
    world = world_for(None, SEED)
    truth = world.truth()
    camera = CameraModel.from_dict(truth["camera"])
    he = ActiveMapping("handeye", 1, {**HE, "T_tool_cam": truth["T_tool_cam"]}, camera, None, "handeye")
    T = world.T_base_cam() @ g.invert(np.asarray(truth["T_tool_cam"], dtype=np.float64))
    uv_px, xy_mm, _ = simulate_npoint(np.random.default_rng(3), camera)
    npm = ActiveMapping("npoint", 2, fit_npoint(uv_px, xy_mm).to_json(), None, None)
    return [(he, np.array([700.0, 400.0]), T), (npm, np.asarray(uv_px).mean(axis=0), None)]


@pytest.mark.parametrize("which", [0, 1], ids=["handeye", "npoint"])
def test_the_mappings_sigma_grows_with_the_pixel_sigma_as_the_local_scale_says(which: int) -> None:
    mapping, uv, T = _mappings()[which]
    J = _local_scale(mapping, uv, T)
    var0 = mapping.map(uv, 0.0, T, pixel_sigma_px=0.0).sigma_mm[:2] ** 2
    previous = -1.0
    for s_px in (0.05, 0.5, 2.0):
        got = mapping.map(uv, 0.0, T, pixel_sigma_px=s_px).sigma_mm[:2]
        want = np.sqrt(var0 + s_px**2 * np.sum(J**2, axis=1))
        assert got == pytest.approx(want, rel=0.01), (s_px, got, want)
        assert got[0] > previous
        previous = float(got[0])
    # None: the calibration's own pixel sigma, as before
    default_px = 0.05 if mapping.kind == "handeye" else 0.1
    assert mapping.map(uv, 0.0, T).sigma_mm[:2] == pytest.approx(
        mapping.map(uv, 0.0, T, pixel_sigma_px=default_px).sigma_mm[:2], rel=1e-9)
