"""The belt's pieces without a service: the sim belt and its encoder, the queue, the meeting plan, the
encoder watch and the belt fit of ``conveyor-calibrate`` (fast, in-process)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from cellctl.production.belt import BeltCalibration, BeltPart, BeltQueue, BeltWatch, Meeting, Missed, plan_meeting
from cellctl.routines.conveyor_calibrate import fit_belt
from drivers.sim.conveyor import BeltSpec, SimBelt
from drivers.sim.scene import load_scene
from drivers.sim.world import SimWorld


def test_the_belt_moves_at_its_speed_and_its_encoder_counts_the_travel() -> None:
    belt = SimBelt(BeltSpec(speed_mm_s=200.0, latch_jitter_ms=0.0), seed=1)
    t0 = time.monotonic()
    assert belt.position_m(t0 + 2.0) - belt.position_m(t0) == pytest.approx(0.4, abs=1e-9)
    assert belt.ticks(t0 + 2.0) - belt.ticks(t0) == pytest.approx(4000, abs=1)
    belt.set_speed(0.0)
    t1 = time.monotonic()
    assert belt.ticks(t1 + 5.0) == belt.ticks(t1)
    with pytest.raises(ValueError, match="outside 0..300"):
        belt.set_speed(301.0)


def test_a_slowly_varying_belt_swings_about_its_set_speed() -> None:
    belt = SimBelt(BeltSpec(speed_mm_s=100.0, speed_variation=0.2, variation_period_s=10.0), seed=1)
    t0 = time.monotonic()
    speeds = [belt.speed_mm_s(t0 + k * 0.5) for k in range(20)]
    assert max(speeds) == pytest.approx(120.0, abs=1.0) and min(speeds) == pytest.approx(80.0, abs=1.0)
    travel = belt.position_m(t0 + 10.0) - belt.position_m(t0)  # one whole period: the set speed's travel
    assert travel == pytest.approx(1.0, abs=0.01)


def test_the_latched_count_jitters_by_the_stated_latch_jitter() -> None:
    belt = SimBelt(BeltSpec(speed_mm_s=300.0, latch_jitter_ms=1.0, ticks_per_m=1e6), seed=4)
    t = time.monotonic()
    off = np.array([belt.latched_ticks(t) - belt.ticks(t) for _ in range(400)], dtype=float)
    # 1 ms at 300 mm/s is 0.3 mm = 300 ticks at 1e6 ticks/m
    assert np.std(off) == pytest.approx(300.0, rel=0.15) and abs(np.mean(off)) < 40


def test_parts_ride_the_belt_and_fall_off_its_end() -> None:
    world = SimWorld(load_scene("conveyor"))
    assert world.belt is not None
    world.belt.set_speed(300.0)
    s = world.belt.position_m()
    first = dict((p.id, T) for p, T in world.production.poses(world.T_base_tool_true, s))  # type: ignore[union-attr]
    assert first[0][0, 3] == pytest.approx(0.040 + s, abs=1e-9)  # the first part: at x = 40 mm at the start
    assert abs(math.atan2(first[0][1, 0], first[0][0, 0])) < 1e-9  # upright: the one to teach
    later = dict((p.id, (p.state, T)) for p, T in world.production.poses(world.T_base_tool_true, s + 0.25))  # type: ignore[union-attr]
    assert later[0][1][0, 3] - first[0][0, 3] == pytest.approx(0.25, abs=0.002)
    gone = [p.state for p, _ in world.production.poses(world.T_base_tool_true, s + 1.0)]  # type: ignore[union-attr]
    assert "in_area" in gone  # a snapshot at a later travel lists, it does not change states
    world.belt.set_speed(0.0)
    part0 = world.production.parts[0]  # type: ignore[union-attr]
    part0.belt_s_m = world.belt.position_m() - 1.0  # as if the belt had carried it 1 m further
    states = {p.id: p.state for p, _ in world.production.poses(world.T_base_tool_true)}  # type: ignore[union-attr]
    assert states[0] == "fallen"
    truth = world.truth()
    assert set(truth["conveyor"]) >= {"ticks", "speed_mm_s", "window_mm"}
    assert set(truth["camera"]) >= {"T_base_cam", "K", "dist"}


def _part(x_mm: float, ticks: int, yaw_deg: float = 0.0, key: int = 1) -> BeltPart:
    from types import SimpleNamespace

    T = np.eye(4)
    a = math.radians(yaw_deg)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[0, 3], T[2, 3] = x_mm * 1e-3, 0.006
    app = T.copy()
    app[2, 3] += 0.03
    cand = SimpleNamespace(T_base_part=T, T_pick=T, T_approach=app, sigma_mm=[0.1, 0.1, 0.5], base_yaw_deg=yaw_deg)
    return BeltPart(key, cand, ticks, None)  # type: ignore[arg-type]


BELT = BeltCalibration(np.array([1.0, 0.0, 0.0]), 10000.0)


def test_the_same_part_in_two_pictures_is_one_part_and_a_neighbour_is_another() -> None:
    q = BeltQueue(BELT)
    first = _part(100.0, 1000, 30.0)
    assert q.add([first.cand], 1000, 1).added == 1  # type: ignore[list-item]
    again = _part(150.2, 1500, 30.5)  # 500 ticks = 50 mm later, 0.2 mm off
    s = q.add([again.cand], 1500, 2)  # type: ignore[list-item]
    assert (s.added, s.merged) == (0, 1) and s.offsets_mm[0] == pytest.approx(0.2, abs=1e-6)
    neighbour = _part(190.0, 1500, 31.0)  # touching the first, 40 mm further along
    assert q.add([neighbour.cand], 1500, 3).added == 1 and len(q) == 2  # type: ignore[list-item]
    turned = _part(150.0, 1500, 80.0)  # where the first is, turned: not the same part
    assert q.add([turned.cand], 1500, 4).added == 1  # type: ignore[list-item]
    picked = q.downstream_first(1500)[0]
    q.remove(picked)
    assert q.add([_part(250.0, 2100, 31.0).cand], 2100, 5).done == 1  # type: ignore[list-item]


def test_the_meeting_is_inside_the_window_or_the_part_is_missed() -> None:
    tool = np.array([0.55, -0.30, 0.25])
    part = _part(100.0, 0)
    m = plan_meeting(part, BELT, 0, 100.0, tool, 0.036, (350.0, 740.0), 1.0, 2.0, 0.4)
    assert isinstance(m, Meeting) and 350.0 <= m.x_mm <= 740.0 - 100.0 * 0.4 and m.ticks == round((m.x_mm - 100) * 10)
    late = plan_meeting(_part(720.0, 0), BELT, 0, 100.0, tool, 0.036, (350.0, 740.0), 1.0, 2.0, 0.4)
    assert isinstance(late, Missed) and "past the window" in late
    fast = plan_meeting(_part(330.0, 0), BELT, 0, 300.0, tool, 0.036, (350.0, 500.0), 0.2, 2.0, 0.4)
    assert isinstance(fast, Missed)
    still = plan_meeting(_part(100.0, 0), BELT, 0, 0.0, tool, 0.036, (350.0, 740.0), 1.0, 2.0, 0.4)
    assert isinstance(still, str) and not isinstance(still, Missed) and "belt stopped" in still
    inside = plan_meeting(_part(400.0, 0), BELT, 0, 0.0, tool, 0.036, (350.0, 740.0), 1.0, 2.0, 0.4)
    assert isinstance(inside, Meeting) and inside.x_mm == pytest.approx(400.0)


def test_the_meeting_is_planned_with_the_robots_own_timing_and_the_lead() -> None:
    """``travel`` (the robot's timing of the move to the approach pose) and ``lead_s`` set when the arm can be
    above the part: a slower arm or a longer lead meets the part further along, never past the window."""
    tool = np.array([0.55, -0.30, 0.25])
    part = _part(360.0, 0)  # inside the window already: no slack to spare
    seen: list[np.ndarray] = []

    def travel(T: np.ndarray) -> float:
        seen.append(T)
        return 0.5

    m = plan_meeting(part, BELT, 0, 100.0, tool, 0.036, (350.0, 740.0), 1.0, 2.0, 0.4, travel=travel)
    assert isinstance(m, Meeting) and m.x_mm == pytest.approx(410.0, abs=1.0) and m.wait_s < 0.02
    assert seen[-1][2, 3] == pytest.approx(0.036) and seen[-1][0, 3] == pytest.approx(m.x_mm * 1e-3, abs=1e-3)
    later = plan_meeting(part, BELT, 0, 100.0, tool, 0.036, (350.0, 740.0), 1.0, 2.0, 0.4, travel=travel, lead_s=0.3)
    assert isinstance(later, Meeting) and later.x_mm == pytest.approx(440.0, abs=1.0)
    slow = plan_meeting(part, BELT, 0, 100.0, tool, 0.036, (350.0, 740.0), 1.0, 2.0, 0.4,
                        travel=lambda T: 3.5)
    assert isinstance(slow, Missed) and "cannot reach it inside the window" in slow


def test_the_watch_measures_the_speed_and_catches_a_jump() -> None:
    w = BeltWatch(10000.0)
    for k in range(30):
        assert w.sample(k * 20, t=k * 0.02) is None  # 20 ticks / 20 ms = 100 mm/s
    assert w.speed_mm_s() == pytest.approx(100.0, rel=1e-6)
    problem = w.sample(29 * 20 + 5000, t=30 * 0.02)
    assert problem is not None and "jumped by 5000 ticks" in problem


def test_a_thread_held_between_the_count_and_the_clock_is_not_a_jump() -> None:
    """At 100 mm/s (1 tick a ms): a count read at 1.000 s whose clock was read 30 ms later (the thread held
    by a loaded machine), then the next count read at once 4 ms after that clock: 34 ticks that came in
    34 ms, not 4. A real jump read the same way is still caught."""
    w = BeltWatch(10000.0)
    assert w.sample(1000, t=1.030, read_from_s=1.000) is None
    assert w.sample(1034, t=1.034, read_from_s=1.034) is None
    problem = w.sample(1034 + 500, t=1.038, read_from_s=1.034)
    assert problem is not None and "jumped by 500 ticks" in problem


def test_the_belt_fit_recovers_direction_and_ticks_per_metre_within_its_sigma() -> None:
    rng = np.random.default_rng(3)
    d = np.array([0.999, 0.04, 0.0])
    d /= np.linalg.norm(d)
    misses = 0
    for _ in range(40):
        ticks = np.sort(rng.uniform(0, 3000, 8))
        pts = np.array([0.1, 0.02, 0.0]) + np.outer(ticks / 9876.0, d) + rng.normal(0, 5e-5, (8, 3))
        out = fit_belt(ticks, pts)
        err = abs(out["ticks_per_m"] - 9876.0)
        misses += err > 3 * out["sigma_ticks_per_m"]
        ang = math.degrees(math.acos(min(1.0, float(np.dot(out["direction_base"], d)))))
        assert ang < 5 * out["sigma_direction_deg"] + 1e-3
    assert misses <= 2  # 3-sigma: about 1 in 370 expected


def test_the_plc_reads_missed_window_and_the_queue_length_after_every_older_register() -> None:
    from cellctl.plc import modbus_map as mm

    assert (mm.address("MISSED_WINDOW"), mm.address("QUEUE_LENGTH"), mm.MAP_END) == (mm.END, mm.END + 2, mm.END + 3)
    assert all(p.end < mm.END for name, p in mm.REGISTERS.items() if name not in ("MISSED_WINDOW", "QUEUE_LENGTH"))
    words = mm.conveyor_block_words(70000, 3)
    assert mm.words_int32(words[:2]) == 70000 and words[2] == 3


def test_a_belt_configured_still_never_ran_at_the_scenes_speed() -> None:
    """The world (and its belt at the scene's 100 mm/s) is made by the first device that opens; the
    conveyor's own setting, applied when it opens later, holds from the belt's start: a belt configured
    at 0 has not moved. Once the speed was changed, a setting changes it from now on (no travel undone)."""
    belt = SimBelt(BeltSpec(speed_mm_s=100.0, latch_jitter_ms=0.0), seed=1)
    time.sleep(0.05)
    belt.configure(0.0)
    assert belt.position_m() == 0.0 and belt.ticks() == 0
    belt.set_speed(100.0)
    time.sleep(0.05)
    moved = belt.position_m()
    belt.configure(0.0)
    assert belt.position_m() == pytest.approx(moved, abs=2e-3) and moved > 0.004


def test_the_grasp_is_folded_to_the_symmetric_one_nearest_the_tools_yaw() -> None:
    """A part seen with the grasp folded near yaw 0 and a tool turned to 170 deg: the planner takes the gripper's
    other (180 deg) grasp, a turn of 20 deg instead of 160, at the same pick point; nothing else changes."""
    from types import SimpleNamespace

    from cellctl.pick.candidate import PickCandidate
    from cellctl.pick.pose import PartPose, grasp
    from cellctl.production.belt import grasp_near
    from drivers.base import MotionLimits
    from drivers.robot_base import turn_deg

    recipe = SimpleNamespace(grasp_yaw_deg=0.0, gripper_symmetry_deg=180.0, tool_rotvec_rad=[math.pi, 0.0, 0.0],
                             grasp_offset_mm=(0.0, 0.0), grasp_z_mm=0.0, tool_centre_offset_mm=None,
                             approach_height_mm=30.0)
    T = np.eye(4)
    a = math.radians(10.0)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:3, 3] = [0.5, 0.0, 0.006]
    g = grasp(recipe, PartPose(T, a, [0.1, 0.1, 0.5]), 0.0)  # type: ignore[arg-type]
    cand = PickCandidate(None, T, [0.1, 0.1, 0.5], None, 10.0, g.T_part_grip, g.T_grip_flange,  # type: ignore[arg-type]
                         g.T_pick, g.T_approach, math.degrees(g.gripper_yaw_rad))
    b = math.radians(170.0)
    tool = np.eye(4)
    tool[:3, :3] = np.array([[math.cos(b), -math.sin(b), 0], [math.sin(b), math.cos(b), 0], [0, 0, 1]]) @ np.diag(
        [1.0, -1.0, -1.0])  # pointing down, its x axis at 170 deg
    tool[:3, 3] = [0.55, -0.3, 0.25]
    limits = MotionLimits((-1000.0, 1000.0), (-1000.0, 1000.0), (-100.0, 1000.0), max_linear_speed_m_s=1.0)
    out = grasp_near(recipe, cand, tool, limits)  # type: ignore[arg-type]
    assert turn_deg(tool, cand.T_approach) == pytest.approx(160.0, abs=1e-6)
    assert turn_deg(tool, out.T_approach) == pytest.approx(20.0, abs=1e-6)
    assert (out.gripper_yaw_deg - 190.0 + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(out.T_pick[:3, 3], cand.T_pick[:3, 3], atol=1e-12)
    assert out.T_base_part is cand.T_base_part and grasp_near(recipe, out, tool, limits) is out  # type: ignore[arg-type]
