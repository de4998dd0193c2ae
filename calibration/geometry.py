"""Rigid transforms and rotation forms.

Conventions (docs/conventions.md): ``T_a_b`` is a 4x4 homogeneous matrix that maps
coordinates in frame ``b`` into frame ``a``; compose left to right
(``T_base_cam = T_base_tool @ T_tool_cam``). Translations are metres, angles radians.

The Universal Robots TCP-pose form is ``[x, y, z, rx, ry, rz]``: metres and a rotation vector
(axis times angle, radians). HALCON's pose type 0 is ``[x, y, z, a, b, c, 0]`` with Euler angles
in degrees applied as ``R = Rx(a) @ Ry(b) @ Rz(c)`` (rotations about the fixed axes, in the order
c then b then a).
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from calibration import CalibrationError

Mat4 = NDArray[np.float64]
Mat3 = NDArray[np.float64]
Vec = NDArray[np.float64]

_ORTHONORMAL_TOL: Final = 1e-6


class PoseError(CalibrationError):
    """A pose is not a valid rigid transform (wrong shape, not orthonormal, not finite)."""


def as_transform(T: ArrayLike, name: str = "T") -> Mat4:
    """Validate and return a 4x4 rigid transform as a float64 array.

    Raises PoseError naming ``name`` when the matrix is not 4x4, not finite, its last row is not
    ``[0, 0, 0, 1]`` or its rotation block is not orthonormal with determinant +1.
    """
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise PoseError(f"{name} must be a 4x4 matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise PoseError(f"{name} contains NaN or infinity")
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise PoseError(f"{name} last row must be [0, 0, 0, 1], got {M[3].tolist()}")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=_ORTHONORMAL_TOL) or np.linalg.det(R) < 0:
        raise PoseError(f"{name} rotation block is not a proper rotation (orthonormal, det +1)")
    return M


def make_transform(R: ArrayLike, t: ArrayLike) -> Mat4:
    """Build ``T`` from a 3x3 rotation and a translation (metres)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T_a_b: ArrayLike) -> Mat4:
    """Return ``T_b_a`` for a rigid ``T_a_b`` (exact, no general matrix inverse)."""
    T = np.asarray(T_a_b, dtype=np.float64)
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> NDArray[np.float64]:
    """Map (N, 3) points given in frame ``b`` into frame ``a``."""
    T = np.asarray(T_a_b, dtype=np.float64)
    P = np.asarray(points_b, dtype=np.float64).reshape(-1, 3)
    return P @ T[:3, :3].T + T[:3, 3]


