"""The test-kind markers: registered in pyproject.toml and assigned by tests/conftest.py."""

from __future__ import annotations

import tomllib
from types import SimpleNamespace
from typing import Any, cast

import pytest

from tests.conftest import (
    REPO,
    SLOW_LIST,
    UR_GROUP,
    XdistGroupIds,
    kinds_of,
    never_selected,
    slow_tests,
    xdist_group_of,
)

KINDS = {"unit", "peer", "e2e", "browser", "slow"}
# Spelled in pieces: the module scan of tests/conftest.py must not take this file for a peer or e2e test.
SERVED, START, PEER, PG = "served" + "_virtual_cell", "start" + "_served(tmp)", "Peer" + "Process", "post" + "gres"
MODBUS_CLIENT, OPCUA_CLIENT = "from pymodbus" + ".client import ModbusTcpClient", "from " + "asyncua import Client"


def test_the_markers_are_registered() -> None:
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    names = {m.split(":", 1)[0] for m in config["tool"]["pytest"]["ini_options"]["markers"]}
    assert names >= KINDS


def test_kinds_by_path_fixture_and_module() -> None:
    assert kinds_of("ui/test_operator_page.py", ["page"], "") == {"browser", "e2e"}
    assert kinds_of("cellctl/test_auth.py", [SERVED], "") == {"e2e"}
    assert kinds_of("cellctl/test_tls.py", ["tmp_path"], "served = " + START) == {"e2e"}
    assert kinds_of("drivers/test_ur_rtde.py", ["ur" + "_emulator"], "") == {"peer"}
    assert kinds_of("drivers/test_serial_light.py", ["tmp_path"], "from tests.drivers.peers import " + PEER) \
        == {"peer"}
    assert kinds_of("store/test_store.py", ["store_url", PG], "") == {"peer"}
    assert kinds_of("test_readme.py", ["tmp_path"], "") == {"e2e"}
    # a PLC client against the PLC servers of the app in this process: a peer, not a served process
    assert kinds_of("plc/test_modbus_server.py", ["plc_app"], MODBUS_CLIENT) == {"peer"}
    assert kinds_of("plc/test_opcua_server.py", ["plc_app"], OPCUA_CLIENT) == {"peer"}
    assert kinds_of("calibration/test_pnp.py", ["tmp_path"], "import numpy as np") == {"unit"}


def test_a_file_is_left_uncollected_only_where_the_mark_expression_deselects_all_its_tests() -> None:
    """``-m``: a whole-slow file (or a page test file) is not imported when no test of it can be selected."""
    assert never_selected("not slow", {"slow"})
    assert never_selected("unit and not slow", {"slow"}) and never_selected("not (slow or peer)", {"slow"})
    assert not never_selected("slow", {"slow"}) and not never_selected("e2e or not slow", {"slow"})
    assert not never_selected("not unit", {"slow"}) and not never_selected("browser", {"browser", "slow"})
    assert never_selected("not browser", {"browser", "e2e", "slow"})


def test_the_slow_list_parses_and_names_tests_that_exist() -> None:
    assert slow_tests(["# a comment", "", "tests/a.py::test_x  # 20 s", "tests/b.py"]) == {"tests/a.py::test_x",
                                                                                       "tests/b.py"}
    listed = slow_tests(SLOW_LIST.read_text().splitlines())
    assert listed
    missing = [n for n in listed if not (REPO / n.split("::", 1)[0]).is_file()]
    assert not missing, f"tests/slow.txt names files that are gone: {missing}"


def test_this_test_got_its_marker(request: pytest.FixtureRequest) -> None:
    assert request.node.get_closest_marker("unit") is not None
    assert request.node.get_closest_marker("slow") is None


def test_only_the_ur_cases_of_a_ur_module_share_the_emulators_worker() -> None:
    def case(adapter: str) -> Any:
        return SimpleNamespace(callspec=SimpleNamespace(params={"rig": adapter}), fixturenames=["rig", "tmp_path"])

    text = PEER + '("drivers.peers.ur' + '_emulator")'
    assert xdist_group_of(case("ur_rtde"), "drivers/test_robot_contract.py", text) == UR_GROUP
    for adapter in ("sim", "modbus", "replay"):
        assert xdist_group_of(case(adapter), "drivers/test_robot_contract.py", text) is None
    plain: Any = SimpleNamespace(fixturenames=["tmp_path"])  # not parametrized: a UR test
    assert xdist_group_of(plain, "drivers/test_ur_rtde.py", text) == UR_GROUP
    assert xdist_group_of(plain, "drivers/test_motion.py", "import numpy") is None


def test_a_group_reaches_the_node_id_the_scheduler_splits() -> None:
    """xdist's loadgroup scheduler groups by the ``@group`` suffix of node ids (not by the mark itself)."""
    from xdist.scheduler.loadgroup import LoadGroupScheduling

    mark = pytest.mark.xdist_group("cellctl/test_x.py").mark
    item: Any = SimpleNamespace(nodeid="tests/cellctl/test_x.py::test_y[1]", _id=None,
                                iter_markers=lambda name: [mark] if name == "xdist_group" else [])
    loose: Any = SimpleNamespace(nodeid="tests/a.py::test_b", _id=None, iter_markers=lambda name: [])
    XdistGroupIds().pytest_collection_modifyitems(cast(Any, SimpleNamespace(option=SimpleNamespace(loadgroup=True))),
                                                  [item, loose])
    assert str(item._id) == "tests/cellctl/test_x.py::test_y[1]@cellctl/test_x.py" and loose._id is None
    assert LoadGroupScheduling._split_scope(cast(Any, None), str(item._id)) == "cellctl/test_x.py"
