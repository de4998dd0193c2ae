"""Typed routine parameters on the virtual cell: ``GET /routines`` and OpenAPI carry each
routine's JSON schema (units, defaults); bad values name the field; an abandoned interactive step
times out and cancels the job; ``job run --follow`` into a file writes whole lines, no ``\\r``.

The cell is the app served by uvicorn from a thread of this process (``served_in_thread``): a real
HTTP server for ``cellctl job run --url`` (run as its console script, the command's entry-point
test), without a ``cellctl serve`` process to start; ``job run --help`` runs in-process (``run_cli``).
"""

from __future__ import annotations

import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import CELLCTL
from tests.support.app import ThreadServed, served_in_thread
from tests.support.cli import run_cli

ROUTINES = ("handeye-capture", "intrinsics-capture", "jog-to-mark", "verify")


@pytest.fixture(scope="module")
def http_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ThreadServed]:
    with served_in_thread(tmp_path_factory.mktemp("params")) as cell:
        yield cell


def test_routines_list_their_parameter_schemas(http_cell: ThreadServed) -> None:
    with http_cell.client() as http:
        listed = http.get("/routines").json()
    assert [r["name"] for r in listed] == list(ROUTINES)
    by_name = {r["name"]: r for r in listed}
    props = by_name["intrinsics-capture"]["params_schema"]["properties"]
    assert props["views"]["default"] == 16 and props["views"]["minimum"] == 4
    assert "degrees" in props["max_tilt_deg"]["description"]
    assert "m/s" in props["speed_m_s"]["description"]
    assert by_name["intrinsics-capture"]["role"] == "engineer" and by_name["verify"]["role"] == "operator"
    for r in listed:
        assert r["params_schema"]["additionalProperties"] is False
        assert r["description"] and "``" not in r["description"]
        for key, prop in r["params_schema"]["properties"].items():
            assert prop.get("description"), f"{r['name']}.{key} has no description"


def test_openapi_documents_each_routine_body(http_cell: ThreadServed) -> None:
    with http_cell.client() as http:
        spec = http.get("/openapi.json").json()
        listed = {r["name"]: r["params_schema"] for r in http.get("/routines").json()}
    for name in ROUTINES:
        op = spec["paths"][f"/routines/{name}"]["post"]
        schema = op["requestBody"]["content"]["application/json"]["schema"]
        assert schema["title"] == listed[name]["title"]
        assert set(schema["properties"]) == set(listed[name]["properties"])
    assert "stations" in spec["paths"]["/routines/handeye-capture"]["post"]["requestBody"]["content"][
        "application/json"]["schema"]["properties"]


@pytest.mark.parametrize(("body", "field"), [({"views": "many"}, "views"), ({"max_tilt_deg": 90}, "max_tilt_deg"),
                                             ({"viewz": 3}, "viewz"), ({"speed_m_s": -1}, "speed_m_s")])
def test_bad_parameters_name_the_field(http_cell: ThreadServed, body: dict[str, object], field: str) -> None:
    with http_cell.client() as http:
        r = http.post("/routines/intrinsics-capture", json=body)
    assert r.status_code == 422
    err = r.json()["error"]
    assert err["code"] == "invalid_params" and field in err["message"] and "GET /routines" in err["message"]


def test_non_json_and_non_object_bodies_are_refused(http_cell: ThreadServed) -> None:
    with http_cell.client() as http:
        r = http.post("/routines/verify", content=b"{not json", headers={"Content-Type": "application/json"})
        assert r.status_code == 422 and r.json()["error"]["code"] == "invalid_params"
        r = http.post("/routines/verify", json=[1, 2])
        assert r.status_code == 422 and "JSON object" in r.json()["error"]["message"]


def test_abandoned_jog_to_mark_times_out_and_cancels(http_cell: ThreadServed) -> None:
    with http_cell.client() as http:
        r = http.post("/routines/jog-to-mark", json={"marks": 4, "step_timeout_s": 1.5})
        assert r.status_code == 202, r.text
        job_id = r.json()["id"]
        deadline = time.monotonic() + 60
        job = r.json()
        while time.monotonic() < deadline:
            job = http.get(f"/jobs/{job_id}").json()
            if job["state"] != "running":
                break
            time.sleep(0.2)
        assert job["state"] == "cancelled", job
        assert "no operator input within 2 s" in job["error"] and "abandoned" in job["error"]
        assert job["waiting_for"] is None
        cals = http.get("/calibrations", params={"kind": "npoint"}).json()
        assert cals == []


def test_follow_into_a_file_writes_whole_lines(http_cell: ThreadServed, tmp_path: Path) -> None:
    log = tmp_path / "follow.log"
    with log.open("w") as err:
        r = subprocess.run([CELLCTL, "job", "run", "verify", "--follow", "--url", http_cell.base_url,
                            "--token", http_cell.token, "--param", "target=" + "no-such-target-" * 8],
                           stdout=subprocess.PIPE, stderr=err, text=True, timeout=120, stdin=subprocess.DEVNULL)
    text = log.read_text()
    assert r.returncode == 2  # refused at once (the config has no such target): one whole line
    assert "\r" not in text and "\033" not in text
    assert ("no target '" + "no-such-target-" * 8 + "'") in text  # the reason, whole (> 80 columns)
    assert any(len(line) > 120 for line in text.splitlines())


def test_job_run_help_lists_parameters_with_units() -> None:
    r = run_cli("job", "run", "--help")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    for name in ROUTINES:
        assert f"\n{name}  (role:" in out
    assert "max_tilt_deg (number, [5..60]; default 32.0)" in out
    assert "step_timeout_s" in out and "m/s" in out
    assert "--url URL" in out and "CELLCTL_URL" in out and "--token TOKEN" in out and "CELLCTL_TOKEN" in out