def exp_so3(rotvec: ArrayLike) -> NDArray[np.float64]:
    """The SO(3) exponential: rotation vector(s) (axis * angle, radians), shape (3,) or (N, 3), to
    rotation matrices, shape (3, 3) or (N, 3, 3) (Rodrigues' formula, vectorised).

    The one copy in ``calibration``: every solver's small-angle perturbation goes through it.
    """
    w = np.asarray(rotvec, dtype=np.float64)
    single = w.ndim == 1
    rv = w.reshape(-1, 3)
    th = np.linalg.norm(rv, axis=1)
    small = th < 1e-12
    k = rv / np.where(small, 1.0, th)[:, None]
    Kx = np.zeros((len(rv), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    R = np.eye(3)[None] + s * Kx + (1 - c) * (Kx @ Kx)
    R[small] = np.eye(3)
    return R[0] if single else R


def rot_z(angle_rad: float) -> Mat3:
    """The rotation by ``angle_rad`` (radians, counter-clockwise) about z, 3x3."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def perturb(T: Mat4, p: ArrayLike) -> Mat4:
    """``[Exp(w) R, t + v]`` for ``p = (w, v)`` (rotation vector in radians, translation in metres;
    the left, base-frame perturbation every solver and simulator uses)."""
    q = np.asarray(p, dtype=np.float64)
    return make_transform(exp_so3(q[:3]) @ T[:3, :3], T[:3, 3] + q[3:6])


def log_so3(R: ArrayLike) -> Vec:
    """Rotation vector (radians) of a 3x3 rotation matrix: closed form, scipy near 180 deg where the
    closed form is ill-conditioned."""
    M = np.asarray(R, dtype=np.float64)
    th = float(np.arccos(np.clip((M[0, 0] + M[1, 1] + M[2, 2] - 1.0) / 2.0, -1.0, 1.0)))
    v = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    if th < 1e-6:
        return 0.5 * v
    if th > np.pi - 1e-3:
        return np.asarray(Rotation.from_matrix(M).as_rotvec(), dtype=np.float64)
    return th / (2.0 * np.sin(th)) * v


def rotvec_to_matrix(rotvec: ArrayLike) -> Mat3:
    """Rotation vector (axis * angle, radians) to a 3x3 matrix (``exp_so3`` of one vector)."""
    return exp_so3(np.asarray(rotvec, dtype=np.float64).reshape(3))


def matrix_to_rotvec(R: ArrayLike) -> Vec:
    """3x3 rotation matrix to a rotation vector (radians); angle in [0, pi]."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


def ur_pose_to_transform(pose: ArrayLike) -> Mat4:
    """UR TCP pose ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in radians) to ``T``."""
    p = np.asarray(pose, dtype=np.float64).reshape(-1)
    if p.shape != (6,):
        raise PoseError(f"a UR pose has 6 numbers [x, y, z, rx, ry, rz], got {p.size}")
    if not np.all(np.isfinite(p)):
        raise PoseError("a UR pose contains NaN or infinity")
    return make_transform(rotvec_to_matrix(p[3:]), p[:3])


def transform_to_ur_pose(T: ArrayLike) -> Vec:
    """``T`` to the UR TCP pose form ``[x, y, z, rx, ry, rz]`` (metres, radians)."""
    M = np.asarray(T, dtype=np.float64)
    return np.concatenate([M[:3, 3], matrix_to_rotvec(M[:3, :3])])


def quaternion_to_matrix(q_xyzw: ArrayLike) -> Mat3:
    """Unit quaternion with the scalar last ``[qx, qy, qz, qw]`` to a 3x3 matrix."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=np.float64).reshape(4)).as_matrix()


def matrix_to_quaternion(R: ArrayLike) -> Vec:
    """3x3 rotation matrix to a unit quaternion ``[qx, qy, qz, qw]`` (scalar last, qw >= 0)."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return np.asarray(q if q[3] >= 0 else -q, dtype=np.float64)


def halcon_pose_to_transform(pose: ArrayLike) -> Mat4:
    """HALCON pose type 0 ``[x, y, z, a_deg, b_deg, c_deg]`` (metres, degrees) to ``T``."""
    p = np.asarray(pose, dtype=np.float64).reshape(-1)[:6]
    R = Rotation.from_euler("XYZ", p[3:6], degrees=True).as_matrix()
    return make_transform(R, p[:3])


def transform_to_halcon_pose(T: ArrayLike) -> Vec:
    """``T`` to HALCON pose type 0 ``[x, y, z, a_deg, b_deg, c_deg]`` (metres, degrees)."""
    M = np.asarray(T, dtype=np.float64)
    abc = Rotation.from_matrix(M[:3, :3]).as_euler("XYZ", degrees=True)
    return np.concatenate([M[:3, 3], abc])


def rotation_angle(R: ArrayLike) -> float:
    """Angle (radians, in [0, pi]) of a 3x3 rotation matrix."""
    M = np.asarray(R, dtype=np.float64)
    c = (np.trace(M) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def transform_error(T_est: ArrayLike, T_true: ArrayLike) -> tuple[float, float]:
    """Rotation (radians) and translation (metres) difference between two transforms."""
    A = np.asarray(T_est, dtype=np.float64)
    B = np.asarray(T_true, dtype=np.float64)
    rot = rotation_angle(A[:3, :3].T @ B[:3, :3])
    trans = float(np.linalg.norm(A[:3, 3] - B[:3, 3]))
    return rot, trans


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> Mat4:
    """``T_world_cam`` of a camera at ``eye`` looking at ``target`` (OpenCV camera frame).

    The camera's z axis points from ``eye`` to ``target``; the world direction ``up`` appears
    towards the top of the image (camera y, image down, is as close as possible to ``-up``).
    """
    e = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - e
    z /= np.linalg.norm(z)
    u = np.asarray(up, dtype=np.float64)
    x = np.cross(z, u)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.column_stack([x, y, z]), e)


# -- robot controllers' orientation conventions (the robot socket, docs/robot-socket.md) ----------------
#
# Every form describes the same rotation R of a pose T_base_tool (the tool's axes in the base frame):
# ``ur``: rotation vector (axis * angle, radians); ``abb``: unit quaternion [q1, q2, q3, q4] = [w, x, y, z]
# (scalar first, q1 >= 0); ``fanuc`` (W, P, R) and ``yaskawa`` (Rx, Ry, Rz): degrees about the fixed
# base axes X, then Y, then Z, so R = Rz(R) @ Ry(P) @ Rx(W); ``kuka`` (A, B, C): degrees about Z, then the
# new Y', then the new X'' (intrinsic), so R = Rz(A) @ Ry(B) @ Rx(C) -- the same matrix as FANUC's with
# the angles listed in the other order. Written in closed form (not scipy), so the tests can hold them
# against scipy's Rotation as an independent reference.

ROBOT_ORIENTATIONS: Final = ("ur", "abb", "fanuc", "kuka", "yaskawa")


def _rx(a: float) -> Mat3:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> Mat3:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> Mat3:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def zyx_deg_to_matrix(z_deg: float, y_deg: float, x_deg: float) -> Mat3:
    """``R = Rz(z) @ Ry(y) @ Rx(x)`` (degrees): KUKA's A, B, C in that order; FANUC's R, P, W reversed."""
    return _rz(np.radians(z_deg)) @ _ry(np.radians(y_deg)) @ _rx(np.radians(x_deg))


def matrix_to_zyx_deg(R: ArrayLike) -> tuple[float, float, float]:
    """The angles (z, y, x) in degrees with ``R = Rz(z) @ Ry(y) @ Rx(x)``; y in [-90, 90], z and x in
    (-180, 180]. At y = +-90 (gimbal lock) only z -+ x is defined: x is set to 0."""
    M = np.asarray(R, dtype=np.float64)
    cy = float(np.hypot(M[0, 0], M[1, 0]))
    y = float(np.arctan2(-M[2, 0], cy))
    if cy > 1e-9:
        z = float(np.arctan2(M[1, 0], M[0, 0]))
        x = float(np.arctan2(M[2, 1], M[2, 2]))
    else:  # y = +-90 deg: R = Rz(z -+ x) Ry(+-90); keep x = 0
        z = float(np.arctan2(-M[0, 1], M[1, 1]))
        x = 0.0
    return float(np.degrees(z)), float(np.degrees(y)), float(np.degrees(x))


def matrix_to_quaternion_wxyz(R: ArrayLike) -> Vec:
    """3x3 rotation matrix to a unit quaternion ``[w, x, y, z]`` (scalar first, ABB's q1..q4, w >= 0);
    Shepperd's method (the largest of the four squared components first, for accuracy)."""
    M = np.asarray(R, dtype=np.float64)
    t = float(np.trace(M))
    diag = (t, M[0, 0], M[1, 1], M[2, 2])
    k = int(np.argmax(diag))
    if k == 0:
        s = 2.0 * np.sqrt(max(1.0 + t, 0.0))
        q = [0.25 * s, (M[2, 1] - M[1, 2]) / s, (M[0, 2] - M[2, 0]) / s, (M[1, 0] - M[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(max(1.0 + M[0, 0] - M[1, 1] - M[2, 2], 0.0))
        q = [(M[2, 1] - M[1, 2]) / s, 0.25 * s, (M[0, 1] + M[1, 0]) / s, (M[0, 2] + M[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(max(1.0 - M[0, 0] + M[1, 1] - M[2, 2], 0.0))
        q = [(M[0, 2] - M[2, 0]) / s, (M[0, 1] + M[1, 0]) / s, 0.25 * s, (M[1, 2] + M[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(max(1.0 - M[0, 0] - M[1, 1] + M[2, 2], 0.0))
        q = [(M[1, 0] - M[0, 1]) / s, (M[0, 2] + M[2, 0]) / s, (M[1, 2] + M[2, 1]) / s, 0.25 * s]
    v = np.asarray(q, dtype=np.float64)
    v /= np.linalg.norm(v)
    return -v if v[0] < 0 else v


def quaternion_wxyz_to_matrix(q_wxyz: ArrayLike) -> Mat3:
    """Quaternion ``[w, x, y, z]`` (scalar first; normalised here) to a 3x3 matrix."""
    q = np.asarray(q_wxyz, dtype=np.float64).reshape(4)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-12:
        raise PoseError(f"a quaternion needs a finite non-zero norm, got {q.tolist()}")
    w, x, y, z = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def matrix_to_robot_orientation(R: ArrayLike, convention: str) -> list[float]:
    """A rotation in a robot controller's own form (see ``ROBOT_ORIENTATIONS`` above): 3 numbers, 4 for ``abb``."""
    if convention == "ur":
        return [float(v) for v in log_so3(R)]
    if convention == "abb":
        return [float(v) for v in matrix_to_quaternion_wxyz(R)]
    z, y, x = matrix_to_zyx_deg(R)
    if convention == "kuka":
        return [z, y, x]
    if convention in ("fanuc", "yaskawa"):
        return [x, y, z]
    raise PoseError(f"unknown robot orientation convention {convention!r}; one of {', '.join(ROBOT_ORIENTATIONS)}")


def robot_orientation_to_matrix(values: ArrayLike, convention: str) -> Mat3:
    """The inverse of :func:`matrix_to_robot_orientation`."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if convention == "ur":
        return rotvec_to_matrix(v)
    if convention == "abb":
        return quaternion_wxyz_to_matrix(v)
    if convention == "kuka":
        return zyx_deg_to_matrix(v[0], v[1], v[2])
    if convention in ("fanuc", "yaskawa"):
        return zyx_deg_to_matrix(v[2], v[1], v[0])
    raise PoseError(f"unknown robot orientation convention {convention!r}; one of {', '.join(ROBOT_ORIENTATIONS)}")
