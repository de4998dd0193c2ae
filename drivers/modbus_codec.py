"""Modbus register codecs: 16- and 32-bit integers and IEEE floats in one or two holding registers.

One place for the conversions the Modbus robot adapter and its simulator share (pymodbus does
the packing; the word order of 32-bit values is the device's, ``big`` or ``little``).
"""

from __future__ import annotations

from typing import Literal

from pymodbus.client import ModbusTcpClient

DataTypeName = Literal["int16", "uint16", "int32", "uint32", "float32"]
WordOrder = Literal["big", "little"]
WIDTH: dict[str, int] = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2}
"""Registers each data type takes."""
_DT = ModbusTcpClient.DATATYPE
_PYMODBUS_TYPE = {
    "int16": _DT.INT16,
    "uint16": _DT.UINT16,
    "int32": _DT.INT32,
    "uint32": _DT.UINT32,
    "float32": _DT.FLOAT32,
}


def decode(regs: list[int], data_type: DataTypeName, word_order: WordOrder, scale: float = 1.0) -> float:
    """The engineering value (raw value x ``scale``) held in ``regs``."""
    value = ModbusTcpClient.convert_from_registers(regs, _PYMODBUS_TYPE[data_type], word_order=word_order)
    return float(value) * scale  # type: ignore[arg-type]


def encode(value: float, data_type: DataTypeName, word_order: WordOrder, scale: float = 1.0) -> list[int]:
    """The registers holding engineering value ``value`` (raw = value / ``scale``, rounded for integers)."""
    raw: float | int = value / scale
    if data_type != "float32":
        raw = int(round(raw))
    regs: list[int] = ModbusTcpClient.convert_to_registers(raw, _PYMODBUS_TYPE[data_type], word_order=word_order)
    return regs
