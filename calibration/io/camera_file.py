"""Read and write the camera result file ``cam.json`` and pose files (docs/cli.md).

Errors name the file and what is wrong with it, so the CLI can print them as one line.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration import CalibrationError
from calibration.camera_model import CameraModel, CameraModelError
from calibration.geometry import PoseError, as_transform


class CameraFileError(CalibrationError):
    """A camera or pose file is missing, not JSON, or lacks a required key."""


def _load_json(path: str | Path, what: str) -> Any:
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise CameraFileError(f"{p}: cannot read {what} file ({exc.strerror})") from exc
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise CameraFileError(f"{p}: not valid JSON (line {exc.lineno}: {exc.msg}); expected a {what} "
                              "file") from exc


def camera_from_json(data: Any, source: str = "camera") -> CameraModel:
    """The camera model of a ``cam.json`` mapping, with clear errors."""
    if not isinstance(data, dict):
        raise CameraFileError(f"{source}: a camera file must be a JSON object with model, width, height, K, "
                              "dist")
    try:
        K = np.asarray(data.get("K"), dtype=np.float64) if "K" in data else None
        if K is not None and K.shape != (3, 3):
            raise CameraFileError(f"{source}: K must be a 3x3 matrix [[fx,0,cx],[0,fy,cy],[0,0,1]]")
        return CameraModel.from_dict(data)
    except CameraModelError as exc:
        raise CameraFileError(f"{source}: {exc}") from exc
    except (TypeError, ValueError) as exc:
        if isinstance(exc, CameraFileError):
            raise
        raise CameraFileError(f"{source}: malformed camera values ({exc})") from exc


def read_camera(path: str | Path) -> tuple[CameraModel, dict[str, Any]]:
    """The camera model and the whole JSON mapping of a camera file."""
    data = _load_json(path, "camera")
    return camera_from_json(data, str(path)), data


def write_camera(path: str | Path, data: dict[str, Any]) -> None:
    """Write a camera result mapping (as produced by ``IntrinsicsResult.to_json``) as JSON."""
    Path(path).write_text(json.dumps(_plain(data), indent=2) + "\n")


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return _plain(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def read_pose(path: str | Path, key: str = "T_cam_target") -> NDArray[np.float64]:
    """``T_cam_target`` (4x4, metres) from a pose JSON (``cellctl pose`` output, or a bare 4x4)."""
    data = _load_json(path, "pose")
    M = data.get(key) if isinstance(data, dict) else data
    if M is None:
        raise CameraFileError(f"{path}: pose file lacks {key!r} (a 4x4 matrix in metres)")
    try:
        return as_transform(M, f"{path}: {key}")
    except (PoseError, ValueError, TypeError) as exc:
        raise CameraFileError(str(exc) if isinstance(exc, PoseError) else f"{path}: {key} is not a 4x4 matrix"
                              ) from exc
