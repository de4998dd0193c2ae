"""LED light controllers with an ASCII command protocol on a serial port (``kind: serial_light``).

The commands are templates in the settings (the defaults speak the protocol of
``drivers/peers/serial_light.py``; most controllers differ only in the words): set a channel's
intensity, read it back, fire a strobe pulse. As a digital IO device, output *ch* switches channel
*ch* on (at ``on_intensity_percent``) or off, and input *ch* reads whether it is lit.

Every command waits at most ``timeout_s`` for its reply line; a missing, malformed or error reply
raises a typed error naming the command and the reply. A port that disappears (cable pulled, USB
adapter gone) is reopened on the next command, no more often than the backoff allows; outages
are counted (``health()``).
"""

from __future__ import annotations

import re
import termios
import threading
from typing import Any

import serial
from pydantic import BaseModel, ConfigDict, Field

from drivers.backoff import Backoff, Outages
from drivers.base import DeviceOperationError, DeviceTimeout, DeviceUnavailable, DigitalIOBase
from drivers.health import DeviceHealth


class SerialLightSettings(BaseModel):
    """Port, line settings and command templates of the light controller."""

    model_config = ConfigDict(extra="forbid")

    port: str = Field(min_length=1, description="serial device, e.g. /dev/ttyUSB0")
    baudrate: int = Field(115200, ge=300, le=4_000_000)
    timeout_s: float = Field(0.5, gt=0, le=30, description="deadline of one reply line")
    channels: int = Field(4, ge=1, le=64)
    max_raw_intensity: int = Field(255, ge=1, le=65535, description="raw value of 100 %")
    on_intensity_percent: float = Field(100.0, gt=0, le=100)
    terminator: str = Field("\r", min_length=1, max_length=2)
    set_command: str = "SET {channel} {value}"
    get_command: str = "GET {channel}"
    get_reply: str = Field(r"^(?P<channel>\d+) (?P<value>\d+)$", description="regex with a 'value' group")
    strobe_command: str = "STROBE {channel} {duration_us}"
    ok_reply: str = "OK"
    error_prefix: str = "ERR"
    reconnect_initial_s: float = Field(0.25, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)


