"""poses.csv / pairs.csv reading: round trips and clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.geometry import ur_pose_to_transform
from calibration.io import RobotPoseFileError, read_pairs_csv, read_poses_csv, write_pairs_csv, write_poses_csv


def test_poses_round_trip(tmp_path: Path) -> None:
    poses = np.array([[0.4, -0.1, 0.3, 0.1, 3.0, -0.2], [0.45, 0.0, 0.35, -0.2, 2.9, 0.1]])
    write_poses_csv(tmp_path / "poses.csv", ["a.png", "b.png"], poses)
    got = read_poses_csv(tmp_path / "poses.csv")
    assert got.images == ["a.png", "b.png"]
    assert np.array_equal(got.ur_poses, poses)
    assert np.allclose(got.T_base_tool[1], ur_pose_to_transform(poses[1]))


def test_poses_tolerates_spaces_and_comments(tmp_path: Path) -> None:
    p = tmp_path / "poses.csv"
    p.write_text("# recorded on ur5e\nimage, x, y, z, rx, ry, rz\n a.png , 0.1, 0.2, 0.3, 0, 0, 0.5\n\n")
    got = read_poses_csv(p)
    assert got.images == ["a.png"] and got.ur_poses[0, 5] == 0.5


@pytest.mark.parametrize(("text", "match"), [
    ("", "empty"),
    ("image,x,y,z,a,b,c\na.png,0,0,0,0,0,0\n", "header must be image,x,y,z,rx,ry,rz"),
    ("image,x,y,z,rx,ry,rz\n", "no data rows"),
    ("image,x,y,z,rx,ry,rz\na.png,0,0,0,0,0\n", r"poses.csv:2: expected 7 values"),
    ("image,x,y,z,rx,ry,rz\na.png,0,0,zero,0,0,0\n", r"poses.csv:2: z is not a number"),
    ("image,x,y,z,rx,ry,rz\na.png,0,0,nan,0,0,0\n", "not finite"),
    ("image,x,y,z,rx,ry,rz\na.png,0,0,0,0,0,0\na.png,0,0,0,0,0,0\n", "listed twice"),
])
def test_poses_errors(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "poses.csv"
    p.write_text(text)
    with pytest.raises(RobotPoseFileError, match=match):
        read_poses_csv(p)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RobotPoseFileError, match="cannot read"):
        read_poses_csv(tmp_path / "nope.csv")


def test_pairs_round_trip_and_errors(tmp_path: Path) -> None:
    uv = np.array([[1.5, 2.5], [100.0, 3.0], [4.0, 90.0]])
    xy = np.array([[10.0, 20.0], [30.0, 20.0], [10.0, -5.0]])
    write_pairs_csv(tmp_path / "pairs.csv", uv, xy)
    got_uv, got_xy = read_pairs_csv(tmp_path / "pairs.csv")
    assert np.array_equal(got_uv, uv) and np.array_equal(got_xy, xy)
    bad = tmp_path / "bad.csv"
    bad.write_text("u,v,x,y\n1,2,3,4\n")
    with pytest.raises(RobotPoseFileError, match="header must be u_px,v_px,x_mm,y_mm"):
        read_pairs_csv(bad)
