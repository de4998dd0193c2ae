"""The CLI answers for the service it names: the session token is the one of the service at ``--url``
(not the newest ``*.session-token`` in the data dir), ``job list`` is a table (``--json`` for JSON),
and ``job run NAME --help`` shows that routine only."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator

import pytest

from tests.conftest import Served, start_served, stop_served
from tests.support.cli import run_cli


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = start_served(tmp_path_factory.mktemp("target"))
    try:
        yield s
    finally:
        stop_served(s)


def _env(served: Served) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("CELLCTL_TOKEN", "CELLCTL_URL")}
    return {**env, "CELLCTL_DATA_DIR": str(served.data_dir)}


def test_the_token_is_the_one_of_the_service_at_url(served: Served) -> None:
    # Another cell's token file, newer than this service's: the old rule (newest file) took it and got a 401.
    other = served.data_dir / "production-cell.session-token"
    other.write_text("not-this-services-token\n")
    later = time.time() + 60
    os.utime(other, (later, later))
    try:
        r = run_cli("job", "list", "--json", "--url", served.base_url, env=_env(served))
        assert r.returncode == 0, r.stderr
        assert isinstance(json.loads(r.stdout), list)
        # This service's own file holding a stale token: the 401 names the file it came from.
        own = served.data_dir / "virtual-cell.session-token"
        saved = own.read_text()
        own.write_text("stale\n")
        try:
            r = run_cli("job", "list", "--url", served.base_url, env=_env(served))
        finally:
            own.write_text(saved)
        assert r.returncode == 2 and "401" in r.stderr and str(own) in r.stderr
    finally:
        other.unlink()
    # No token file for the cell at --url: says which file it looked for.
    empty = served.data_dir.parent / "empty-data"
    empty.mkdir(exist_ok=True)
    r = run_cli("job", "list", "--url", served.base_url, env={**_env(served), "CELLCTL_DATA_DIR": str(empty)})
    assert r.returncode == 2 and "virtual-cell" in r.stderr and "--token" in r.stderr


def test_job_list_is_a_table_and_json_on_request(served: Served) -> None:
    started = run_cli("job", "run", "jog-to-mark", "--url", served.base_url, "--token", served.token)
    assert started.returncode == 0, started.stderr
    job_id = json.loads(started.stdout)["id"]
    try:
        r = run_cli("job", "list", "--url", served.base_url, "--token", served.token)
        assert r.returncode == 0, r.stderr
        lines = r.stdout.splitlines()
        assert lines[0].split()[:5] == ["ID", "ROUTINE", "STATE", "PROGRESS", "VERDICT"]
        row = next(line for line in lines if line.startswith(job_id))
        assert row.split()[1:3] == ["jog-to-mark", "running"]
        assert len(lines) <= 1 + len(json.loads(run_cli("job", "list", "--json", "--url", served.base_url,
                                                             "--token", served.token).stdout))
    finally:
        run_cli("job", "cancel", job_id, "--url", served.base_url, "--token", served.token)


def test_job_run_name_help_shows_that_routine_only() -> None:
    r = run_cli("job", "run", "intrinsics-capture", "--help")
    assert r.returncode == 0
    assert "intrinsics-capture  (role: engineer)" in r.stdout
    for other in ("handeye-capture  (role", "jog-to-mark  (role", "verify  (role"):
        assert other not in r.stdout
    everything = run_cli("job", "run", "--help").stdout
    assert "handeye-capture  (role" in everything and "verify  (role" in everything
    assert len(r.stdout.splitlines()) < len(everything.splitlines()) / 2
    unknown = run_cli("job", "run", "nosuch", "--help").stdout
    assert "no routine 'nosuch'" in unknown and "verify  (role" in unknown
