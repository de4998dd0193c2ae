"""Views for calibrating a fixed camera: the robot carries the plate through the camera's view.

Eye-to-hand: the camera is fixed, the plate is on the tool, facing it. The plan is the
eye-in-hand one (``ViewPlanner``: probe shifts that measure the image Jacobian, the four image
corners reached in a closed loop, tilts about both camera axes, other distances), with the moves
that differ when the plate moves instead of the camera:

- **Which way is the camera looking?** The probe shifts move the plate by a known base-frame vector;
  the plate's motion in the camera frame (its pose from a rough pinhole, ``T_cam_target`` of each
  view) gives the camera's axes in the base frame (``R_base_cam``). Farther (``_along_view``)
  moves the plate along the camera's view axis, away from it; tilts turn about the camera's x and
  y axes, so they are the tilts the verdict counts.
- **Where is the plate on the tool?** A tilt turns the plate about its own centre, which is
  somewhere on the tool (``q_tool_m``, the plate centre in the tool frame). Two small tilt probes
  about the tool's x and y axes show it: every view says ``T_base_tool · q = T_base_cam · c_cam``
  (``c_cam`` the plate centre seen by the camera), linear in ``q`` and the camera's position, solved
  in the least-squares sense over all good views with a weak pull towards ``q = 0`` while the tilts
  have not yet separated the two.

Lengths are metres, angles degrees, pixels ``(u, v)``; ``T_a_b`` maps frame ``b`` into ``a``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration import geometry as g
from cellctl.routines.view_plan import Mat4, ViewPlanner

PROBE_TILT_DEG = 10.0
"""The tilt probes turn the tool by this much about its x and y axes (the plate stays in view for a
plate up to about a quarter of the camera distance off the guessed centre)."""
PRIOR_WEIGHT = 1e-3
"""How strongly an unseen part of ``q`` is pulled to 0 (relative to one view's equations)."""


@dataclass
class FixedCameraViewPlanner(ViewPlanner):
    """Plans eye-to-hand views: the plate on the tool, shown to a fixed camera (module docstring)."""

    centre_target_m: NDArray[np.float64] | None = None
    """The plate's centre in its own frame (the mean of its points)."""
    R_base_cam: NDArray[np.float64] | None = None
    """The camera's axes in the base frame, measured by the probe shifts (None until then)."""
    q_tool_m: NDArray[np.float64] | None = None
    """The plate's centre in the tool frame, measured by the views (None: taken as the tool centre)."""
    scene_sign = 1.0

    def _after_probes(self) -> Iterator[tuple[str, Mat4]]:
        self.R_base_cam = self._camera_axes()
        self.q_tool_m = self._plate_on_tool()
        for axis in (0, 1):
            R = g.rotvec_to_matrix(self.T0[:3, axis] * math.radians(PROBE_TILT_DEG))
            yield f"probe tilt {'xy'[axis]}", self._turned(self.T0, R)
            self.q_tool_m = self._plate_on_tool()

    # -- what the views measure ------------------------------------------------------------------------
    def _centre_cam(self, T_cam_target: Mat4) -> NDArray[np.float64]:
        c = self.centre_target_m if self.centre_target_m is not None else np.zeros(3)
        return np.asarray(T_cam_target[:3, :3] @ c + T_cam_target[:3, 3], dtype=np.float64)

    def _measured(self) -> list[tuple[Mat4, NDArray[np.float64]]]:
        return [(s.T_base_tool, self._centre_cam(s.T_cam_target)) for s in self.seen
                if s.good and s.T_cam_target is not None]

    def _camera_axes(self) -> NDArray[np.float64] | None:
        """``R_base_cam`` from the views taken at the start orientation: the plate moved with the tool."""
        views = [(T, c) for T, c in self._measured() if np.allclose(T[:3, :3], self.T0[:3, :3], atol=1e-9)]
        if len(views) < 3:
            return None
        T_ref, c_ref = views[0]
        base, cam = [], []
        for T, c in views[1:]:
            base.append(T[:3, 3] - T_ref[:3, 3])
            cam.append(c - c_ref)
        base.append(np.cross(base[0], base[1]))
        cam.append(np.cross(cam[0], cam[1]))
        A = np.array(base) / np.linalg.norm(base, axis=1, keepdims=True).clip(1e-12)
        B = np.array(cam) / np.linalg.norm(cam, axis=1, keepdims=True).clip(1e-12)
        # Kabsch: the rotation that best turns the base-frame motions into the camera-frame ones.
        U, _, Vt = np.linalg.svd(A.T @ B)
        D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
        return np.asarray(U @ D @ Vt, dtype=np.float64)

    def _plate_on_tool(self) -> NDArray[np.float64] | None:
        """``q`` (plate centre, tool frame) from ``R_i q + t_i = R_base_cam c_i + t_base_cam`` over the views."""
        if self.R_base_cam is None:
            return None
        views = self._measured()
        rows, rhs = [], []
        for T, c in views:
            rows.append(np.hstack([T[:3, :3], -np.eye(3)]))
            rhs.append(self.R_base_cam @ c - T[:3, 3])
        rows.append(np.hstack([np.eye(3), np.zeros((3, 3))]) * PRIOR_WEIGHT)
        rhs.append(np.zeros(3))
        x, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
        return np.asarray(x[:3], dtype=np.float64)

    # -- geometry ------------------------------------------------------------------------------------
    def _pivot(self, T: Mat4) -> NDArray[np.float64]:
        q = self.q_tool_m if self.q_tool_m is not None else np.zeros(3)
        return np.asarray(T[:3, :3] @ q + T[:3, 3], dtype=np.float64)

    def _turned(self, T: Mat4, R: NDArray[np.float64]) -> Mat4:
        """``T`` turned by ``R`` (base frame) about the plate's centre."""
        p = self._pivot(T)
        out = np.eye(4)
        out[:3, :3] = R @ T[:3, :3]
        out[:3, 3] = p + R @ (T[:3, 3] - p)
        return out

    def _along_view(self, T0: Mat4, dz_m: float) -> Mat4:
        """Positive ``dz_m`` moves the plate away from the camera, along its view axis."""
        T = T0.copy()
        axis = self.R_base_cam[:, 2] if self.R_base_cam is not None else T0[:3, 2]
        T[:3, 3] += axis * dz_m
        return T

    def _tilted(self, T: Mat4, axis: int, tilt_deg: float) -> Mat4:
        """``T`` turned about the plate's centre, about the camera's x (axis 0) or y (axis 1)."""
        a = self.R_base_cam[:, axis] if self.R_base_cam is not None else T[:3, axis]
        return self._turned(T, g.rotvec_to_matrix(a * math.radians(tilt_deg)))
