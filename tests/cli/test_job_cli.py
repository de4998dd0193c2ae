"""``cellctl job list|cancel|status`` against a served cell, and the CLI's global flags."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import cellctl
from tests.conftest import Served, start_served, stop_served
from tests.support.cli import run_cli


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("jobs"))
    try:
        yield s
    finally:
        stop_served(s)


def _job(served: Served, *args: str) -> Any:
    r = run_cli("job", *args, "--url", served.base_url, "--token", served.token)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_list_shows_a_running_job_and_cancel_ends_it(served: Served) -> None:
    started = _job(served, "run", "jog-to-mark")  # waits for the operator: it stays running
    assert started["state"] == "running"
    listed = _job(served, "list", "--json")
    assert started["id"] in [j["id"] for j in listed]
    _job(served, "cancel", started["id"])
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        job = _job(served, "status", started["id"])
        if job["state"] != "running":
            break
        time.sleep(0.2)
    assert job["state"] == "cancelled"


def test_cancel_of_an_unknown_job_is_one_line(served: Served) -> None:
    r = run_cli("job", "cancel", "nosuch", "--url", served.base_url, "--token", served.token)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and "unknown_job" in r.stderr


def test_version() -> None:
    r = run_cli("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"cellctl {cellctl.__version__}"


@pytest.mark.parametrize("where", ["before", "after"])
def test_verbose_before_or_after_the_command(tmp_path: Path, where: str) -> None:
    cmd = ["target", "render", "--target", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "t.svg")]
    r = run_cli(*(["-v", *cmd] if where == "before" else [*cmd, "-v"]))
    assert r.returncode == 2 and "Traceback (most recent call last)" in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("cellctl: error:")
    assert "Traceback" not in run_cli(*cmd).stderr
