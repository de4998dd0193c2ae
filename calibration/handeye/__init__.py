"""Hand-eye calibration (eye-in-hand and eye-to-hand) with checks, joint refinement and uncertainty.

Conventions (docs/conventions.md): ``T_a_b`` maps frame ``b`` into frame ``a``; SI inside.

Model. With ``G_i = T_base_tool`` of station ``i`` and ``C_i = T_cam_target`` seen in its image:

- eye-in-hand: ``C_i = inv(T_tool_cam) · inv(G_i) · T_base_target``;
- eye-to-hand: ``C_i = inv(T_base_cam) · G_i · T_tool_target``.

Both are ``H_i · X · C_i = Z`` with ``H_i = G_i`` (eye-in-hand) or ``inv(G_i)`` (eye-to-hand),
``X`` the hand-eye transform and ``Z`` the constant target pose; relative motions give
``A X = X B`` with ``A = inv(H_j) H_i`` and ``B = C_j inv(C_i)``.

What is OpenCV's and what is ours:

- the closed-form initial solutions are OpenCV's ``cv2.calibrateHandEye`` (TSAI, PARK, HORAUD,
  ANDREFF, DANIILIDIS; eye-to-hand by passing the inverted robot poses, as OpenCV documents) plus
  our own pair-filtered least-squares (Kabsch on the rotation logs, then linear translation),
  which drops pairs whose relative rotation is too small or near 180°;
- the per-station target pose is ``calibration.pose.pnp.estimate_pose`` (OpenCV's PnP on undistorted
  points, refined on pixels through our camera model; any lens model, division included);
- the **joint refinement** is ours: a maximum-likelihood estimate over ``X``, ``Z`` and a small
  pose correction per station, minimising the reprojection error of every target point in every
  image (each point weighted by its own detection uncertainty, ``Detection.uv_sigma_px``) plus a
  Gaussian prior on the corrections (the stated robot noise model). Treating the recorded robot
  poses as exact was 2–10x worse (docs/field-notes.md). Optionally the camera intrinsics are
  refined in the same problem (on by default when the intrinsics' own verdict was not ok);
- the **robot error model** is chosen, not assumed (``error_model``): the fixed prior, i.i.d.
  noise estimated from the data, or a systematic pose-dependent position correction — whichever
  predicts held-out stations best in leave-one-out; that leave-one-out pixel prediction is the
  primary quality figure (``quality.loo_prediction_rms_px``).

Robot noise model (stated, used by the prior and by the benchmark's generator): the recorded
flange pose ``G_i`` differs from the true one by an orientation error ``Exp(w_i)`` applied in the
base frame and a position error ``v_i`` (base frame), ``w_i ~ N(0, σ_r² I)``, ``v_i ~ N(0, σ_t² I)``
— σ per axis. Pixel noise σ_px is estimated from the per-station PnP residuals (which carry no
robot noise) unless given.

Uncertainty: the 6x6 covariance of ``X`` in the parametrisation ``R = Exp(ω) R̂`` (ω in radians,
base/left perturbation) and ``t = t̂ + v`` (metres), from the Gauss-Newton normal matrix of the
whitened problem, scaled up by the reduced χ² when the data are noisier than stated. The reported
``uncertainty.rot_deg`` and ``trans_mm`` are the RMS rotation angle sqrt(trace Σ_ω) and RMS
translation distance sqrt(trace Σ_v), 1-σ.

Modules: ``model`` (types, limits, errors), ``frames`` (frame algebra, station poses),
``closed_form`` (AX = XB closed forms), ``checks`` (conventions, motion, outliers), ``consensus``
(stations far off the solution's consensus, left out when held-out prediction agrees), ``joint``
(the joint refinement, optionally with the intrinsics and a systematic robot error),
``error_model`` (the robot error model chosen by leave-one-out prediction), ``solve``
(``calibrate_handeye``).

The other hand-eye problems live beside it: ``dof4`` (4-DOF: SCARA, delta, top-down picking;
``dof4_checks`` its motion checks), ``measured`` (a measured target frame, from one station up),
``stations`` (the reprojection problem those two share) and ``tool_centre`` (the tool centre seen
by a fixed camera while the tool turns about z). Virtual-cell data with truth is
``calibration.synthetic``.
Everything public is exported here: ``from calibration.handeye import X`` is the interface.
"""

