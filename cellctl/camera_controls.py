"""A camera's exposure, gain and trigger mode where its driver has them (``GET``/``PUT
/cameras/{id}/controls``): what it offers, within which bounds, and a change checked against them.

Exposure is microseconds (``exposure_us``), gain decibels (``gain_db``), the trigger one of
``free_run``, ``software``, ``hardware``. A driver lists what it has (``drivers.base.CameraBase.control_ranges``:
Aravis from the camera's own GenICam bounds, the virtual cell's camera from its settings' bounds);
a control it does not list is refused with the reason, never silently ignored.
"""

from __future__ import annotations

from typing import Any, Final

from cellctl.errors import CellctlError

__all__ = ["CONTROLS", "ControlRefused", "apply_controls", "controls_of"]

CONTROLS: Final[tuple[str, ...]] = ("exposure_us", "gain_db", "trigger")
UNITS: Final[dict[str, str]] = {"exposure_us": "us", "gain_db": "dB"}


class ControlRefused(CellctlError, ValueError):
    """A control the camera does not have, or a value outside its bounds (the message says which)."""

    def __init__(self, message: str, code: str) -> None:
        super().__init__(message)
        self.code = code


def _ranges(cam: Any) -> dict[str, Any]:
    """The driver's ``control_ranges()`` (``drivers.base.CameraBase``); none for a driver without it."""
    fn = getattr(cam, "control_ranges", None)
    return dict(fn()) if callable(fn) else {}


def controls_of(cam: Any, kind: str) -> dict[str, Any]:
    """Each control: ``supported``, its ``value`` now (None when unsupported) and its ``min``/``max`` (numbers)
    or ``options`` (the trigger), and ``why`` when the driver has none."""
    ranges = _ranges(cam)
    now = cam.settings()
    out: dict[str, Any] = {}
    for name in CONTROLS:
        r = ranges.get(name)
        if r is None:
            out[name] = {"supported": False, "value": None,
                         "why": f"the {kind} camera driver has no {name.replace('_', ' ')} control"}
        elif name == "trigger":
            out[name] = {"supported": True, "value": now.get(name), "options": list(r)}
        else:
            out[name] = {"supported": True, "value": now.get(name), "min": float(r[0]), "max": float(r[1]),
                         "unit": UNITS[name]}
    return out


def check_changes(cam: Any, kind: str, camera_id: str, changes: dict[str, Any]) -> None:
    """Refuse a change the camera cannot take (``ControlRefused``), before anything is set."""
    ranges = _ranges(cam)
    for name, value in changes.items():
        r = ranges.get(name)
        if r is None:
            offered = ", ".join(k for k in CONTROLS if k in ranges) or "none"
            raise ControlRefused(f"camera {camera_id} ({kind}) has no {name} control (its driver offers: {offered})",
                                 "control_unsupported")
        if name == "trigger":
            if value not in r:
                raise ControlRefused(f"camera {camera_id}: trigger {value!r} is not one this camera offers "
                                     f"({', '.join(r)})", "invalid_control")
        elif not float(r[0]) <= float(value) <= float(r[1]):
            raise ControlRefused(f"camera {camera_id}: {name} {value:g} {UNITS[name]} is outside the camera's range "
                                 f"{float(r[0]):g}..{float(r[1]):g} {UNITS[name]}", "invalid_control")


def apply_controls(cam: Any, kind: str, camera_id: str, changes: dict[str, Any]) -> dict[str, Any]:
    """Check every change, then set them (trigger last: a frame already waiting is taken with the new
    exposure); the controls as they are afterwards."""
    check_changes(cam, kind, camera_id, changes)
    if "exposure_us" in changes:
        cam.set_exposure_us(float(changes["exposure_us"]))
    if "gain_db" in changes:
        cam.set_gain_db(float(changes["gain_db"]))
    if "trigger" in changes:
        cam.set_trigger(str(changes["trigger"]))
    return controls_of(cam, kind)
