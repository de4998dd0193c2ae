"""Cameras through OpenCV's VideoCapture, plus image folders (``kind: opencv``).

Sources:

- ``device``: a V4L2 device by path (``/dev/video0``) or index (``0``), with FOURCC, size, frame
  rate and exposure where the driver accepts them;
- ``file``: a video file (replays plant footage; ``loop`` rewinds at the end);
- ``folder``: an image folder (png/jpg/bmp/tif, in sorted name order; ``loop`` as above);
- ``stream``: a network stream URL (``rtsp://``, ``http://``...).

Live sources (device, stream) are read by a background thread so that ``grab()`` returns the
newest frame, never one that waited in a driver queue; a live source that stops delivering is
reopened with exponential backoff and the outages are counted (``health()``). Files and folders
return their frames in order, one per ``grab()``.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any, Literal

import cv2
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

from drivers.backoff import Backoff, Outages
from drivers.base import (
    CameraBase,
    DeviceInitError,
    DeviceOperationError,
    DeviceTimeout,
    DeviceUnavailable,
    Frame,
)
from drivers.health import DeviceHealth

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
SourceType = Literal["auto", "device", "file", "folder", "stream"]


class OpenCVCameraSettings(BaseModel):
    """Settings of an OpenCV camera: the source and what to ask of it."""

    model_config = ConfigDict(extra="forbid")

    source: str | int = Field(description="/dev/videoN, a device index, a video file, an image folder or a URL")
    source_type: SourceType = "auto"
    fourcc: str | None = Field(None, description="four-character code, e.g. MJPG or YUYV (devices)")
    width_px: int | None = Field(None, gt=0, le=20000)
    height_px: int | None = Field(None, gt=0, le=20000)
    frame_rate_hz: float | None = Field(None, gt=0, le=1000)
    exposure_us: float | None = Field(None, gt=0, le=10_000_000)
    grey: bool = Field(False, description="deliver single-channel grey images")
    loop: bool = Field(True, description="files and folders: start again at the end")
    open_timeout_s: float = Field(5.0, gt=0, le=120)
    stall_timeout_s: float = Field(2.0, gt=0, le=120, description="live source: no frame this long -> reopen")
    reconnect_initial_s: float = Field(0.25, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)

    @field_validator("fourcc")
    @classmethod
    def _fourcc(cls, v: str | None) -> str | None:
        if v is not None and len(v) != 4:
            raise ValueError(f"fourcc must have exactly 4 characters (e.g. MJPG), got {v!r}")
        return v


def _resolve_type(source: str | int, declared: SourceType) -> SourceType:
    if declared != "auto":
        return declared
    if isinstance(source, int) or str(source).isdigit() or str(source).startswith("/dev/video"):
        return "device"
    if "://" in str(source):
        return "stream"
    return "folder" if Path(str(source)).is_dir() else "file"


class OpenCVCamera(CameraBase):
    """A V4L2 camera, video file, image folder or stream through OpenCV."""

    Settings = OpenCVCameraSettings

    def __init__(self, camera_id: str, settings: OpenCVCameraSettings | dict[str, Any]) -> None:
        super().__init__(camera_id)
        self.config = (
            settings if isinstance(settings, OpenCVCameraSettings) else OpenCVCameraSettings.model_validate(settings)
        )
        self.source_type: SourceType = _resolve_type(self.config.source, self.config.source_type)
        self._cap: cv2.VideoCapture | None = None
        self._files: list[Path] = []
        self._index = 0
        self._frame_id = 0
        self._lock = threading.Lock()
        self._newest: Frame | None = None
        self._new_frame = threading.Condition(self._lock)
        self._reader: threading.Thread | None = None
        self._closing = threading.Event()
        self._opened = False
        self._outages = Outages()
        self._outages.reason = "not opened"
        self.frames_read = 0

    # -- opening ---------------------------------------------------------------------------------------
    def open(self) -> None:
        """Open the source; live sources start their reader thread."""
        if self._opened:
            return
        src = self.config.source
        if self.source_type == "folder":
            folder = Path(str(src))
            if not folder.is_dir():
                raise DeviceUnavailable(f"camera {self.camera_id}: image folder {folder} does not exist")
            self._files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self._files:
                raise DeviceInitError(
                    f"camera {self.camera_id}: image folder {folder} has no "
                    f"{'/'.join(s[1:] for s in IMAGE_SUFFIXES)} images"
                )
        elif self.source_type == "file":
            path = Path(str(src))
            if not path.is_file():
                raise DeviceUnavailable(f"camera {self.camera_id}: video file {path} does not exist")
            self._cap = self._open_capture()
        else:
            self._cap = self._open_capture()
            self._closing.clear()
            self._reader = threading.Thread(target=self._read_live, name=f"cam-{self.camera_id}", daemon=True)
            self._reader.start()
        self._opened = True
        if self._reader is None:
            self._outages.up()  # a live source's reader says so itself

    def _open_capture(self) -> cv2.VideoCapture:
        src = self.config.source
        if self.source_type == "device":
            target: str | int = int(src) if isinstance(src, int) or str(src).isdigit() else str(src)
            cap = cv2.VideoCapture(target, cv2.CAP_V4L2)
        elif self.source_type == "stream":
            cap = cv2.VideoCapture(
                str(src),
                cv2.CAP_FFMPEG,
                [
                    cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
                    int(self.config.open_timeout_s * 1000),
                    cv2.CAP_PROP_READ_TIMEOUT_MSEC,
                    int(self.config.stall_timeout_s * 1000),
                ],
            )
        else:
            cap = cv2.VideoCapture(str(src))
        if not cap.isOpened():
            cap.release()
            raise DeviceUnavailable(
                f"camera {self.camera_id}: OpenCV cannot open {self.source_type} {src!r}; "
                "check the path/URL, permissions and that no other program holds it"
            )
        self._apply_capture_settings(cap)
        return cap

    def _apply_capture_settings(self, cap: cv2.VideoCapture) -> None:
        c = self.config
        if self.source_type != "device":
            return
        requests: list[tuple[str, int, float]] = []
        if c.fourcc:
            requests.append(("fourcc", cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter.fourcc(*c.fourcc))))
        if c.width_px:
            requests.append(("width_px", cv2.CAP_PROP_FRAME_WIDTH, float(c.width_px)))
        if c.height_px:
            requests.append(("height_px", cv2.CAP_PROP_FRAME_HEIGHT, float(c.height_px)))
        if c.frame_rate_hz:
            requests.append(("frame_rate_hz", cv2.CAP_PROP_FPS, float(c.frame_rate_hz)))
        if c.exposure_us:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual
            # V4L2's exposure_time_absolute is in units of 100 us
            requests.append(("exposure_us", cv2.CAP_PROP_EXPOSURE, c.exposure_us / 100.0))
        refused = [name for name, prop, value in requests if not cap.set(prop, value)]
        if refused:
            cap.release()
            raise DeviceInitError(
                f"camera {self.camera_id}: the device refused {', '.join(refused)}; "
                "list what it supports with `v4l2-ctl --list-formats-ext`"
            )

    # -- live reading -------------------------------------------------------------------------------
    def _read_live(self) -> None:
        backoff = Backoff(self.config.reconnect_initial_s, self.config.reconnect_max_s)
        last_frame = time.monotonic()
        self._outages.up()
        while not self._closing.is_set():
            cap = self._cap
            ok, img = cap.read() if cap is not None else (False, None)
            now = time.monotonic()
            if ok and img is not None:
                last_frame = now
                backoff.reset()
                self._outages.up()
                self._publish(img, {"source": str(self.config.source)})
                continue
            if now - last_frame < self.config.stall_timeout_s and cap is not None:
                time.sleep(0.01)
                continue
            self._outages.down(f"{self.source_type} {self.config.source!r} delivers no frames; reopening")
            if cap is not None:
                cap.release()
                self._cap = None
            if self._closing.wait(backoff.next_wait_s()):
                return
            self._outages.reconnected()
            try:
                self._cap = self._open_capture()
                last_frame = time.monotonic()
            except (DeviceUnavailable, DeviceInitError) as exc:
                self._outages.down(str(exc))

    def _convert(self, img: NDArray[Any]) -> NDArray[Any]:
        if self.config.grey and img.ndim == 3:
            return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return img

    def _publish(self, img: NDArray[Any], metadata: dict[str, Any]) -> Frame:
        with self._lock:
            self._frame_id += 1
            self.frames_read += 1
            frame = Frame(
                pixels=self._convert(img),
                timestamp_s=time.time(),
                frame_id=self._frame_id,
                camera_id=self.camera_id,
                metadata=metadata,
            )
            self._newest = frame
            self._new_frame.notify_all()
            return frame

    # -- grabbing ---------------------------------------------------------------------------------------
    def grab(self, timeout_s: float = 2.0) -> Frame:
        """Live: the newest frame newer than the last grab. File/folder: the next frame in order."""
        if not self._opened:
            raise DeviceUnavailable(f"camera {self.camera_id} is not open (call open())")
        if self.source_type == "folder":
            return self._grab_folder()
        if self.source_type == "file":
            return self._grab_file()
        deadline = time.monotonic() + timeout_s
        with self._lock:
            last_id = self._newest.frame_id if self._newest is not None else 0
            while self._newest is None or self._newest.frame_id == last_id:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(
                        f"camera {self.camera_id}: no frame within {timeout_s} s "
                        f"({self._outages.reason or 'the source is silent'})"
                    )
                self._new_frame.wait(remaining)
            return self._newest

    def _grab_folder(self) -> Frame:
        if self._index >= len(self._files):
            if not self.config.loop:
                raise DeviceUnavailable(
                    f"camera {self.camera_id}: image folder {self.config.source} is exhausted "
                    f"({len(self._files)} images; set loop: true to start again)"
                )
            self._index = 0
        path = self._files[self._index]
        self._index += 1
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DeviceOperationError(f"camera {self.camera_id}: {path} is not a readable image; replace or remove it")
        if img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        return self._publish(img, {"file": path.name, "index": self._index - 1})

    def _grab_file(self) -> Frame:
        cap = self._cap
        if cap is None:
            raise DeviceUnavailable(f"camera {self.camera_id}: the video file is not open; open() the camera first")
        pos_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
        ok, img = cap.read()
        if not ok and self.config.loop:
            cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            pos_ms = 0.0
            ok, img = cap.read()
        if not ok or img is None:
            raise DeviceUnavailable(
                f"camera {self.camera_id}: video file {self.config.source} has no more "
                "frames (or cannot be decoded); set loop: true to start again"
            )
        return self._publish(img, {"file": str(self.config.source), "position_ms": pos_ms})

    # -- the rest of the contract ---------------------------------------------------------------------
    def close(self) -> None:
        """Stop the reader and release the source; safe to call twice."""
        self._closing.set()
        if self._reader is not None:
            self._reader.join(timeout=5.0)
            self._reader = None
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        self._opened = False

    def set_exposure_us(self, exposure_us: float) -> None:
        if self.source_type != "device" or self._cap is None:
            raise DeviceInitError(f"camera {self.camera_id}: exposure can only be set on a V4L2 device")
        self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)
        if not self._cap.set(cv2.CAP_PROP_EXPOSURE, exposure_us / 100.0):
            raise DeviceOperationError(f"camera {self.camera_id}: the device refused exposure {exposure_us} us")

    def health(self) -> DeviceHealth:
        live = self.source_type in ("device", "stream")
        available = self._opened and (not live or self._cap is not None)
        return self._outages.health(available, frames_received=self.frames_read)

    def settings(self) -> dict[str, Any]:
        out: dict[str, Any] = {"source": self.config.source, "source_type": self.source_type}
        if self.source_type == "folder":
            out["images"] = len(self._files)
        elif self._cap is not None:
            out["width_px"] = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))
            out["height_px"] = int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            out["frame_rate_hz"] = float(self._cap.get(cv2.CAP_PROP_FPS))
            if self.source_type == "file":
                out["frames"] = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        return out
