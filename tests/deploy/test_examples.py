"""Every example config in deploy/examples/ passes ``cellctl config check``, and names its peer."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest

from cellctl.cli import main
from tests.conftest import CELLCTL, REPO

EXAMPLES = sorted((REPO / "deploy" / "examples").glob("*.yaml"))


def test_the_examples_are_there() -> None:
    names = {p.name for p in EXAMPLES}
    assert {"virtual-cell.yaml", "real-cell.yaml"} <= names, names


@pytest.mark.parametrize("example", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_example_passes_config_check(example: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["config", "check", "--config", str(example)])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert json.loads(out)["ok"] is True
    header = "".join(line + "\n" for line in example.read_text().splitlines() if line.startswith("#"))
    assert example.read_text().startswith("# cellctl:"), "an example opens with a '# cellctl:' header comment"
    assert re.search(r"^# .*\bPeers?:", header, re.M), "the header names the peer it runs against (INTERFACES §6)"


def test_real_cell_example_through_the_console_script() -> None:
    """The real cell: GigE camera (Aravis), UR arm (RTDE), Modbus RTU gripper, HTTPS at the documented place."""
    r = subprocess.run([CELLCTL, "config", "check", "--config", str(REPO / "deploy/examples/real-cell.yaml")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout) == {"ok": True, "cell_id": "line1-cell3", "cameras": {"cam0": "aravis"},
                                    "robots": {"robot0": "ur_rtde"}, "io": {"grip0": "robotiq_gripper"}}
    text = (REPO / "deploy/examples/real-cell.yaml").read_text()
    assert "tls_cert: /etc/cellctl/tls/cert.pem" in text and "tls_key: /etc/cellctl/tls/key.pem" in text
