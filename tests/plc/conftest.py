"""The PLC tests' served cell: one ``tests.support.served_plc`` cell for the whole session."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.conftest import stop_served
from tests.support.served_plc import RECIPE, SEED, PlcCell, prepare_cell, start_plc_cell

__all__ = ["RECIPE", "SEED", "PlcCell", "prepare_cell", "start_plc_cell"]


@pytest.fixture(scope="session")
def plc_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PlcCell]:
    """One served virtual cell with Modbus TCP and OPC UA (security none) for the PLC tests."""
    cell = start_plc_cell(tmp_path_factory.mktemp("plc"))
    try:
        yield cell
    finally:
        stop_served(cell.served)
