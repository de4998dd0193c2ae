"""Reading robot pose files (``poses.csv``) and N-point pair files (``pairs.csv``).

Formats (docs/datasets.md):

- ``poses.csv``: header ``image,x,y,z,rx,ry,rz``; one row per image; the pose is ``T_base_tool``
  in Universal Robots' TCP-pose form (metres, rotation vector in radians).
- ``pairs.csv``: header ``u_px,v_px,x_mm,y_mm``: an image point and the robot point the tool
  was jogged to.

Errors name the file, the line and what to do. Nothing is silently reinterpreted (units and
rotation conventions are checked against the images by ``calibration.handeye``).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import numpy as np
from numpy.typing import NDArray

from calibration import CalibrationError
from calibration.geometry import ur_pose_to_transform

POSE_COLUMNS: Final[tuple[str, ...]] = ("image", "x", "y", "z", "rx", "ry", "rz")
PAIR_COLUMNS: Final[tuple[str, ...]] = ("u_px", "v_px", "x_mm", "y_mm")


class RobotPoseFileError(CalibrationError):
    """A poses.csv / pairs.csv file is missing, malformed or inconsistent."""


@dataclass(frozen=True)
class RobotPoses:
    """The rows of a ``poses.csv``: image names, raw UR poses and ``T_base_tool`` matrices."""

    images: list[str]
    ur_poses: NDArray[np.float64]
    """(N, 6) ``x, y, z`` (m), ``rx, ry, rz`` (rad) exactly as in the file."""

    @property
    def T_base_tool(self) -> list[NDArray[np.float64]]:
        return [ur_pose_to_transform(p) for p in self.ur_poses]


def _read_rows(path: Path, columns: tuple[str, ...], what: str) -> list[tuple[int, list[str]]]:
    try:
        text = path.read_text()
    except OSError as exc:
        raise RobotPoseFileError(f"{path}: cannot read {what} ({exc.strerror})") from exc
    lines = [(k + 1, line) for k, line in enumerate(text.splitlines())
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise RobotPoseFileError(f"{path}: empty {what}; expected the header {','.join(columns)}")
    header = [h.strip() for h in next(csv.reader([lines[0][1]]))]
    if tuple(header) != columns:
        raise RobotPoseFileError(f"{path}: header must be {','.join(columns)} (got {','.join(header)})")
    rows: list[tuple[int, list[str]]] = []
    for lineno, line in lines[1:]:
        cells = [c.strip() for c in next(csv.reader([line]))]
        if len(cells) != len(columns):
            raise RobotPoseFileError(f"{path}:{lineno}: expected {len(columns)} values ({','.join(columns)}), "
                                     f"got {len(cells)}")
        rows.append((lineno, cells))
    if not rows:
        raise RobotPoseFileError(f"{path}: no data rows after the header")
    return rows


def _floats(path: Path, lineno: int, cells: list[str], names: tuple[str, ...]) -> list[float]:
    out = []
    for name, cell in zip(names, cells, strict=True):
        try:
            v = float(cell)
        except ValueError:
            raise RobotPoseFileError(f"{path}:{lineno}: {name} is not a number ({cell!r})") from None
        if not np.isfinite(v):
            raise RobotPoseFileError(f"{path}:{lineno}: {name} is not finite ({cell!r})")
        out.append(v)
    return out


def read_poses_csv(path: str | Path) -> RobotPoses:
    """Read ``poses.csv`` (header ``image,x,y,z,rx,ry,rz``, UR TCP-pose form)."""
    p = Path(path)
    images: list[str] = []
    poses: list[list[float]] = []
    for lineno, cells in _read_rows(p, POSE_COLUMNS, "robot pose file"):
        name = cells[0]
        if not name:
            raise RobotPoseFileError(f"{p}:{lineno}: empty image name")
        if name in images:
            raise RobotPoseFileError(f"{p}:{lineno}: image {name!r} listed twice; one pose per image")
        images.append(name)
        poses.append(_floats(p, lineno, cells[1:], POSE_COLUMNS[1:]))
    return RobotPoses(images, np.array(poses, dtype=np.float64))


def write_poses_csv(path: str | Path, images: list[str], ur_poses: NDArray[np.float64]) -> None:
    """Write a ``poses.csv`` (full float precision)."""
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(POSE_COLUMNS)
        for name, pose in zip(images, np.asarray(ur_poses).reshape(-1, 6), strict=True):
            w.writerow([name, *[repr(float(v)) for v in pose]])


def read_pairs_csv(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read ``pairs.csv`` (header ``u_px,v_px,x_mm,y_mm``): (N, 2) pixels and (N, 2) robot mm."""
    p = Path(path)
    vals = [_floats(p, lineno, cells, PAIR_COLUMNS) for lineno, cells in _read_rows(p, PAIR_COLUMNS, "pairs file")]
    a = np.array(vals, dtype=np.float64)
    return a[:, :2], a[:, 2:]


def write_pairs_csv(path: str | Path, uv_px: NDArray[np.float64], xy_mm: NDArray[np.float64]) -> None:
    """Write a ``pairs.csv``."""
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(PAIR_COLUMNS)
        for (u, v), (x, y) in zip(np.asarray(uv_px).reshape(-1, 2), np.asarray(xy_mm).reshape(-1, 2), strict=True):
            w.writerow([repr(float(u)), repr(float(v)), repr(float(x)), repr(float(y))])
