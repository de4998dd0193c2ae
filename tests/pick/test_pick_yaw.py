"""What ``part_yaw_deg`` means on the virtual cell: the part's turn from the teach image,
counter-clockwise on screen (0: it lies as taught), with ``base_yaw_deg`` its yaw in the robot base
frame and ``sigma_yaw_deg`` the match's own 1-sigma.

The expected image turn is computed from the world's truth: the part's reference point and a point
along one of its directions projected through the true camera, before and after the part is turned.
The direction is the one that lay along the image's x axis when taught (the model's x axis): seen in
perspective, other directions turn by a few tenths of a degree more or less on screen.
"""

from __future__ import annotations

import math

import numpy as np

from cellctl.pick.flow import run_pick
from cellctl.services import Services
from drivers.sim.world import SimWorld, world_for
from tests.cellctl.test_pick_flow import SEED, part_pixel, services, teach_bracket

__all__ = ["services"]  # the fixture, shared with tests/cellctl/test_pick_flow.py


def _image_angle_deg(world: SimWorld, phi_deg: float = 0.0) -> float:
    """The on-screen direction (counter-clockwise, degrees) of the first part's direction ``phi_deg``
    (part frame, from its x axis)."""
    part = world.scene.parts[0]
    a = math.radians(part.angle_deg + phi_deg)
    u0, v0 = part_pixel(world, part.x_mm, part.y_mm)
    u1, v1 = part_pixel(world, part.x_mm + 10.0 * math.cos(a), part.y_mm + 10.0 * math.sin(a))
    return math.degrees(math.atan2(-(v1 - v0), u1 - u0))


def _horizontal_direction(world: SimWorld) -> float:
    """The part-frame direction (deg) that the camera shows along the image's x axis (secant steps)."""
    a, b = 0.0, -_image_angle_deg(world, 0.0)
    fa = _image_angle_deg(world, a)
    for _ in range(8):
        fb = _image_angle_deg(world, b)
        if abs(fb) < 1e-9 or fb == fa:
            break
        a, b, fa = b, b - fb * (b - a) / (fb - fa), fb
    return b


def _wrap(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def test_an_unmoved_part_reports_zero_yaw_within_its_sigma(services: Services) -> None:
    teach_bracket(services)
    best = run_pick(services, 1)["picks"][0]
    sigma = best["uncertainty"]["sigma_yaw_deg"]
    assert sigma is not None and 0.0 < sigma < 0.2  # a part found to hundredths of a degree says so
    assert abs(best["part_yaw_deg"]) <= 3.0 * sigma + 1e-3
    assert "base_yaw_deg" in best and math.isfinite(best["base_yaw_deg"])


def test_a_turned_part_reports_its_turn_on_screen(services: Services) -> None:
    teach_bracket(services)
    world = world_for(None, SEED)
    part = world.scene.parts[0]
    phi = _horizontal_direction(world)
    assert abs(_image_angle_deg(world, phi)) < 1e-6
    base0 = run_pick(services, 1)["picks"][0]["base_yaw_deg"]
    part.angle_deg += 30.0
    expected = _wrap(_image_angle_deg(world, phi))
    best = run_pick(services, 1)["picks"][0]
    sigma = best["uncertainty"]["sigma_yaw_deg"]
    # the render's own sub-pixel model (and the part's true pose) differ from the projected axis by
    # far less than a tenth of a degree; the match's sigma is of the order of 0.01 deg
    assert abs(_wrap(best["part_yaw_deg"] - expected)) <= 3.0 * sigma + 0.05
    assert abs(abs(expected) - 30.0) < 2.0  # the camera looks nearly straight down
    # the base-frame yaw turned by the true 30 deg (the sense of base z, whatever the camera's)
    assert abs(abs(_wrap(best["base_yaw_deg"] - base0)) - 30.0) < 0.2
    assert np.isfinite(best["gripper_yaw_deg"])
