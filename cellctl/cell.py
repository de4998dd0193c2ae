"""The live cell: builds the configured drivers, owns them, and knows which are available.

A device that fails to open (or later fails) is marked unavailable with the reason; the next
use retries it after a back-off (exponential, capped), so the service reconnects by itself when
the device comes back, and callers get ``DeviceUnavailable`` quickly instead of hanging.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from cellctl.config import CellConfig
from cellctl.errors import CellctlError
from drivers.backoff import Backoff
from drivers.base import CameraBase, DeviceUnavailable, DigitalIOBase, DriverError, RobotBase
from drivers.conveyor.base import ConveyorBase
from drivers.registry import Category, adapter_class

log = logging.getLogger(__name__)

D = TypeVar("D", CameraBase, RobotBase, DigitalIOBase, ConveyorBase)

class UnknownDevice(CellctlError, LookupError):
    """A camera or robot id that the config does not name."""


RETRY_INITIAL_S = 0.5
RETRY_MAX_S = 10.0


@dataclass
class DeviceSlot(Generic[D]):
    """One configured device: the adapter, whether it is open, and why not."""

    device_id: str
    kind: str
    category: Category
    device: D
    is_open: bool = False
    reason: str = "not opened yet"
    outages: int = 0
    _backoff: Backoff = field(default_factory=lambda: Backoff(RETRY_INITIAL_S, RETRY_MAX_S))
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def ensure_open(self) -> D:
        """The open device, opening (or re-opening after back-off) it if needed."""
        with self._lock:
            if self.is_open:
                return self.device
            if not self._backoff.due():
                raise DeviceUnavailable(f"{self.category} {self.device_id} is unavailable: {self.reason} "
                                        f"(retrying in {self._backoff.remaining_s():.1f} s)")
            try:
                if isinstance(self.device, RobotBase):
                    self.device.connect()
                else:
                    self.device.open()
            except DriverError as exc:
                self._mark_failed(str(exc))
                raise DeviceUnavailable(f"{self.category} {self.device_id} is unavailable: {exc}") from exc
            except OSError as exc:
                self._mark_failed(str(exc))
                raise DeviceUnavailable(f"{self.category} {self.device_id} is unavailable: {exc}") from exc
            self.is_open = True
            self.reason = ""
            self._backoff.reset()
            return self.device

    def report_failure(self, exc: BaseException) -> None:
        """Called by users of the device when an operation found it gone: close and back off."""
        with self._lock:
            if self.is_open:
                self.outages += 1
                log.warning("%s %s lost: %s", self.category, self.device_id, exc)
            try:
                self.device.close()
            except Exception:  # noqa: BLE001 - closing a broken device must not mask the cause
                log.debug("closing %s failed", self.device_id, exc_info=True)
            self.is_open = False
            self._mark_failed(str(exc))

    def _mark_failed(self, reason: str) -> None:
        self.reason = reason
        self._backoff.schedule()

    def close(self) -> None:
        with self._lock:
            try:
                self.device.close()
            finally:
                self.is_open = False
                self.reason = "closed"

    def status(self) -> dict[str, Any]:
        return {"id": self.device_id, "kind": self.kind, "available": self.is_open,
                "reason": self.reason or None, "outages": self.outages}


class Cell:
    """All devices of one cell, built from its config. Use as a context manager or call close()."""

    def __init__(self, config: CellConfig) -> None:
        self.config = config
        self.cameras: dict[str, DeviceSlot[CameraBase]] = {}
        self.robots: dict[str, DeviceSlot[RobotBase]] = {}
        self.io: dict[str, DeviceSlot[DigitalIOBase]] = {}
        self.conveyors: dict[str, DeviceSlot[ConveyorBase]] = {}
        for cam_id, cam in config.cameras.items():
            cls = adapter_class("camera", cam.kind)
            self.cameras[cam_id] = DeviceSlot(cam_id, cam.kind, "camera",
                                              cls(cam_id, config.validated_settings("camera", cam_id)))
        for rob_id, rob in config.robots.items():
            cls = adapter_class("robot", rob.kind)
            settings = config.validated_settings("robot", rob_id)
            if rob.kind == "sim" and getattr(settings, "state_file", "") is None:
                # The virtual production cell keeps its parts and arm across a restart, as a real one does.
                from cellctl.paths import data_dir

                settings = settings.model_copy(
                    update={"state_file": str(data_dir() / "sim" / f"{config.cell_id}-{rob_id}.json")})
            self.robots[rob_id] = DeviceSlot(rob_id, rob.kind, "robot", cls(rob_id, settings, rob.limits()))
        for io_id, io in config.io.items():
            cls = adapter_class("io", io.kind)
            self.io[io_id] = DeviceSlot(io_id, io.kind, "io", cls(io_id, config.validated_settings("io", io_id)))
        for cv_id, cv in config.conveyors.items():
            cls = adapter_class("conveyor", cv.kind)
            self.conveyors[cv_id] = DeviceSlot(cv_id, cv.kind, "conveyor",
                                               cls(cv_id, config.validated_settings("conveyor", cv_id)))

    def open_all(self) -> None:
        """Try to open every device; failures are recorded, not raised (the service still starts)."""
        for slot in self._slots():
            try:
                slot.ensure_open()
            except DeviceUnavailable as exc:
                log.warning("%s", exc)

    def close(self) -> None:
        for slot in self._slots():
            try:
                slot.close()
            except Exception:  # noqa: BLE001 - close everything even when one fails
                log.exception("closing %s failed", slot.device_id)

    def _slots(self) -> list[DeviceSlot[Any]]:
        return [*self.cameras.values(), *self.robots.values(), *self.io.values(), *self.conveyors.values()]

    def __enter__(self) -> Cell:
        self.open_all()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def camera(self, camera_id: str) -> DeviceSlot[CameraBase]:
        try:
            return self.cameras[camera_id]
        except KeyError:
            raise UnknownDevice(f"no camera {camera_id!r} in the config; configured: {sorted(self.cameras)}") from None

    def robot(self, robot_id: str) -> DeviceSlot[RobotBase]:
        try:
            return self.robots[robot_id]
        except KeyError:
            raise UnknownDevice(f"no robot {robot_id!r} in the config; configured: {sorted(self.robots)}") from None

    def conveyor(self, conveyor_id: str) -> DeviceSlot[ConveyorBase]:
        try:
            return self.conveyors[conveyor_id]
        except KeyError:
            raise UnknownDevice(f"no conveyor {conveyor_id!r} in the config; configured: "
                                f"{sorted(self.conveyors)}") from None
