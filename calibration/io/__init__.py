"""Files in and out: camera files (``cam.json``, pose files), robot pose and pair CSVs, camera
exports (OpenCV, ROS, HALCON), results to JSON, and reading the files a user names with typed errors.

Modules: ``camera_file``, ``solved_camera`` (the camera a hand-eye was solved with), ``robot_poses``,
``export``, ``jsonable``, ``files``.
Everything public is exported here: ``from calibration.io import X`` is the interface.
"""

from calibration.io.camera_file import CameraFileError, camera_from_json, read_camera, read_pose, write_camera
from calibration.io.export import (
    ExportError,
    halcon_cam_par,
    read_halcon_cam_par,
    read_opencv_yaml,
    read_ros_yaml,
    ros_camera_info,
    write_opencv_yaml,
    write_ros_yaml,
)
from calibration.io.files import read_json, read_text, read_yaml, yaml_error_text
from calibration.io.jsonable import NonFiniteError, dumps, to_jsonable
from calibration.io.robot_poses import (
    PAIR_COLUMNS,
    POSE_COLUMNS,
    RobotPoseFileError,
    RobotPoses,
    read_pairs_csv,
    read_poses_csv,
    write_pairs_csv,
    write_poses_csv,
)
from calibration.io.solved_camera import (
    SAME_CAMERA_TOLERANCE_PX,
    camera_difference_px,
    camera_mismatch,
    handeye_camera,
    handeye_start_camera,
)

__all__ = [
    "PAIR_COLUMNS", "POSE_COLUMNS", "SAME_CAMERA_TOLERANCE_PX", "camera_difference_px", "camera_mismatch",
    "handeye_camera", "handeye_start_camera", "CameraFileError", "ExportError", "NonFiniteError", "RobotPoseFileError",
    "RobotPoses", "camera_from_json", "dumps", "halcon_cam_par", "read_camera", "read_halcon_cam_par", "read_json",
    "read_opencv_yaml", "read_pairs_csv", "read_pose", "read_poses_csv", "read_ros_yaml", "read_text", "read_yaml",
    "ros_camera_info", "to_jsonable", "write_camera", "write_opencv_yaml", "write_pairs_csv", "write_poses_csv",
    "write_ros_yaml", "yaml_error_text",
]