from calibration.handeye.checks import check_conventions, check_motion, find_outlier_stations
from calibration.handeye.closed_form import axxb_residuals, opencv_handeye, relative_motions, solve_pairs, stats
from calibration.handeye.consensus import (
    CONSENSUS_FACTOR,
    confirmed_by_held_out,
    consensus_misses,
    off_consensus,
)
from calibration.handeye.dof4 import (
    DEFAULT_TARGET_Z_SIGMA_MM,
    HandEyeDof4Result,
    Station4,
    calibrate_handeye_dof4,
    make_stations4,
)
from calibration.handeye.dof4_checks import check_dof4_motion, is_dof4, pair_residuals, tool_tilts_deg
from calibration.handeye.error_model import ERROR_MODELS, choose_model, fit_model, leave_one_out_prediction
from calibration.handeye.frames import (
    hand_pose,
    make_stations,
    mean_pose,
    perturb,
    predict_cam_target,
    station_pose,
    target_from_station,
    transform_error_deg_mm,
)
from calibration.handeye.joint import JointOptions, JointProblem, LMResult, refine, vce_robot_noise
from calibration.handeye.measured import (
    DEFAULT_TRACKER,
    MeasuredHandEyeResult,
    calibrate_handeye_measured,
    compare_handeye,
)
from calibration.handeye.model import (
    MAX_PAIR_ANGLE_DEG,
    MIN_AXIS_SPREAD_DEG,
    MIN_PAIR_ANGLE_DEG,
    MIN_STATIONS,
    OPENCV_METHODS,
    OUTLIER_FACTOR,
    OUTLIER_FLOOR,
    RECOMMENDED_STATIONS,
    SETUPS,
    WARN_AXIS_SPREAD_DEG,
    ConventionError,
    HandEyeError,
    HandEyeResult,
    Mat4,
    Problem,
    RobotNoise,
    Setup,
    Station,
)
from calibration.handeye.solve import calibrate_handeye
from calibration.handeye.tool_centre import (
    MIN_ANGLES,
    MIN_ARC_DEG,
    RECOMMENDED_ANGLES,
    ToolCentreError,
    ToolCentreResult,
    fit_tool_centre,
    flange_pose_for_feature,
    tool_offset_vector,
)

__all__ = [
    "CONSENSUS_FACTOR", "confirmed_by_held_out", "consensus_misses", "off_consensus",
    "DEFAULT_TARGET_Z_SIGMA_MM", "DEFAULT_TRACKER", "ERROR_MODELS", "JointOptions", "choose_model", "fit_model",
    "MAX_PAIR_ANGLE_DEG", "MIN_ANGLES", "MIN_ARC_DEG", "MIN_AXIS_SPREAD_DEG", "MIN_PAIR_ANGLE_DEG", "MIN_STATIONS",
    "OPENCV_METHODS", "OUTLIER_FACTOR", "OUTLIER_FLOOR", "RECOMMENDED_ANGLES", "RECOMMENDED_STATIONS", "SETUPS",
    "WARN_AXIS_SPREAD_DEG", "ConventionError", "HandEyeDof4Result", "HandEyeError", "HandEyeResult", "JointProblem",
    "LMResult", "Mat4", "MeasuredHandEyeResult", "Problem", "RobotNoise", "Setup", "Station", "Station4",
    "ToolCentreError", "ToolCentreResult", "axxb_residuals", "calibrate_handeye", "calibrate_handeye_dof4",
    "calibrate_handeye_measured", "check_conventions", "check_dof4_motion", "check_motion", "compare_handeye",
    "find_outlier_stations", "fit_tool_centre", "flange_pose_for_feature", "hand_pose", "is_dof4",
    "leave_one_out_prediction", "make_stations", "make_stations4", "mean_pose", "opencv_handeye", "pair_residuals",
    "perturb", "predict_cam_target", "refine", "relative_motions", "solve_pairs", "station_pose", "stats",
    "target_from_station", "tool_offset_vector", "tool_tilts_deg", "transform_error_deg_mm", "vce_robot_noise",
]
