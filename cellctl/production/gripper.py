"""Gripper actions of a production cycle: open before the approach, close, settle, check, release.

The recipe's ``gripper.device`` (``cellctl.production.config.GripperDevice``) names a configured io device
and its kind:

- ``robotiq_2f``: ``move(position)`` / ``status()`` of ``drivers.io.robotiq_gripper`` (or the
  virtual cell's ``sim_gripper``): the grip holds when the status says *object detected* and, if
  the recipe gives ``grip_width_mm``, the closed width is within ``width_tolerance_mm`` of it;
- ``vacuum``: the output switches the vacuum; the grip holds when the vacuum switch input comes on
  within ``input_timeout_s``; release switches it off (and pulses ``open_output``, the blow-off);
- ``parallel``: ``output`` closes, ``open_output`` opens; the grip holds when the "closed on part"
  input comes on within ``input_timeout_s``.

Every action answers the seconds it took (the cycle's gripper time).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from cellctl.pick.recipe import GripperSettings, PickError
from cellctl.production.config import GripperDevice
from cellctl.services import Services
from drivers.base import DigitalIOBase

POLL_S = 0.01


@dataclass(frozen=True)
class GripCheck:
    """The outcome of a close: held or not, why, and the closed width when the gripper reports one."""

    held: bool
    detail: str
    width_mm: float | None
    elapsed_s: float


class Gripper:
    """The recipe's gripper on its io device (opened through the cell, like every device)."""

    def __init__(self, services: Services, settings: GripperSettings) -> None:
        device = settings.device
        if device is None:
            raise PickError("the recipe's gripper names no device (gripper.device): a production run must grip; "
                            "see docs/production.md")
        if device.io_id not in services.cell.io:
            raise PickError(f"the recipe's gripper device {device.io_id!r} is not a configured io device; "
                            f"configured: {sorted(services.cell.io)}")
        self.settings = settings
        self.device: GripperDevice = device
        self._slot = services.cell.io[device.io_id]
        self._io: DigitalIOBase | None = None
        if device.kind == "robotiq_2f" and not hasattr(self._slot.device, "status"):
            raise PickError(f"io device {device.io_id!r} ({self._slot.kind}) is not a Robotiq-style gripper; "
                            "use kind vacuum or parallel for digital I/O")

    @property
    def io(self) -> Any:
        if self._io is None:
            self._io = self._slot.ensure_open()
        return self._io

    # -- actions ----------------------------------------------------------------------------------
    def open(self) -> float:
        """Open the fingers (to ``open_width_mm``) or switch the vacuum off; seconds taken."""
        t0 = time.monotonic()
        d = self.device
        if d.kind == "robotiq_2f":
            width = self.settings.open_width_mm
            position = 0 if width is None else round(255 * (1.0 - min(width, d.stroke_mm) / d.stroke_mm))
            self.io.move(position)
        elif d.kind == "vacuum":
            self.io.write_output(d.output, False)
        else:
            self.io.write_output(d.output, False)
            self.io.write_output(d.open_output, True)
        return time.monotonic() - t0

    def release(self) -> float:
        """Let the part go where it is and wait ``release_s``; seconds taken."""
        t0 = time.monotonic()
        d = self.device
        self.open()
        if d.kind == "vacuum" and d.open_output is not None:  # the blow-off pulse
            self.io.write_output(d.open_output, True)
            time.sleep(d.release_s)
            self.io.write_output(d.open_output, False)
        else:
            time.sleep(d.release_s)
        return time.monotonic() - t0

    def close_and_check(self) -> GripCheck:
        """Close, wait ``settle_s``, and check that the part is held."""
        t0 = time.monotonic()
        d = self.device
        if d.kind == "robotiq_2f":
            self.io.move(255)
            time.sleep(self.settings.settle_s)
            held, detail, width = self._check_fingers()
        else:
            if d.kind == "parallel":
                self.io.write_output(d.open_output, False)
            self.io.write_output(d.output, True)
            time.sleep(self.settings.settle_s)
            held, detail, width = self._wait_input(), "", None
            if not held:
                what = "vacuum switch" if d.kind == "vacuum" else "'closed on part' input"
                detail = f"the {what} (input {d.input}) did not come on within {d.input_timeout_s} s"
        return GripCheck(held, detail, width, time.monotonic() - t0)

    def holding(self) -> bool:
        """Whether the gripper says it holds something now (no action)."""
        d = self.device
        if d.kind == "robotiq_2f":
            return bool(self.io.status()["object_detected"])
        return bool(self.io.read_input(d.input))

    # -- checks -----------------------------------------------------------------------------------
    def _check_fingers(self) -> tuple[bool, str, float | None]:
        d = self.device
        status = self.io.status()
        width = status.get("width_mm")
        if width is None:
            width = d.stroke_mm * (1.0 - float(status["position"]) / 255.0)
        if not status["object_detected"]:
            return False, f"the gripper closed empty (width {width:.1f} mm)", float(width)
        want = self.settings.grip_width_mm
        if want is not None and abs(width - want) > d.width_tolerance_mm:
            return False, (f"the fingers closed at {width:.1f} mm, not {want:.1f} +/- {d.width_tolerance_mm} mm: "
                           "not the part (or not across it)"), float(width)
        return True, "", float(width)

    def _wait_input(self) -> bool:
        d = self.device
        deadline = time.monotonic() + d.input_timeout_s
        while True:
            if self.io.read_input(d.input):
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(POLL_S)
