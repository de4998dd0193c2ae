"""Tool centre from turning the tool about z: truth within the reported 1-σ, refusals with the
reason (2 angles, a 10° arc), and the tool offset applied when converting to a flange pose."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.geometry import make_transform
from calibration.handeye import ToolCentreError, fit_tool_centre, flange_pose_for_feature, tool_offset_vector
from calibration.npoint import fit_npoint
from calibration.synthetic import simulate_tool_centre

CAM = CameraModel("opencv5", 1920, 1200, np.array([[1900.0, 0, 962], [0, 1900, 597], [0, 0, 1]]),
                  np.array([-0.05, 0.01, 0.0, 0.0, 0.0]))


def test_offset_within_reported_uncertainty() -> None:
    ratios = []
    for seed in range(8):
        s = simulate_tool_centre(np.random.default_rng(seed), CAM)
        npm = fit_npoint(s.npoint_uv_px, s.npoint_xy_mm, "homography", CAM)
        res = fit_tool_centre(s.uv_px, s.flange_mm, s.rz_deg, npm)
        err = float(np.linalg.norm(res.offset_mm - s.offset_mm))
        assert err <= 0.05
        ratios.append(err / res.sigma_offset_mm)
        out = res.to_json()
        assert len(out["rotation_centre_px"]) == 2 and out["rms_mm"] < 0.05
        for pos in out["positions"]:  # the circle centre is the flange axis the robot reported
            assert pos["flange_axis_vs_reported_mm"] < 0.15 and pos["angles"] == 7
    assert 0.3 < np.sqrt(np.mean(np.square(ratios))) < 2.0, ratios


def test_rotation_centre_px_is_the_flange_axis_in_the_image() -> None:
    s = simulate_tool_centre(np.random.default_rng(3), CAM, pixel_sigma_px=0.0)
    npm = fit_npoint(s.npoint_uv_px, s.npoint_xy_mm, "homography", CAM)
    out = fit_tool_centre(s.uv_px, s.flange_mm, s.rz_deg, npm).to_json()
    for pos, c_px in zip(out["positions"], out["rotation_centre_px"], strict=True):
        back = npm.map(np.array([c_px]))[0]
        assert np.linalg.norm(back - np.array(pos["centre_mm"])) < 1e-6


def test_refused_with_the_reason() -> None:
    s2 = simulate_tool_centre(np.random.default_rng(1), CAM, n_angles=2, flange_mm=((450.0, 50.0),))
    npm = fit_npoint(s2.npoint_uv_px, s2.npoint_xy_mm, "homography")
    with pytest.raises(ToolCentreError, match=r"only 2 angle\(s\); a circle needs at least 3"):
        fit_tool_centre(s2.uv_px, s2.flange_mm, s2.rz_deg, npm)
    s10 = simulate_tool_centre(np.random.default_rng(1), CAM, n_angles=5, arc_deg=10.0)
    with pytest.raises(ToolCentreError, match=r"span only 10.0 deg; an arc under 30 deg"):
        fit_tool_centre(s10.uv_px, s10.flange_mm, s10.rz_deg, npm)
    # an arc across +-180 deg counts as the short arc it is
    wrap = np.array([175.0, 179.0, -178.0, -175.0])
    with pytest.raises(ToolCentreError, match=r"span only 10.0 deg"):
        fit_tool_centre(np.zeros((4, 2)) + 500, np.tile([450.0, 50.0], (4, 1)), wrap, npm)
    with pytest.raises(ToolCentreError, match="one of each per row"):
        fit_tool_centre(np.zeros((4, 2)), np.zeros((3, 2)), np.zeros(4), npm)


def test_flange_pose_applies_the_offset() -> None:
    """A tool pointing down, turned by 30 deg: the feature lands where asked."""
    offset_mm = np.array([32.5, -18.0])
    R0 = Rotation.from_rotvec([np.pi, 0.0, 0.0]).as_matrix()  # top-down tool
    o_tool = tool_offset_vector(offset_mm, R0)
    rz = np.radians(30.0)
    Rz = Rotation.from_rotvec([0.0, 0.0, rz]).as_matrix()
    T_feature = make_transform(Rz @ R0, [0.5, 0.1, 0.02])
    T_flange = flange_pose_for_feature(T_feature, o_tool)
    feature = T_flange[:3, :3] @ o_tool + T_flange[:3, 3]
    assert np.allclose(feature, T_feature[:3, 3], atol=1e-12)
    expected = np.array([0.5, 0.1]) - (Rz[:2, :2] @ offset_mm) * 1e-3  # flange = feature - Rz(rz) o
    assert np.allclose(T_flange[:2, 3], expected, atol=1e-12)
    assert np.allclose(T_flange[:3, :3], T_feature[:3, :3])
