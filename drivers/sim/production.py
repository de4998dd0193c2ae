"""Parts as objects of the virtual cell: scattered in a pick area, gripped, carried, put down.

Each part has a state: ``in_area`` (lying in the pick area), ``held`` (in the sim gripper: its pose
is the tool's true pose times where it sat in the gripper when it closed), ``placed`` (put down in
the place area) or ``dropped`` (anywhere else: it slipped, or was let go elsewhere). A part that
is let go lands on the table below where it was, level, keeping its yaw.

With a conveyor (``drivers.sim.conveyor``) the pick area is the belt: a part on it rides it (its
pose is where it lay when the belt had travelled ``belt_s_m``, moved along the belt by the travel
since), appears when it reaches the belt's start and is ``fallen`` once carried past its end.

Poses are ``T_base_part`` (4x4, metres): the part's reference point on its top face, x along the
outline's x (``drivers.sim.production_spec.PartTemplate``). The pick area's scatter is seeded and
deterministic (``drivers.sim.scatter``); so are the gripper's failures (the world's seed).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from drivers.sim.conveyor import SimBelt
from drivers.sim.production_spec import ProductionSpec
from drivers.sim.scatter import PartScatter

PartState = Literal["in_area", "held", "placed", "dropped", "fallen"]


@dataclass
class SimPart:
    """One part: its id, state and pose (the pose while held is relative to the tool)."""

    id: int
    state: PartState
    T_base_part: NDArray[np.float64]
    """Where it lies (``in_area``, ``placed``, ``dropped``); its pose when it was gripped, while held."""
    T_tool_part: NDArray[np.float64] | None = None
    belt_s_m: float | None = None
    """On a belt: its travel (m) when the part lay at ``T_base_part``; None: the part does not ride a belt."""


@dataclass(frozen=True)
class GripOutcome:
    """What one close did: the part now held (or None) and why not."""

    part_id: int | None
    reason: str


def yaw_of(T: NDArray[np.float64]) -> float:
    """The yaw (rad) of a pose's x axis about the base z axis."""
    return math.atan2(float(T[1, 0]), float(T[0, 0]))


def flat_pose(x_mm: float, y_mm: float, z_mm: float, yaw_deg: float) -> NDArray[np.float64]:
    return g.make_transform(g.rotvec_to_matrix([0.0, 0.0, math.radians(yaw_deg)]),
                            [x_mm * 1e-3, y_mm * 1e-3, z_mm * 1e-3])


