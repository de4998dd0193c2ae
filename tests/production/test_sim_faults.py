"""The sim gripper's fault draw: seeded (the same scene draws the same faults), its own stream per
scatter seed (a bench's seeds do not replay one another's faults), and at the rate it says."""

from __future__ import annotations

import math

import numpy as np
import yaml

from drivers.sim.production import ProductionParts
from drivers.sim.production_spec import ProductionSpec
from drivers.sim.scene import BUILTIN_SCENES

FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
"""The tool pointing down, its x axis along the part's (a turn of pi about x)."""


def parts(p: float, scatter_seed: int = 3, scene_seed: int = 5, fail_seed: int | None = None) -> ProductionParts:
    data = yaml.safe_load(BUILTIN_SCENES["production"].read_text())["production"]
    data["scatter"].update({"count": 1, "seed": scatter_seed})
    data["gripper"].update({"fail_probability": p, "fail_seed": fail_seed})
    data["unreachable"] = []
    return ProductionParts(ProductionSpec.model_validate(data), 0.0, scene_seed)


def faults(pp: ProductionParts, closes: int) -> list[int]:
    """Close on part 0 ``closes`` times (opening between); the closes that failed."""
    failed = []
    for k in range(closes):
        T_tool = pp.parts[0].T_base_part @ FLIP
        if pp.close(T_tool).part_id is None:
            failed.append(k)
        pp.open(T_tool)
    return failed


def test_the_fault_draw_is_seeded_per_scatter_and_at_its_rate() -> None:
    n, p = 2000, 0.02
    a = faults(parts(p), n)
    assert faults(parts(p), n) == a  # seeded: the same scene draws the same faults
    assert faults(parts(p, scatter_seed=4), n) != a  # another scatter, its own stream
    assert faults(parts(p, scene_seed=6), n) != a
    # An explicit fail_seed decides alone.
    assert faults(parts(p, scatter_seed=1, fail_seed=9), n) == faults(parts(p, scatter_seed=2, fail_seed=9), n)
    sd = math.sqrt(n * p * (1 - p))
    assert abs(len(a) - n * p) < 4 * sd, (len(a), n * p)
    pp = parts(p)
    assert len(faults(pp, 200)) == pp.faults and pp.closes_on_part == 200
    assert faults(parts(0.0), 200) == []  # no fault without a probability