class SerialLightController(DigitalIOBase):
    """An LED light controller (intensity per channel, strobe) on a serial port."""

    Settings = SerialLightSettings

    def __init__(self, io_id: str, settings: SerialLightSettings | dict[str, Any]) -> None:
        super().__init__(io_id)
        self.config = (
            settings if isinstance(settings, SerialLightSettings) else SerialLightSettings.model_validate(settings)
        )
        self._ser: serial.Serial | None = None
        self._lock = threading.Lock()
        self._outages = Outages()
        self._outages.reason = "not opened"
        self._backoff = Backoff(self.config.reconnect_initial_s, self.config.reconnect_max_s)
        self._get_re = re.compile(self.config.get_reply)

    # -- port -----------------------------------------------------------------------------------------
    def open(self) -> None:
        with self._lock:
            self._open_port(force=True)

    def _open_port(self, force: bool = False) -> serial.Serial:
        if self._ser is not None:
            return self._ser
        if not force and not self._backoff.due():
            raise DeviceUnavailable(
                f"io {self.io_id}: serial port {self.config.port} is gone ({self._outages.reason}); "
                f"next attempt in {self._backoff.remaining_s():.1f} s"
            )
        try:
            self._ser = serial.Serial(
                self.config.port,
                baudrate=self.config.baudrate,
                timeout=self.config.timeout_s,
                write_timeout=self.config.timeout_s,
            )
        except (serial.SerialException, OSError) as exc:
            self._backoff.schedule()
            self._fail(f"cannot open {self.config.port}: {exc}")
            raise DeviceUnavailable(
                f"io {self.io_id}: cannot open serial port {self.config.port}: {exc}; check the "
                "cable/adapter and the permissions (group dialout)"
            ) from exc
        if not force:
            self._outages.reconnected()
        self._backoff.reset()
        return self._ser

    def _fail(self, reason: str) -> None:
        self._outages.down(reason)

    def close(self) -> None:
        with self._lock:
            if self._ser is not None:
                self._ser.close()
                self._ser = None

    # -- one command -------------------------------------------------------------------------------------
    def command(self, text: str) -> str:
        """Send one command line and return its reply line (without terminator)."""
        with self._lock:
            ser = self._open_port()
            try:
                ser.reset_input_buffer()
                ser.write(text.encode("ascii") + self.config.terminator.encode("ascii"))
                raw = ser.read_until(b"\n")
            except (serial.SerialException, OSError, termios.error) as exc:
                ser.close()
                self._ser = None
                self._fail(f"serial port error: {exc}")
                raise DeviceUnavailable(
                    f"io {self.io_id}: serial port {self.config.port} failed during {text!r}: "
                    f"{exc}; it is reopened on the next command"
                ) from exc
            if not raw.endswith(b"\n"):
                self._fail(f"no reply to {text!r}")
                raise DeviceTimeout(
                    f"io {self.io_id}: no reply to {text!r} within {self.config.timeout_s} s "
                    f"(got {raw!r}); check power, cable and baud rate ({self.config.baudrate})"
                )
            try:
                reply = raw.decode("ascii").strip()
            except UnicodeDecodeError:
                self._fail(f"malformed reply to {text!r}")
                raise DeviceOperationError(
                    f"io {self.io_id}: malformed reply to {text!r}: {raw!r}; check the baud "
                    "rate and that the device speaks this protocol"
                ) from None
            if reply.startswith(self.config.error_prefix):
                self._outages.up()
                raise DeviceOperationError(f"io {self.io_id}: the controller rejected {text!r}: {reply}")
            self._outages.up()
            return reply

    def _expect_ok(self, text: str) -> None:
        reply = self.command(text)
        if reply != self.config.ok_reply:
            raise DeviceOperationError(
                f"io {self.io_id}: unexpected reply to {text!r}: {reply!r} (expected {self.config.ok_reply!r})"
            )

    def _check_channel(self, channel: int) -> None:
        if not 0 <= channel < self.config.channels:
            raise DeviceOperationError(f"io {self.io_id}: channel {channel} is not in 0..{self.config.channels - 1}")

    # -- light API --------------------------------------------------------------------------------------
    def set_intensity_percent(self, channel: int, percent: float) -> None:
        self._check_channel(channel)
        if not 0 <= percent <= 100:
            raise DeviceOperationError(f"io {self.io_id}: intensity {percent} % is not in 0..100 %")
        value = round(percent / 100.0 * self.config.max_raw_intensity)
        self._expect_ok(self.config.set_command.format(channel=channel, value=value))

    def intensity_percent(self, channel: int) -> float:
        self._check_channel(channel)
        text = self.config.get_command.format(channel=channel)
        reply = self.command(text)
        m = self._get_re.match(reply)
        if m is None:
            raise DeviceOperationError(f"io {self.io_id}: malformed reply to {text!r}: {reply!r}")
        return 100.0 * int(m.group("value")) / self.config.max_raw_intensity

    def strobe(self, channel: int, duration_us: int) -> None:
        self._check_channel(channel)
        if not 1 <= duration_us <= 1_000_000:
            raise DeviceOperationError(f"io {self.io_id}: strobe duration {duration_us} us is not in 1..1000000 us")
        self._expect_ok(self.config.strobe_command.format(channel=channel, duration_us=int(duration_us)))

    # -- DigitalIO contract -----------------------------------------------------------------------------
    def write_output(self, channel: int, value: bool) -> None:
        self.set_intensity_percent(channel, self.config.on_intensity_percent if value else 0.0)

    def read_input(self, channel: int) -> bool:
        return self.intensity_percent(channel) > 0

    def health(self) -> DeviceHealth:
        return self._outages.health(self._outages.is_up)
