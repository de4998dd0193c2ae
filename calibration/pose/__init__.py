"""Target pose from one view: ``T_cam_target`` with a known camera (PnP), or the camera and its pose
from one view of a non-coplanar 3D target (DLT).

Modules: ``pnp`` (``estimate_pose``: OpenCV's non-iterative search, refined on pixels through our
camera model), ``methods`` (``estimate_pose_by``: a named solver, or the best of all), ``rpnp``
(RPnP of Li, Xu and Xie, our own code), ``dlt`` (``calibrate_dlt``: DLT then a nonlinear
refinement). Everything public is exported here: ``from calibration.pose import X`` is the interface.
"""

from calibration.pose.dlt import DLTError, DLTResult, calibrate_dlt, dlt_matrix
from calibration.pose.methods import METHODS, candidates, estimate_pose_by, refine_pose
from calibration.pose.pnp import PoseEstimationError, PoseResult, estimate_pose
from calibration.pose.rpnp import RPnPError, reprojection_cost, rpnp

__all__ = [
    "METHODS", "DLTError", "DLTResult", "PoseEstimationError", "PoseResult", "RPnPError", "calibrate_dlt",
    "candidates", "dlt_matrix", "estimate_pose", "estimate_pose_by", "refine_pose", "reprojection_cost", "rpnp",
]
