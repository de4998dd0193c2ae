"""Every IO adapter meets the DigitalIO Protocol and reports typed health, before it is ever opened.

(Their behaviour against real peers is in test_modbus_robot.py, test_serial_light.py and
test_robotiq_gripper.py.)
"""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.base import DeviceUnavailable, DigitalIO
from drivers.health import DeviceHealth, Monitored
from drivers.registry import adapter_class, kinds


def _settings(kind: str, tmp_path: Path) -> dict[str, object]:
    if kind == "modbus":
        return {"host": "127.0.0.1", "port": 1, "timeout_s": 0.2}  # nothing listens on port 1
    if kind == "sim_gripper":
        return {"scene": None}  # the built-in virtual cell has no production parts: nothing to grip
    return {"port": str(tmp_path / "no-such-tty")}


@pytest.mark.parametrize("kind", kinds("io"))
def test_io_adapter_is_a_digital_io_with_typed_health(kind: str, tmp_path: Path) -> None:
    cls = adapter_class("io", kind)
    io = cls("io0", _settings(kind, tmp_path))
    assert isinstance(io, DigitalIO) and isinstance(io, Monitored)
    h = io.health()
    assert isinstance(h, DeviceHealth) and not h.available and h.reason
    with pytest.raises(DeviceUnavailable):
        io.open()
    io.close()
    io.close()
