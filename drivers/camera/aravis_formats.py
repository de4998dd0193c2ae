"""The Aravis adapter's settings, its binding import, and raw GenICam buffers to OpenCV images.

Pixel formats: Mono8, Mono12/Mono16 (uint16, little-endian), Bayer*8 (demosaiced to BGR) and
RGB8 (to BGR). The binding (PyGObject + Debian's typelib ``gir1.2-aravis-0.8``) is imported only
when an adapter is built, with a message naming the packages when it is missing.
"""

from __future__ import annotations

from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from drivers.base import DeviceInitError

PixelFormat = Literal["Mono8", "Mono12", "Mono16", "BayerRG8", "BayerBG8", "BayerGR8", "BayerGB8", "RGB8"]
TriggerMode = Literal["free_run", "software", "hardware"]
Interface = Literal["GigEVision", "USB3Vision", "Fake"]
_BAYER_TO_CV = {
    "BayerRG8": cv2.COLOR_BayerBG2BGR,
    "BayerBG8": cv2.COLOR_BayerRG2BGR,
    "BayerGR8": cv2.COLOR_BayerGB2BGR,
    "BayerGB8": cv2.COLOR_BayerGR2BGR,
}
"""GenICam names the first row's pixels (BayerRG: R G / G B); OpenCV names the second row's."""
MISSING_BINDING = (
    "the Aravis Python binding is missing: install the Debian packages libaravis-0.8-0 "
    "gir1.2-aravis-0.8 (and aravis-tools for the fake camera; build deps libgirepository1.0-dev "
    "libcairo2-dev pkg-config), then `pip install 'PyGObject>=3.42,<3.51'` into the venv"
)


class Roi(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x_px: int = Field(0, ge=0)
    y_px: int = Field(0, ge=0)
    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)


class AravisCameraSettings(BaseModel):
    """Settings of a GenICam camera reached through Aravis."""

    model_config = ConfigDict(extra="forbid")

    device_id: str = Field(min_length=1, description="Aravis device id, serial number or IP address")
    interfaces: list[Interface] = Field(
        default_factory=lambda: list[Interface](["GigEVision", "USB3Vision"]),
        description="Aravis transports to enable (others stay disabled)",
    )
    pixel_format: PixelFormat | None = None
    exposure_us: float | None = Field(None, gt=0, le=60_000_000)
    gain_db: float | None = Field(None, ge=0, le=60)
    roi: Roi | None = None
    frame_rate_hz: float | None = Field(None, gt=0, le=10_000)
    trigger: TriggerMode = "free_run"
    trigger_source: str = Field("Line1", min_length=1, description="GenICam TriggerSource in hardware mode")
    buffer_count: int = Field(8, ge=2, le=256, description="bounded pool of stream buffers")
    packet_size_bytes: int | None = Field(None, ge=576, le=16384, description="GigE packet size (None: negotiate)")
    stall_timeout_s: float = Field(2.0, gt=0, le=120, description="free run: no frame this long -> check camera")
    reconnect_initial_s: float = Field(0.25, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)


def import_aravis() -> Any:
    """The ``Aravis`` GI module; DeviceInitError naming the packages to install when it is missing."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise DeviceInitError(MISSING_BINDING) from exc
    return Aravis


def to_pixels(data: bytes, width: int, height: int, pixel_format: str) -> NDArray[Any]:
    """Raw buffer bytes to an OpenCV image: grey (uint8/uint16) or BGR."""
    if pixel_format in ("Mono12", "Mono16"):
        return np.frombuffer(data, dtype="<u2", count=width * height).reshape(height, width).copy()
    if pixel_format == "RGB8":
        rgb = np.frombuffer(data, dtype=np.uint8, count=width * height * 3).reshape(height, width, 3)
        return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    mono = np.frombuffer(data, dtype=np.uint8, count=width * height).reshape(height, width)
    if pixel_format in _BAYER_TO_CV:
        return cv2.cvtColor(mono, _BAYER_TO_CV[pixel_format])
    return mono.copy()
