"""A bounded schemathesis run over the served OpenAPI schema: no 5xx for any generated request.

The routines are left out here (each would start a long robot job); a longer, unbounded run that
includes them is ``bench/api_fuzz.py``.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.conftest import start_served, stop_served


def test_schemathesis_finds_no_server_error(tmp_path: Path) -> None:
    served = start_served(tmp_path)
    try:
        st = str(Path(sys.executable).with_name("schemathesis"))
        r = subprocess.run(
            [st, "run", served.base_url + "/openapi.json", "-H", f"Authorization: Bearer {served.token}",
             "--checks", "not_a_server_error", "--max-examples", "8", "--seed", "20261123",
             "--exclude-path-regex", "^/routines/", "--request-timeout", "20", "--workers", "1",
             "--phases", "examples,fuzzing"],
            capture_output=True, text=True, timeout=600)
    finally:
        stop_served(served)
    assert r.returncode == 0, r.stdout[-6000:]
    assert "Server error" not in r.stdout
