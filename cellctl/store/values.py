"""Checks and encodings of what the store is given: ids, keys, JSON payloads and their checksum."""

from __future__ import annotations

import hashlib
from typing import Any

from calibration import io as cal_io
from cellctl.store.errors import InvalidInput
from cellctl.store.records import CALIBRATION_KINDS


def to_json_text(value: Any, what: str) -> str:
    """``value`` as canonical JSON text; numpy arrays/scalars become lists/numbers; NaN/inf are refused."""
    try:
        return cal_io.dumps(value, separators=(",", ":"), sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"{what} cannot be stored as JSON: {exc}") from None


def payload_sha256(result_json: str, inputs_json: str) -> str:
    h = hashlib.sha256(result_json.encode())
    h.update(b"\n")
    h.update(inputs_json.encode())
    return h.hexdigest()


def describe_key(kind: str, camera_id: str, robot_id: str | None) -> str:
    return f"{kind}/{camera_id}" + (f"/{robot_id}" if robot_id else "")


def check_key(kind: str, camera_id: str, robot_id: str | None) -> None:
    if kind not in CALIBRATION_KINDS:
        raise InvalidInput(f"calibration kind {kind!r} is not one of {', '.join(CALIBRATION_KINDS)}")
    check_text(camera_id, "camera_id")
    if kind == "camera" and robot_id is not None:
        raise InvalidInput("a camera calibration belongs to a camera alone; pass robot_id=None")
    if kind != "camera" and robot_id is None:
        raise InvalidInput(f"a {kind} calibration relates a camera to a robot; pass its robot_id")
    if robot_id is not None:
        check_text(robot_id, "robot_id")


def check_text(value: object, what: str) -> None:
    if not isinstance(value, str) or not value.strip():
        raise InvalidInput(f"{what} must be a non-empty string, got {value!r}")
