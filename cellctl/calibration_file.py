"""A calibration file made elsewhere (``cam.json``, ``he.json``, ``np.json``), checked for the store.

What ``POST /calibrations`` and ``cellctl store add`` take: the JSON that ``cellctl calib
intrinsics`` / ``calib import`` / ``calib dlt`` (camera), ``calib handeye`` (hand-eye, ``--dof 4``
included) or ``calib npoint`` (n-point) wrote. The kind is recognised from the keys (or given),
and the file is read by the calibration package's own readers (``camera_from_json``,
``as_transform``, ``NPointResult.from_json``), so what is stored is what the service can use.
Every number must be finite and the sizes sane. A file of another kind (a target description,
detections, a pose, a tool centre, a part model, a cell config) is named, with what to give instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final, Literal

from cellctl.errors import CellctlError

Kind = Literal["camera", "handeye", "npoint"]
KINDS: Final = ("camera", "handeye", "npoint")
MAX_IMAGE_SIDE_PX: Final = 100_000
MAX_TRANSLATION_M: Final = 100.0
"""A hand-eye translation beyond this is no work cell (metres)."""
MAX_NPOINT_SCALE_MM_PER_PX: Final = 1e4

_MAKE = {"camera": "cellctl calib intrinsics (or calib import / calib dlt)", "handeye": "cellctl calib handeye",
         "npoint": "cellctl calib npoint"}
GIVE: Final = ("a calibration result file: cam.json (cellctl calib intrinsics, calib import, calib dlt), "
               "he.json (cellctl calib handeye) or np.json (cellctl calib npoint)")


class CalibrationFileError(CellctlError, ValueError):
    """The file is not a usable calibration of the kind given or recognised; the message says why and what to give.

    ``code``: ``not_a_calibration`` (a file of another kind, or of another calibration kind than asked),
    ``invalid_calibration`` (the right kind, but a value is wrong), ``unknown_device`` (no such camera/robot).
    """

    def __init__(self, message: str, code: str = "invalid_calibration") -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class CheckedCalibration:
    """A calibration file that passed the checks: its kind, its content and its verdict (None: the file has none)."""

    kind: Kind
    result: dict[str, Any]
    verdict_ok: bool | None
    notes: list[str]


def check_calibration(data: Any, kind: str | None = None, source: str = "the file") -> CheckedCalibration:
    """Recognise (or check the given ``kind`` of) a calibration file's JSON and validate it.

    Raises :class:`CalibrationFileError` naming what is wrong; a file of another kind is named.
    """
    if kind is not None and kind not in KINDS:
        raise CalibrationFileError(f"kind {kind!r} is not one of {', '.join(KINDS)}")
    if not isinstance(data, dict):
        raise CalibrationFileError(f"{source} is {_looks_like_list(data)}, not a calibration; give {GIVE}",
                                   "not_a_calibration")
    bad = _non_finite(data, "")
    if bad is not None:
        raise CalibrationFileError(f"{source}: {bad} is not a finite number; a calibration holds finite numbers only")
    seen: str | None = recognise(data)
    if seen is None:
        other = _other_kind(data)
        if other is not None:
            raise CalibrationFileError(f"{source} looks like {other}, not a calibration; give {GIVE}",
                                       "not_a_calibration")
        if kind is None:
            keys = ", ".join(sorted(map(str, data))[:8]) or "none"
            raise CalibrationFileError(f"{source} is not a calibration file this service knows (its keys: {keys}); "
                                       f"give {GIVE}", "not_a_calibration")
        seen = kind
    if kind is not None and seen != kind:
        raise CalibrationFileError(f"{source} is a {seen} calibration (its keys say so), not a {kind} one; "
                                   f"give kind {seen}, or a file of {_MAKE[kind]}", "not_a_calibration")
    if seen is None:  # unreachable: a file whose kind is unknown was refused above
        raise CalibrationFileError(f"{source}: its calibration kind could not be told; give {GIVE}",
                                   "not_a_calibration")
    checker = {"camera": _check_camera, "handeye": _check_handeye, "npoint": _check_npoint}[seen]
    notes = checker(data, source)
    verdict = data.get("verdict")
    verdict_ok: bool | None = None
    if verdict is not None:
        if not isinstance(verdict, dict) or not isinstance(verdict.get("ok"), bool):
            raise CalibrationFileError(f"{source}: verdict must be an object with ok true or false "
                                       "(and problems), as the calibration commands write it")
        verdict_ok = verdict["ok"]
    else:
        notes.append("the file has no verdict (made elsewhere or imported): check it before activating it")
    return CheckedCalibration(seen, data, verdict_ok, notes)  # type: ignore[arg-type]


def recognise(data: dict[str, Any]) -> Kind | None:
    """The calibration kind that the keys of ``data`` say, or None."""
    if "setup" in data and any(k in data for k in ("T_tool_cam", "T_base_cam")):
        return "handeye"
    if "H" in data and "model" in data:
        return "npoint"
    if "K" in data and "model" in data:
        return "camera"
    return None


def _check_camera(data: dict[str, Any], source: str) -> list[str]:
    from calibration.io import CameraFileError, camera_from_json

    for key in ("width", "height"):
        v = data.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or not 0 < v <= MAX_IMAGE_SIDE_PX:
            raise CalibrationFileError(f"{source}: {key} must be the image's {key} in pixels, an integer "
                                       f"1-{MAX_IMAGE_SIDE_PX}, got {v!r}")
    try:
        camera = camera_from_json(data, source)
    except CameraFileError as exc:
        raise CalibrationFileError(str(exc)) from None
    if not (0 <= camera.cx <= camera.width and 0 <= camera.cy <= camera.height):
        raise CalibrationFileError(f"{source}: the principal point ({camera.cx:g}, {camera.cy:g}) px lies outside "
                                   f"the {camera.width}x{camera.height} image; K is [[fx,0,cx],[0,fy,cy],[0,0,1]]")
    return []


def _check_handeye(data: dict[str, Any], source: str) -> list[str]:
    from calibration import geometry as g
    from calibration.io import CameraFileError, camera_from_json

    setup = data.get("setup")
    names = {"eye-in-hand": ("T_tool_cam", "T_base_target"), "eye-to-hand": ("T_base_cam", "T_tool_target")}
    if not isinstance(setup, str) or setup not in names:
        raise CalibrationFileError(f"{source}: setup must be eye-in-hand or eye-to-hand, got {setup!r}")
    for name in names[setup]:
        if name not in data:
            raise CalibrationFileError(f"{source}: an {setup} hand-eye calibration needs {' and '.join(names[setup])}"
                                       f" (4x4, metres); {name} is missing")
        try:
            T = g.as_transform(data[name], f"{source}: {name}")
        except (g.PoseError, ValueError, TypeError) as exc:
            raise CalibrationFileError(str(exc) if isinstance(exc, g.PoseError)
                                       else f"{source}: {name} is not a 4x4 matrix of numbers") from None
        if float(abs(T[:3, 3]).max()) > MAX_TRANSLATION_M:
            raise CalibrationFileError(f"{source}: {name}'s translation {T[:3, 3].tolist()} is beyond "
                                       f"{MAX_TRANSLATION_M:g} m; hand-eye files are in metres")
    dof = data.get("dof", 6)
    if dof not in (4, 6) or isinstance(dof, bool):
        raise CalibrationFileError(f"{source}: dof must be 4 or 6, got {dof!r}")
    for key in ("camera", "camera_initial"):
        if key in data:
            try:
                camera_from_json(data[key], f"{source}: {key}")
            except CameraFileError as exc:
                raise CalibrationFileError(str(exc)) from None
    if data.get("intrinsics_refined") is True and "camera" not in data:
        # the solution fits the pixels through the refined camera only (calibration/io/solved_camera.py)
        raise CalibrationFileError(f"{source}: the hand-eye refined the intrinsics (intrinsics_refined: true) but "
                                   "carries no camera; it maps only through the camera it was solved with: give "
                                   "the he.json as cellctl calib handeye wrote it")
    return []


def _check_npoint(data: dict[str, Any], source: str) -> list[str]:
    import numpy as np

    from calibration.camera_model import CameraModelError
    from calibration.npoint import NPointError, NPointResult

    try:
        result = NPointResult.from_json(data)
    except (NPointError, CameraModelError) as exc:
        raise CalibrationFileError(f"{source}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise CalibrationFileError(f"{source}: malformed n-point values ({exc})") from None
    A = result.H[:2, :2]
    det = float(np.linalg.det(A))
    if not (math.isfinite(det) and abs(det) > 1e-12) or float(abs(A).max()) > MAX_NPOINT_SCALE_MM_PER_PX:
        raise CalibrationFileError(f"{source}: H does not map the image onto a plane (its 2x2 part {A.tolist()} is "
                                   "singular or its scale unreasonable); calibrate again with cellctl calib npoint")
    return []


_TARGET_TYPES = ("chessboard", "charuco", "circle_plate", "circle_grid", "points3d")


def _other_kind(data: dict[str, Any]) -> str | None:
    """What a non-calibration JSON object looks like, in words (None: nothing we know)."""
    if data.get("type") in _TARGET_TYPES:
        return f"a calibration target description (type {data['type']}; docs/targets.md)"
    if "T_cam_target" in data:
        return "a target pose (cellctl pose output, T_cam_target)"
    if "offset_mm" in data and "rotation_centre_px" in data:
        return "a tool centre (cellctl calib tcp output, tcp.json)"
    if "cameras" in data or "robots" in data or "cell_id" in data:
        return "a cell configuration (cell.yaml)"
    if "image" in data and ("points" in data or "found" in data):
        return "one image's target detections (cellctl detect output)"
    if "matches" in data or ("model" in data and "mode" in data):
        return "a part model or pick result (cellctl pick)"
    if "calibration" in data and "x_mm" in data:
        return "a mapped point (cellctl map output)"
    return None


def _looks_like_list(data: Any) -> str:
    if isinstance(data, list):
        first = data[0] if data else None
        if isinstance(first, dict) and "image" in first and ("points" in first or "found" in first):
            return "a list of target detections (cellctl detect output)"
        if isinstance(first, dict) and "matches" in first:
            return "a list of pick matches (cellctl pick find output)"
        return "a JSON list"
    return f"a JSON {type(data).__name__.replace('str', 'string').replace('NoneType', 'null')}"


def _non_finite(value: Any, path: str) -> str | None:
    """The dotted path of the first NaN or infinity in ``value`` (None: all finite)."""
    if isinstance(value, float) and not math.isfinite(value):
        return path or "the value"
    if isinstance(value, dict):
        items: Any = value.items()
    elif isinstance(value, list):
        items = enumerate(value)
    else:
        return None
    for k, v in items:
        found = _non_finite(v, f"{path}.{k}" if path else str(k))
        if found is not None:
            return found
    return None


def add_calibration(store: Any, config: Any, data: Any, who: str, kind: str | None = None,
                    camera_id: str | None = None, robot_id: str | None = None, note: str = "",
                    source: str = "the file") -> dict[str, Any]:
    """Check ``data`` and store it as a new, inactive version of ``(kind, camera_id, robot_id)``.

    ``camera_id``/``robot_id`` default to the config's ``calibration.camera``/``calibration.robot``
    (a camera calibration has no robot); each must be configured. Answers the stored version's
    summary with ``verdict_ok``, the verdict, ``notes`` and ``activated: false``.
    """
    checked = check_calibration(data, kind, source)
    cam = camera_id or config.calibration.camera
    if cam not in config.cameras:
        raise CalibrationFileError(f"no camera {cam!r} in the config; configured: {', '.join(sorted(config.cameras))}"
                                   " (give camera_id)", "unknown_device")
    rob: str | None = None
    if checked.kind == "camera":
        if robot_id is not None:
            raise CalibrationFileError("a camera calibration belongs to a camera alone; leave robot_id out",
                                       "invalid_calibration")
    else:
        rob = robot_id or config.calibration.robot
        if rob not in config.robots:
            raise CalibrationFileError(f"no robot {rob!r} in the config; configured: "
                                       f"{', '.join(sorted(config.robots)) or 'none'} (give robot_id)",
                                       "unknown_device")
    record = store.save_calibration(checked.kind, cam, rob, checked.result,
                                    {"added": {"by": who, "from": source, "recognised_kind": checked.kind}},
                                    creator=who, note=note or f"added from {source}")
    return {**record.summary().to_dict(), "verdict_ok": checked.verdict_ok,
            "verdict": checked.result.get("verdict"), "notes": checked.notes, "activated": False}
