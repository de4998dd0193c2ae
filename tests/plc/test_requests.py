"""PLC requests in process: how failures become the documented error classes and texts."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration import geometry as g
from cellctl.cell import Cell
from cellctl.config import load_config, parse_config
from cellctl.jobs import JobManager
from cellctl.plc.requests import (
    CLASS_DRIFT,
    CLASS_REQUEST,
    CLASS_RUNTIME,
    CLASS_SETUP,
    ERROR_TEXTS,
    TEXT_BAD_RECIPE,
    TEXT_DRIFTED,
    TEXT_NO_CALIBRATION,
    TEXT_RECIPE_RANGE,
    TEXT_STORE,
    execute_pick,
    execute_verify,
)
from cellctl.services import Services
from cellctl.store import open_store
from tests.plc.conftest import RECIPE, prepare_cell
from tests.store.helpers import damage_table


@pytest.fixture(scope="module")
def prepared(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path, _ = prepare_cell(tmp_path_factory.mktemp("plc-req"), {})
    return path


def services_of(path: Path) -> Services:
    config = load_config(path)
    return Services(config, Cell(config), open_store(config), JobManager())


@pytest.fixture()
def services(prepared: Path) -> Iterator[Services]:
    svc = services_of(prepared)
    try:
        yield svc
    finally:
        svc.close()


def test_error_table_is_consistent() -> None:
    assert ERROR_TEXTS[0] == (0, "no error")
    assert all(0 <= cls <= 9 and text for cls, text in ERROR_TEXTS.values())
    assert len({text for _, text in ERROR_TEXTS.values()}) == len(ERROR_TEXTS)


def test_recipe_out_of_range_and_unusable_recipe(services: Services) -> None:
    out = execute_pick(services, 70000, "test")
    assert not out.ok and out.text_index == TEXT_RECIPE_RANGE and out.error_class == CLASS_REQUEST
    assert "70000" in out.message
    services.store.save_recipe(5, "broken", {"name": "broken", "models": [{"format": "nonsense"}]}, "test")
    out = execute_pick(services, 5, "test")
    assert not out.ok and out.text_index == TEXT_BAD_RECIPE and out.error_class == CLASS_SETUP
    assert out.message.startswith("recipe 5 cannot be used")


def test_pick_without_an_active_calibration(prepared: Path, tmp_path: Path) -> None:
    data = yaml.safe_load(prepared.read_text())
    data["store"] = {"path": str(tmp_path / "empty.db")}
    config = parse_config(data)
    svc = Services(config, Cell(config), open_store(config), JobManager())
    try:
        src = open_store(load_config(prepared))
        r = src.get_recipe(RECIPE)
        src.close()
        svc.store.save_recipe(RECIPE, r.name, r.data, "test")
        out = execute_pick(svc, RECIPE, "test")
    finally:
        svc.close()
    assert not out.ok and out.text_index == TEXT_NO_CALIBRATION and out.error_class == CLASS_SETUP
    assert out.picks == []


def test_verify_of_a_drifted_hand_eye_is_the_drift_error(services: Services) -> None:
    he = services.store.active("handeye", "cam0", "robot0")
    assert he is not None
    moved = dict(he.result)
    T = np.array(moved["T_tool_cam"])
    moved["T_tool_cam"] = (T @ g.make_transform(np.eye(3), [0.004, 0.0, 0.0])).tolist()  # camera knocked 4 mm
    bad = services.store.save_calibration("handeye", "cam0", "robot0", moved, {}, creator="test", note="knocked")
    services.store.activate(bad.id, "test")
    try:
        out = execute_verify(services, "test")
    finally:
        services.store.activate(he.id, "test")
    assert not out.ok and out.text_index == TEXT_DRIFTED and out.error_class == CLASS_DRIFT
    assert out.verify is not None and out.verify["passed"] is False and out.verify["drift_mm"] > 0.5
    assert "calibration drifted" in out.message
    assert execute_verify(services, "test").ok  # the true one again


def test_a_damaged_store_is_a_runtime_error_naming_the_restore(tmp_path: Path) -> None:
    """Not an internal error: the PLC shows "call the engineer", the message says how to restore."""
    path, _ = prepare_cell(tmp_path, {})
    damage_table(tmp_path / "cell.db", "recipes")
    svc = services_of(path)
    try:
        out = execute_pick(svc, RECIPE, "test")
    finally:
        svc.close()
    assert (out.ok, out.text_index, out.error_class) == (False, TEXT_STORE, CLASS_RUNTIME)
    assert "cell.db is damaged" in out.message and "cellctl store restore --config" in out.message


def test_verify_goes_through_the_one_start_with_typed_refusals(prepared: Path, tmp_path: Path) -> None:
    """The PLC's verify is started by ``cellctl.routines.start`` as REST's is: it holds the robot still
    (refused while another caller owns it), is preflighted (no active calibration is said at once,
    before a job runs) and its refusals are sorted by type, not by their text."""
    from cellctl.plc.requests import TEXT_ROBOT_BUSY

    svc = services_of(prepared)
    try:
        started_before = len(svc.store.audit_log(limit=10_000, action="routine.start"))
        robot = svc.cell.robot("robot0").ensure_open()
        other = robot.motion.begin("someone", "a test holding the robot")
        try:
            busy = execute_verify(svc, "test")
        finally:
            robot.motion.end(other)
        assert not busy.ok and busy.text_index == TEXT_ROBOT_BUSY, busy
        assert not svc.jobs.list()  # refused before a job started
        ok = execute_verify(svc, "test")
        assert ok.ok, ok
        assert [j.name for j in svc.jobs.list()] == ["verify"]
        started = svc.store.audit_log(limit=10_000, action="routine.start")
        assert len(started) == started_before + 1 and ("test", "verify") in [(e.who, e.target) for e in started]
    finally:
        svc.close()

    data = yaml.safe_load(prepared.read_text())
    data["store"] = {"path": str(tmp_path / "empty.db")}
    config = parse_config(data)
    empty = Services(config, Cell(config), open_store(config), JobManager())
    try:
        out = execute_verify(empty, "test")
        assert not out.ok and out.text_index == TEXT_NO_CALIBRATION and out.error_class == CLASS_SETUP, out
        assert "no active calibration" in out.message and not empty.jobs.list()
    finally:
        empty.close()
