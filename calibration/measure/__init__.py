"""Applying a calibration: pixels to metric points.

``plane`` maps image points to a known plane and back (a camera and the plane's pose ``T_cam_plane``;
HALCON's ``image_points_to_world_plane``); ``pixel_to_robot`` maps a pixel to a robot-frame point
in mm with its propagated 1-σ uncertainty, through a hand-eye or an N-point calibration.
Everything public is exported here: ``from calibration.measure import X`` is the interface.
"""

from calibration.measure.plane import PlaneError, image_to_plane, plane_to_image
from calibration.measure.robot_frame import (
    DEFAULT_NPOINT_PIXEL_SIGMA_PX,
    MappingError,
    RobotPoint,
    map_handeye,
    map_npoint,
    pixel_to_robot,
)

__all__ = [
    "DEFAULT_NPOINT_PIXEL_SIGMA_PX", "MappingError", "PlaneError", "RobotPoint", "image_to_plane", "map_handeye",
    "map_npoint", "pixel_to_robot", "plane_to_image",
]
