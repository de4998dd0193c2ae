"""The slots in doubt reach the PLC (issue 34): the Modbus in-doubt block (236..240, pymodbus as the
PLC) and the values of the OPC UA variables ``ProductionSlotsInDoubt`` / ``ProductionFirstSlotInDoubt``
/ ``ProductionFirstSlotInDoubtRecipe`` count them and name the first, from the store: a claim a dead
service left (in doubt at the start), one put in doubt while serving, and an engineer's confirm
(REST) that takes them away.

The app in this process (``in_process_cell``, the built-in virtual cell) with the Modbus server on a
loopback port; the claims are written as a run writes them (``Store.claim_slot``, ``slot_in_doubt``).
"""

from __future__ import annotations

from pathlib import Path

import yaml
from pymodbus.client import ModbusTcpClient

from cellctl.config import default_config_text, load_config
from cellctl.plc import modbus_map as mm
from cellctl.plc import opcua_production
from cellctl.services import Services
from cellctl.store import open_store
from tests.support.app import AppCell, in_process_cell
from tests.support.served import free_port
from tests.support.served_plc import plc_section

UNIT = 1
OPCUA_NAMES = ("ProductionSlotsInDoubt", "ProductionFirstSlotInDoubt", "ProductionFirstSlotInDoubtRecipe")


def modbus_doubt(port: int) -> tuple[int, int, int]:
    """(count, first recipe, first slot) as a PLC reads them: one FC3 of the block."""
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
    assert client.connect()
    try:
        r = client.read_holding_registers(mm.address("DOUBT_COUNT"), count=mm.END - mm.address("DOUBT_COUNT"),
                                          device_id=UNIT)
        assert not r.isError(), r
        w = list(r.registers)
        return w[0], mm.words_int32(w[1:3]), mm.words_int32(w[3:5])
    finally:
        client.close()


def opcua_doubt(services: Services) -> tuple[int, int, int]:
    """(count, first slot, first recipe): the values the OPC UA variables are written from (every 0.1 s,
    ``refresh_production``; an OPC UA server costs seconds of start-up that this test does not need)."""
    values = opcua_production.production_values(services)
    return tuple(int(values[n]) for n in OPCUA_NAMES)  # type: ignore[return-value]


def test_the_slots_in_doubt_reach_the_plc_and_a_confirm_takes_them_away(tmp_path: Path) -> None:
    modbus_port = free_port()
    data = yaml.safe_load(default_config_text())
    data["store"] = {"path": str(tmp_path / "cell.db")}
    data["plc"] = {"modbus": plc_section(modbus_port, 4840)["modbus"]}
    config = tmp_path / "cell.yaml"
    config.write_text(yaml.safe_dump(data))
    with open_store(load_config(config)) as store:
        # A run of recipe 2 killed while it carried its part to slot 5: the claim is left 'claimed'.
        killed = store.new_run(2, "robot0", "eng")
        store.claim_slot(2, 5, killed, 1, {"phase": "carrying"})
        # A run of recipe 1 stopped between claim and release: slot 3 in doubt already.
        stopped = store.new_run(1, "robot0", "eng")
        store.claim_slot(1, 3, stopped, 4, {"phase": "over_slot"})
        store.slot_in_doubt(1, 3, stopped, {"phase": "over_slot"})
        store.update_run(stopped, "stopped", "stopped", {}, ended=True)
    with in_process_cell(tmp_path, config) as cell:
        walk(cell, modbus_port, killed)


def walk(cell: AppCell, modbus_port: int, killed: int) -> None:
    """The PLC's view through the claims' changes."""
    http = cell.http()
    services: Services = cell.client.app.state.services  # type: ignore[attr-defined]
    listed = [(d["recipe_id"], d["slot"]) for d in http.get("/production").json()["slots_in_doubt"]]
    assert listed == [(1, 3), (2, 5)], listed  # the dead service's claim is in doubt after the start
    assert modbus_doubt(modbus_port) == (2, 1, 3)
    assert opcua_doubt(services) == (2, 3, 1)

    # A run puts another slot in doubt while the service serves: the PLC sees it on its next read.
    store = services.store
    store.claim_slot(2, 6, killed, 2, {"phase": "released"})
    assert modbus_doubt(modbus_port) == (2, 1, 3)  # only claimed: not in doubt
    store.slot_in_doubt(2, 6, killed, {"phase": "released"})
    assert modbus_doubt(modbus_port) == (3, 1, 3)

    # The engineer looked: slot 3 of recipe 1 is empty. The first in doubt is now recipe 2's slot 5.
    r = http.post("/production/slots/3/confirm", json={"recipe_id": 1, "occupied": False})
    assert r.status_code == 200, r.text
    assert modbus_doubt(modbus_port) == (2, 2, 5)
    assert opcua_doubt(services) == (2, 5, 2)
    for slot in (5, 6):
        r = http.post(f"/production/slots/{slot}/confirm", json={"recipe_id": 2, "occupied": True})
        assert r.status_code == 200, r.text
    assert modbus_doubt(modbus_port) == (0, -1, -1)
    assert opcua_doubt(services) == (0, -1, -1)
    # Confirming a slot that is no longer in doubt changes nothing.
    assert http.post("/production/slots/5/confirm", json={"recipe_id": 2, "occupied": False}).status_code == 404
    assert modbus_doubt(modbus_port) == (0, -1, -1)


def test_the_block_is_built_from_the_table() -> None:
    words = mm.doubt_block_words(3, 65535, 1_000_000)
    assert len(words) == mm.END - mm.address("DOUBT_COUNT") == 5
    assert (words[0], mm.words_int32(words[1:3]), mm.words_int32(words[3:5])) == (3, 65535, 1_000_000)
    none = mm.doubt_block_words(0, None, None)
    assert (none[0], mm.words_int32(none[1:3]), mm.words_int32(none[3:5])) == (0, -1, -1)
    assert mm.doubt_block_words(None, None, None)[0] == mm.DOUBT_UNKNOWN == 0xFFFF  # the store cannot say
    assert mm.doubt_block_words(70_000, 1, 2)[0] == 0xFFFE  # a count never reads as "not known"
