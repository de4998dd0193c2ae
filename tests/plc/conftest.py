"""The PLC tests' cells: the virtual cell with its Modbus TCP and OPC UA servers on loopback, the true
calibrations active and recipe 1 taught (``tests.support.served_plc``).

``plc_app``: the app in this process, one per test module (what the PLC tests use: no interpreter to
start, no imports or warm-up to pay again). ``plc_cell``: the same cell as a ``cellctl serve``
process, one per session, for a test that needs the served process itself.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.support.served import stop_served
from tests.support.served_plc import RECIPE, SEED, PlcApp, PlcCell, in_process_plc, prepare_cell, start_plc_cell

__all__ = ["RECIPE", "SEED", "PlcApp", "PlcCell", "prepare_cell", "start_plc_cell"]


@pytest.fixture(scope="module")
def plc_app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PlcApp]:
    """The cell in this process, security none. Module scope, not session: the app holds
    ``CELLCTL_DATA_DIR`` while it runs (``in_process_cell``), which must not outlive the module."""
    with in_process_plc(tmp_path_factory.mktemp("plc")) as cell:
        yield cell


@pytest.fixture(scope="session")
def plc_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PlcCell]:
    """The cell as one served ``cellctl serve`` process for the session, security none."""
    cell = start_plc_cell(tmp_path_factory.mktemp("plc-served"))
    try:
        yield cell
    finally:
        stop_served(cell.served)
