"""GigE Vision and USB3 Vision cameras through Aravis 0.8 (``kind: aravis``).

Python reaches Aravis through PyGObject and Debian's typelib (``gir1.2-aravis-0.8``); both are
imported when the adapter is built, so a machine without them fails here with a message that
names the packages, never at import of the registry.

What it does: open by device id, serial number or IP address; pixel format (Mono8, Mono12,
Mono16, Bayer*8 -> BGR, RGB8 -> BGR), exposure, gain, ROI, frame rate; free-run, software-trigger
and hardware-trigger modes through the GenICam features ``TriggerSelector``/``TriggerMode``/
``TriggerSource``/``TriggerSoftware`` (a camera without them gets a clear error); a bounded
buffer pool (``buffer_count``) drained by one reader thread that keeps only the newest complete
frame, with the camera's timestamp; counters of completed, incomplete and lost frames (frame-id
gaps and Aravis underruns); and reconnection, with exponential backoff, after the camera stops
answering (the outages are counted).

**Network safety**: opening a GigE camera makes Aravis search for it, which broadcasts on every
network interface. ``interfaces`` limits Aravis to the transports listed; tests run GigE only in a
loopback-only network namespace (``drivers/peers/netns.py``) or use the in-process ``Fake``.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any

from drivers.backoff import Backoff, Outages
from drivers.base import CameraBase, DeviceInitError, DeviceOperationError, DeviceTimeout, DeviceUnavailable, Frame
from drivers.camera.aravis_formats import (
    AravisCameraSettings,
    TriggerMode,
    import_aravis,
    to_pixels,
)
from drivers.health import DeviceHealth

__all__ = ["AravisCamera", "AravisCameraSettings"]


class AravisCamera(CameraBase):
    """A GigE Vision / USB3 Vision camera through Aravis 0.8."""

    Settings = AravisCameraSettings

    def __init__(self, camera_id: str, settings: AravisCameraSettings | dict[str, Any]) -> None:
        super().__init__(camera_id)
        self.config = (
            settings if isinstance(settings, AravisCameraSettings) else AravisCameraSettings.model_validate(settings)
        )
        self._arv = import_aravis()
        self._cam: Any = None
        self._stream: Any = None
        self._lock = threading.Lock()
        self._cv = threading.Condition(self._lock)
        self._newest: Frame | None = None
        self._reader: threading.Thread | None = None
        self._closing = threading.Event()
        self._control_lost = threading.Event()
        self._outages = Outages()
        self._outages.reason = "not opened"
        self._pixel_format = ""
        self._last_frame_id: int | None = None
        self.counters = {"completed": 0, "incomplete": 0, "lost": 0, "underruns": 0}
        self._frames = 0
        self._trigger = self.config.trigger

    # -- opening ---------------------------------------------------------------------------------------
    def _enable_interfaces(self) -> None:
        arv = self._arv
        for name in ("GigEVision", "USB3Vision", "Fake"):
            if name in self.config.interfaces:
                arv.enable_interface(name)
            else:
                arv.disable_interface(name)

    def _connect_camera(self) -> None:
        """Open the device, configure it and start the stream (caller holds no lock)."""
        arv = self._arv
        self._enable_interfaces()
        try:
            cam = arv.Camera.new(self._resolve_device_id())
        except Exception as exc:  # GLib.Error
            raise DeviceUnavailable(
                f"camera {self.camera_id}: Aravis cannot open {self.config.device_id!r} on "
                f"{'/'.join(self.config.interfaces)}: {exc}; check the id/serial/IP and "
                "the network (`arv-tool-0.8` lists cameras)"
            ) from exc
        try:
            self._configure(cam)
            stream = cam.create_stream(None, None)
            if stream is None:
                raise DeviceInitError(f"camera {self.camera_id}: Aravis could not create a stream")
            payload = cam.get_payload()
            for _ in range(self.config.buffer_count):
                stream.push_buffer(arv.Buffer.new_allocate(payload))
            dev = cam.get_device()
            self._control_lost.clear()
            dev.connect("control-lost", lambda *_: self._control_lost.set())
            cam.start_acquisition()
        except DeviceInitError:
            raise
        except Exception as exc:
            raise DeviceInitError(
                f"camera {self.camera_id}: setting up {self.config.device_id!r} failed: {exc}"
            ) from exc
        self._cam, self._stream = cam, stream
        self._pixel_format = cam.get_pixel_format_as_string()
        self._last_frame_id = None

    def _resolve_device_id(self) -> str:
        """Aravis opens by id, physical id or address; a serial number is looked up in the device list."""
        arv = self._arv
        wanted = self.config.device_id
        arv.update_device_list()
        for i in range(arv.get_n_devices()):
            if wanted in (arv.get_device_id(i), arv.get_device_address(i), arv.get_device_physical_id(i)):
                return wanted
        for i in range(arv.get_n_devices()):
            if arv.get_device_serial_nbr(i) == wanted:
                return str(arv.get_device_id(i))
        return wanted  # let Aravis try (a camera on another subnet answers a direct request)

    def _feature(self, cam: Any, name: str) -> bool:
        return bool(cam.get_device().is_feature_available(name))

    def _configure(self, cam: Any) -> None:
        c = self.config
        try:
            if c.pixel_format is not None:
                available = list(cam.dup_available_pixel_formats_as_strings() or [])
                if c.pixel_format not in available:
                    raise DeviceInitError(
                        f"camera {self.camera_id}: pixel format {c.pixel_format} is not offered; "
                        f"the camera has {', '.join(available)}"
                    )
                cam.set_pixel_format_from_string(c.pixel_format)
            if c.roi is not None:
                cam.set_region(c.roi.x_px, c.roi.y_px, c.roi.width_px, c.roi.height_px)
                got = cam.get_region()
                if (got.width, got.height) != (c.roi.width_px, c.roi.height_px):
                    raise DeviceInitError(
                        f"camera {self.camera_id}: ROI {c.roi.width_px}x{c.roi.height_px} was "
                        f"not accepted (camera set {got.width}x{got.height})"
                    )
            if c.exposure_us is not None:
                cam.set_exposure_time(c.exposure_us)
            if c.gain_db is not None:
                cam.set_gain(c.gain_db)
            if c.frame_rate_hz is not None:
                cam.set_frame_rate(c.frame_rate_hz)
            if c.packet_size_bytes is not None and cam.is_gv_device():
                cam.gv_set_packet_size(c.packet_size_bytes)
        except DeviceInitError:
            raise
        except Exception as exc:
            raise DeviceInitError(f"camera {self.camera_id}: the camera refused a setting: {exc}") from exc
        self._apply_trigger(cam, self._trigger)

    def _apply_trigger(self, cam: Any, mode: TriggerMode) -> None:
        if mode == "free_run":
            if self._feature(cam, "TriggerMode"):
                cam.set_string("TriggerMode", "Off")
            return
        needed = ["TriggerMode", "TriggerSource"] + (["TriggerSoftware"] if mode == "software" else [])
        missing = [f for f in needed if not self._feature(cam, f)]
        if missing:
            raise DeviceInitError(
                f"camera {self.camera_id}: {mode} trigger needs the GenICam feature(s) "
                f"{', '.join(missing)}, which this camera lacks; use trigger: free_run"
            )
        if self._feature(cam, "TriggerSelector"):
            cam.set_string("TriggerSelector", "FrameStart")
        source = "Software" if mode == "software" else self.config.trigger_source
        try:
            cam.set_string("TriggerSource", source)
        except Exception as exc:
            raise DeviceInitError(f"camera {self.camera_id}: TriggerSource {source!r} is not accepted: {exc}") from exc
        cam.set_string("TriggerMode", "On")

    def open(self) -> None:
        """Open the camera, configure it and start the reader thread."""
        if self._reader is not None:
            return
        self._connect_camera()
        self._outages.up()
        self._closing.clear()
        self._reader = threading.Thread(target=self._read, name=f"aravis-{self.camera_id}", daemon=True)
        self._reader.start()

    def _disconnect_camera(self) -> None:
        cam, self._cam, self._stream = self._cam, None, None
        if cam is not None:
            with contextlib.suppress(Exception):  # the camera may be gone; nothing more to release
                cam.stop_acquisition()

    # -- reading ---------------------------------------------------------------------------------------
    def _read(self) -> None:
        backoff = Backoff(self.config.reconnect_initial_s, self.config.reconnect_max_s)
        last_frame = time.monotonic()
        while not self._closing.is_set():
            stream = self._stream
            if stream is None:
                if self._closing.wait(backoff.next_wait_s()):
                    return
                self._outages.reconnected()
                try:
                    self._connect_camera()
                    self._outages.up()
                    backoff.reset()
                    last_frame = time.monotonic()
                except (DeviceUnavailable, DeviceInitError) as exc:
                    self._outages.down(str(exc))
                continue
            buf = stream.timeout_pop_buffer(100_000)  # us; the GIL is released while Aravis waits
            if buf is not None:
                complete = self._handle_buffer(buf)
                stream.push_buffer(buf)
                if complete:
                    last_frame = time.monotonic()
                continue
            silent = time.monotonic() - last_frame
            lost = self._control_lost.is_set()
            if not lost and (self._trigger != "free_run" or silent < self.config.stall_timeout_s):
                continue
            if not lost and self._camera_answers():
                last_frame = time.monotonic()
                continue
            self._outages.down(
                f"camera {self.camera_id} ({self.config.device_id}) stopped answering; reconnecting "
                f"(attempt every {self.config.reconnect_initial_s}-{self.config.reconnect_max_s} s)"
            )
            self._disconnect_camera()

    def _camera_answers(self) -> bool:
        cam = self._cam
        if cam is None:
            return False
        try:
            cam.get_frame_rate()  # one control-channel read
            return True
        except Exception:
            return False

    def _handle_buffer(self, buf: Any) -> bool:
        """Count the buffer and publish it when complete; True when it was complete."""
        status = buf.get_status()
        frame_id = int(buf.get_frame_id())
        if self._last_frame_id is not None:
            gap = frame_id - self._last_frame_id - 1
            if 0 < gap < 1000:  # GigE ids are 16 bit and wrap (65535 -> 1): a negative gap is a wrap
                self.counters["lost"] += gap
        self._last_frame_id = frame_id
        if status != self._arv.BufferStatus.SUCCESS:
            self.counters["incomplete"] += 1
            return False
        self.counters["completed"] += 1
        data = buf.get_data()
        pixels = to_pixels(data, buf.get_image_width(), buf.get_image_height(), self._pixel_format)
        host_ns = buf.get_system_timestamp()
        with self._cv:
            self._frames += 1
            self._newest = Frame(
                pixels=pixels,
                timestamp_s=host_ns * 1e-9 if host_ns else time.time(),
                frame_id=self._frames,
                camera_id=self.camera_id,
                metadata={
                    "camera_timestamp_ns": int(buf.get_timestamp()),
                    "camera_frame_id": frame_id,
                    "pixel_format": self._pixel_format,
                },
            )
            self._cv.notify_all()
        return True

    # -- contract ------------------------------------------------------------------------------------------
    def grab(self, timeout_s: float = 2.0) -> Frame:
        """The newest complete frame newer than the last ``grab()`` (software trigger: fired now)."""
        if self._reader is None:
            raise DeviceUnavailable(f"camera {self.camera_id} is not open (call open())")
        with self._cv:
            last = self._newest.frame_id if self._newest is not None else 0
        if self._trigger == "software":
            cam = self._cam
            if cam is None:
                raise DeviceUnavailable(f"camera {self.camera_id}: {self._outages.reason}")
            try:
                cam.execute_command("TriggerSoftware")
            except Exception as exc:
                raise DeviceOperationError(f"camera {self.camera_id}: TriggerSoftware failed: {exc}") from exc
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while self._newest is None or self._newest.frame_id == last:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    if self._cam is None:
                        raise DeviceUnavailable(f"camera {self.camera_id}: {self._outages.reason}")
                    raise DeviceTimeout(
                        f"camera {self.camera_id}: no complete frame within {timeout_s} s"
                        + (" (waiting for the hardware trigger)" if self._trigger == "hardware" else "")
                    )
                self._cv.wait(remaining)
            return self._newest

    def close(self) -> None:
        """Stop the reader and the acquisition; safe to call twice."""
        self._closing.set()
        if self._reader is not None:
            self._reader.join(timeout=5.0)
            self._reader = None
        self._disconnect_camera()

    def _require_cam(self) -> Any:
        if self._cam is None:
            raise DeviceUnavailable(f"camera {self.camera_id}: {self._outages.reason or 'not open'}")
        return self._cam

    def set_exposure_us(self, exposure_us: float) -> None:
        try:
            self._require_cam().set_exposure_time(float(exposure_us))
        except DeviceUnavailable:
            raise
        except Exception as exc:
            raise DeviceOperationError(f"camera {self.camera_id}: exposure {exposure_us} us refused: {exc}") from exc

    def set_gain_db(self, gain_db: float) -> None:
        try:
            self._require_cam().set_gain(float(gain_db))
        except DeviceUnavailable:
            raise
        except Exception as exc:
            raise DeviceOperationError(f"camera {self.camera_id}: gain {gain_db} dB refused: {exc}") from exc

    def set_trigger(self, mode: str) -> None:
        """``free_run``, ``software`` or ``hardware`` (``TriggerSource`` from the settings)."""
        if mode not in ("free_run", "software", "hardware"):
            raise DeviceInitError(
                f"camera {self.camera_id}: trigger mode {mode!r} is not free_run, software or hardware"
            )
        cam = self._require_cam()
        self._apply_trigger(cam, mode)  # type: ignore[arg-type]
        self._trigger = mode  # type: ignore[assignment]

    def control_ranges(self) -> dict[str, Any]:
        """The camera's own bounds of exposure (us) and gain (dB) where it has them, and the trigger modes its
        GenICam features allow (hardware and software need ``TriggerMode``/``TriggerSource``)."""
        cam = self._require_cam()
        out: dict[str, Any] = {}
        try:
            if cam.is_exposure_time_available():
                out["exposure_us"] = [float(x) for x in cam.get_exposure_time_bounds()]
            if cam.is_gain_available():
                out["gain_db"] = [float(x) for x in cam.get_gain_bounds()]
        except Exception as exc:  # noqa: BLE001 - a GenICam read error: the device's own words
            raise DeviceOperationError(f"camera {self.camera_id}: its control bounds cannot be read: {exc}") from exc
        modes = ["free_run"]
        if all(self._feature(cam, f) for f in ("TriggerMode", "TriggerSource")):
            modes += ["software", "hardware"] if self._feature(cam, "TriggerSoftware") else ["hardware"]
        out["trigger"] = modes
        return out

    def health(self) -> DeviceHealth:
        c = self.counters
        return self._outages.health(self._cam is not None, frames_received=c["completed"],
                                    frames_incomplete=c["incomplete"], frames_lost=c["lost"])

    def settings(self) -> dict[str, Any]:
        cam = self._require_cam()
        region = cam.get_region()
        out: dict[str, Any] = {
            "device_id": self.config.device_id,
            "model": cam.get_model_name(),
            "serial": cam.get_device_serial_number(),
            "pixel_format": cam.get_pixel_format_as_string(),
            "roi": {"x_px": region.x, "y_px": region.y, "width_px": region.width, "height_px": region.height},
            "exposure_us": cam.get_exposure_time(),
            "gain_db": cam.get_gain(),
            "frame_rate_hz": cam.get_frame_rate(),
            "trigger": self._trigger,
            "buffer_count": self.config.buffer_count,
        }
        out["counters"] = dict(self.counters)
        return out
