"""Virtual-cell data with known truth, for tests, benchmarks and worked examples.

Each generator builds the observations a calibration would get (detections, robot poses, jogged
marks) from a stated truth plus stated noise, so a solver can be checked against what it should
recover (the mrcal way). Modules: ``intrinsics`` (a varied capture plan and its detections),
``handeye`` (6-DOF eye-in-hand and eye-to-hand stations), ``special`` (a SCARA cell, a tool centre,
measured target frames; ``write_example`` writes them as files), ``npoint`` (jog-to-mark marks).
``python -m calibration.synthetic scara|tcp FOLDER`` writes the examples of
docs/calibrations-beyond-6dof.md. Everything public is exported here:
``from calibration.synthetic import X`` is the interface.
"""

from calibration.synthetic.handeye import SimulatedHandEye, simulate_handeye
from calibration.synthetic.intrinsics import plan_views, synthetic_detections
from calibration.synthetic.npoint import simulate_npoint
from calibration.synthetic.special import (
    ScaraSet,
    ToolCentreSet,
    perturb_pose,
    simulate_scara,
    simulate_tool_centre,
    write_example,
)

__all__ = [
    "ScaraSet", "SimulatedHandEye", "ToolCentreSet", "perturb_pose", "plan_views", "simulate_handeye",
    "simulate_npoint", "simulate_scara", "simulate_tool_centre", "synthetic_detections", "write_example",
]