class ProductionParts:
    """The parts of a production scene and what the sim gripper does to them (thread-safe)."""

    def __init__(self, spec: ProductionSpec, table_z_m: float, seed: int, belt: SimBelt | None = None) -> None:
        self.spec = spec
        self.belt = belt
        self.table_z_m = table_z_m
        self._lock = threading.RLock()
        fault_seed = [seed, spec.scatter.seed] if spec.gripper.fail_seed is None else [spec.gripper.fail_seed]
        self._rng = np.random.default_rng([*fault_seed, 0x6717])
        """The gripper's fault stream (one draw per close on a part while ``fail_probability`` > 0)."""
        self.closes_on_part = 0
        self.faults = 0
        """Closes on a part so far, and how many of them the fault stream made fail (``GET /sim/truth``)."""
        self._outline = np.asarray(spec.part.outline_mm, dtype=np.float64)
        scatter = PartScatter(spec)
        self.parts: list[SimPart] = [SimPart(k, "in_area", self.lying(*p)) for k, p in enumerate(scatter.in_area())]
        n = len(self.parts)
        for k, fixed in enumerate(spec.unreachable):
            self.parts.append(SimPart(n + k, "in_area", self.lying(fixed.x_mm, fixed.y_mm, fixed.angle_deg)))
        if belt is not None:
            n = len(self.parts)
            self.parts.extend(SimPart(n + k, "in_area", self.lying(*p), belt_s_m=0.0)
                              for k, p in enumerate(scatter.on_belt(belt.spec.parts)))
        self.closed = False
        self._slip_at_close_mm: float | None = None
        """A slip armed for the next close (``slip_at_close``), mm along the belt."""
        self.version = 0
        """Bumped whenever a part moves relative to the table (the render cache key uses it)."""

    # -- poses ------------------------------------------------------------------------------------
    @property
    def top_z_mm(self) -> float:
        return self.table_z_m * 1e3 + self.spec.part.thickness_mm

    def lying(self, x_mm: float, y_mm: float, angle_deg: float) -> NDArray[np.float64]:
        return flat_pose(x_mm, y_mm, self.top_z_mm, angle_deg)

    def pose(self, part: SimPart, T_base_tool_true: NDArray[np.float64], s_m: float | None = None
             ) -> NDArray[np.float64]:
        """The part's true pose now (a held part moves with the tool; one on the belt with the belt, at its
        travel ``s_m``: default now)."""
        if part.state == "held" and part.T_tool_part is not None:
            return T_base_tool_true @ part.T_tool_part
        if part.belt_s_m is not None and self.belt is not None:
            s = self.belt.position_m() if s_m is None else s_m
            T = part.T_base_part.copy()
            T[:3, 3] += self.belt.direction_base * (s - part.belt_s_m)
            return T
        return part.T_base_part

    def poses(self, T_base_tool_true: NDArray[np.float64], s_m: float | None = None
              ) -> list[tuple[SimPart, NDArray[np.float64]]]:
        """The parts there are and their true poses (at the belt's travel ``s_m``: default now); a part not
        yet on the belt is not listed, one carried past its end becomes ``fallen``."""
        with self._lock:
            if self.belt is None:
                return [(p, self.pose(p, T_base_tool_true)) for p in self.parts]
            s = self.belt.position_m() if s_m is None else s_m
            x0, x1 = self.belt.spec.x_mm
            out = []
            for p in self.parts:
                T = self.pose(p, T_base_tool_true, s)
                if p.belt_s_m is not None:
                    x_mm = float(T[0, 3]) * 1e3
                    if x_mm < x0:
                        continue  # not on the belt yet
                    if x_mm > x1 and s_m is None:
                        p.state, p.T_base_part, p.belt_s_m = "fallen", T, None
                        T[2, 3] = self.table_z_m - 0.5  # off the belt's end, out of every view
                        self.version += 1
                out.append((p, T))
            return out

    def key(self, T_base_tool_true: NDArray[np.float64], s_m: float | None = None) -> bytes:
        """Changes whenever what the camera could see of the parts changes."""
        with self._lock:
            held = any(p.state == "held" for p in self.parts)
            belt = b"" if s_m is None else b"s%.6f" % s_m
            return b"parts%d" % self.version + belt + (T_base_tool_true.tobytes() if held else b"")

    def slip(self, part_id: int, along_mm: float) -> None:
        """A part on the belt slips ``along_mm`` along it (a fault: where vision saw it is no longer true)."""
        with self._lock:
            part = self.parts[part_id]
            if part.belt_s_m is None:
                raise ValueError(f"part {part_id} is not on the belt ({part.state})")
            part.T_base_part = part.T_base_part.copy()
            part.T_base_part[0, 3] += along_mm * 1e-3
            self.version += 1

    def slip_at_close(self, along_mm: float) -> None:
        """Arm a slip for the next close: the belt part nearest the gripper slips ``along_mm`` along the belt the
        instant the fingers start to close (after every picture the run took of it: a deterministic slip)."""
        with self._lock:
            self._slip_at_close_mm = float(along_mm)

    def held(self) -> SimPart | None:
        with self._lock:
            return next((p for p in self.parts if p.state == "held"), None)

    # -- the gripper ------------------------------------------------------------------------------
    def close(self, T_base_tool_true: NDArray[np.float64]) -> GripOutcome:
        """Close the gripper at the tool's true pose: hold the part it closes on, if any."""
        gs = self.spec.gripper
        with self._lock:
            if self.closed:
                held = self.held()
                return GripOutcome(None if held is None else held.id, "already closed")
            self.closed = True
            if self._slip_at_close_mm is not None:
                self._slip_nearest(T_base_tool_true, self._slip_at_close_mm)
                self._slip_at_close_mm = None
            best, best_d, best_T = None, math.inf, np.eye(4)
            for p, T_now in self.poses(T_base_tool_true):
                if p.state in ("held", "fallen"):
                    continue
                d = float(np.hypot(*(T_base_tool_true[:2, 3] - T_now[:2, 3]))) * 1e3
                if d < best_d:
                    best, best_d, best_T = p, d, T_now
            if best is None or best_d > gs.tolerance_mm:
                return GripOutcome(None, f"no part within {gs.tolerance_mm} mm of the gripper's centre"
                                   + ("" if best is None else f" (nearest {best_d:.1f} mm)"))
            dz_mm = (T_base_tool_true[2, 3] - best_T[2, 3]) * 1e3
            if not -self.spec.part.thickness_mm <= dz_mm <= gs.above_mm:
                return GripOutcome(None, f"the gripper closed {dz_mm:.1f} mm from part {best.id}'s top face "
                                   f"(allowed -{self.spec.part.thickness_mm}..{gs.above_mm} mm)")
            dyaw = math.degrees(yaw_of(T_base_tool_true) - yaw_of(best_T))
            sym = gs.symmetry_deg
            off = abs((dyaw + sym / 2) % sym - sym / 2)
            if off > gs.tolerance_deg:
                return GripOutcome(None, f"the fingers are {off:.1f} deg off part {best.id}'s grip axis")
            self.closes_on_part += 1
            if gs.fail_probability > 0 and self._rng.uniform() < gs.fail_probability:
                self.faults += 1
                return GripOutcome(None, f"part {best.id} slipped from the fingers as they closed (simulated)")
            best.T_tool_part = g.invert(T_base_tool_true) @ best_T
            best.state, best.T_base_part, best.belt_s_m = "held", best_T, None
            self.version += 1
            return GripOutcome(best.id, "")

    def _slip_nearest(self, T_base_tool_true: NDArray[np.float64], along_mm: float) -> None:
        """(Under the lock.) The belt part nearest the tool slips ``along_mm`` along the belt."""
        on_belt = [(p, T) for p, T in self.poses(T_base_tool_true) if p.belt_s_m is not None and p.state == "in_area"]
        if not on_belt:
            return
        part, _T = min(on_belt, key=lambda pt: float(np.hypot(*(T_base_tool_true[:2, 3] - pt[1][:2, 3]))))
        part.T_base_part = part.T_base_part.copy()
        part.T_base_part[0, 3] += along_mm * 1e-3
        self.version += 1

    def open(self, T_base_tool_true: NDArray[np.float64]) -> int | None:
        """Open the gripper: the held part (its id returned) lands below where it is."""
        with self._lock:
            self.closed = False
            held = self.held()
            if held is None:
                return None
            self._let_go(held, T_base_tool_true)
            return held.id

    def move_started(self, speed_m_s: float, T_base_tool_true: NDArray[np.float64]) -> int | None:
        """A move starts at ``speed_m_s``: a held part slips out when the acceleration is too high."""
        gs = self.spec.gripper
        if gs.slip_accel_m_s2 is None or speed_m_s / gs.accel_ramp_s < gs.slip_accel_m_s2:
            return None
        with self._lock:
            held = self.held()
            if held is None:
                return None
            self._let_go(held, T_base_tool_true, slipped=True)
            return held.id

    def width_mm(self) -> float:
        """The fingers' opening: open, the part's grip width when holding, 0 when closed empty."""
        with self._lock:
            if not self.closed:
                return self.spec.gripper.open_width_mm
            return self.spec.part.grip_width_mm if self.held() is not None else 0.0

    def _let_go(self, part: SimPart, T_base_tool_true: NDArray[np.float64], slipped: bool = False) -> None:
        T = self.pose(part, T_base_tool_true)
        x_mm, y_mm = float(T[0, 3]) * 1e3, float(T[1, 3]) * 1e3
        part.T_base_part = self.lying(x_mm, y_mm, math.degrees(yaw_of(T)))
        part.T_tool_part = None
        if self.belt is not None and self.spec.pick_area.contains(x_mm, y_mm):
            part.belt_s_m = self.belt.position_m()  # let go over the belt: it rides it again
        if slipped:
            part.state = "dropped"
        elif self.spec.place_area.contains(x_mm, y_mm) or (self.spec.fixture is not None
                                                             and self.spec.fixture.contains(x_mm, y_mm)):
            part.state = "placed"
        elif self.spec.pick_area.contains(x_mm, y_mm):
            part.state = "in_area"
        else:
            part.state = "dropped"
        self.version += 1

    # -- kept across a restart (drivers.sim.world.SimWorld.keep_state_in) ---------------------------
    def state(self) -> dict[str, Any]:
        """The parts' states and poses, the gripper closed or not, the fault draw's counters (JSON-able)."""
        with self._lock:
            return {"parts": [{"id": p.id, "state": p.state, "T_base_part": p.T_base_part.tolist(),
                               "T_tool_part": None if p.T_tool_part is None else p.T_tool_part.tolist(),
                               **({} if p.belt_s_m is None else {"belt_s_m": p.belt_s_m})}
                              for p in self.parts],
                    "closed": self.closed, "closes_on_part": self.closes_on_part, "faults": self.faults}

    def set_state(self, state: dict[str, Any]) -> None:
        """Take back :meth:`state` (the same scene's: its part ids); ``ValueError`` when it is not."""
        parts = state["parts"]
        if sorted(int(p["id"]) for p in parts) != [p.id for p in self.parts]:
            raise ValueError("the kept parts are not this scene's (another scatter or part count)")
        with self._lock:
            for kept in parts:
                part = self.parts[int(kept["id"])]
                part.state = kept["state"]
                part.T_base_part = np.asarray(kept["T_base_part"], dtype=np.float64)
                part.T_tool_part = None if kept["T_tool_part"] is None else np.asarray(kept["T_tool_part"],
                                                                                        dtype=np.float64)
                part.belt_s_m = kept.get("belt_s_m")
            self.closed = bool(state["closed"])
            self.closes_on_part = int(state.get("closes_on_part", 0))
            self.faults = int(state.get("faults", 0))
            self.version += 1

    # -- truth ------------------------------------------------------------------------------------
    def outline_in_base(self, T_base_part: NDArray[np.float64]) -> NDArray[np.float64]:
        """The outline's corners in the base frame (metres), on the part's top face."""
        pts = np.column_stack([self._outline * 1e-3, np.zeros(len(self._outline))])
        return g.transform_points(T_base_part, pts)

    def truth(self, T_base_tool_true: NDArray[np.float64]) -> list[dict[str, Any]]:
        return [{"id": p.id, "state": p.state, "T_base_part": T.tolist()} for p, T in self.poses(T_base_tool_true)]
