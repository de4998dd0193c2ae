"""deploy/cellctl.service: systemd accepts it without a single complaint, and it is hardened."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from tests.conftest import REPO
from tests.deploy.conftest import base_root, systemd_analyze, verify_unit

UNIT = REPO / "deploy" / "cellctl.service"
EXEC = "/opt/cellctl/.venv/bin/cellctl"


def unit_root(tmp: Path, unit_text: str, executable: bool = True) -> Path:
    """A root tree with the unit installed and a stand-in for the ExecStart program."""
    root = base_root(tmp / "root")
    exe = root / EXEC.lstrip("/")
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\nexit 0\n")
    exe.chmod(0o755 if executable else 0o644)
    unit_dir = root / "etc" / "systemd" / "system"
    unit_dir.mkdir(parents=True)
    (unit_dir / "cellctl.service").write_text(unit_text)
    return root


def directives(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith(("#", ";", "[")):
            key, _, value = line.partition("=")
            out.setdefault(key.strip(), []).append(value.strip())
    return out


def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    root = unit_root(tmp_path, UNIT.read_text())
    r = verify_unit(root, "/etc/systemd/system/cellctl.service")
    # warnings ("Unknown key", "Failed to parse ...") do not change the exit code: demand silence
    assert r.returncode == 0 and r.stdout.strip() == "" and r.stderr.strip() == "", r.stdout + r.stderr


def test_verify_catches_what_we_would_get_wrong(tmp_path: Path) -> None:
    """The check above can fail: a typo'd directive, a bad value, a missing program are reported."""
    text = UNIT.read_text()
    broken = text.replace("ProtectSystem=strict", "ProtectSystem=stricter\nProtectSytem=strict")
    r = verify_unit(unit_root(tmp_path / "a", broken), "/etc/systemd/system/cellctl.service")
    assert "ProtectSytem" in r.stderr and "stricter" in r.stderr
    r = verify_unit(unit_root(tmp_path / "b", text, executable=False), "/etc/systemd/system/cellctl.service")
    assert r.returncode != 0 and EXEC in r.stderr


def test_unit_is_hardened_and_runs_the_service(tmp_path: Path) -> None:
    d = directives(UNIT.read_text())
    expected = {
        "User": "cellctl", "Group": "cellctl", "ProtectSystem": "strict", "ProtectHome": "yes",
        "NoNewPrivileges": "yes", "PrivateTmp": "yes", "ReadWritePaths": "/var/lib/cellctl",
        "StateDirectory": "cellctl", "Restart": "on-failure", "CapabilityBoundingSet": "",
        "LimitNOFILE": "65536",  # issue 34: the default 1,024 let idle connections starve Stop
        "ExecStart": f"{EXEC} serve --config /etc/cellctl/cell.yaml", "WantedBy": "multi-user.target",
    }
    for key, value in expected.items():
        assert d.get(key) == [value], (key, d.get(key))
    assert "CELLCTL_DATA_DIR=/var/lib/cellctl" in d["Environment"]
    # numba's cache in the state directory (the service may write nothing else; install.sh warms it)
    assert "NUMBA_CACHE_DIR=/var/lib/cellctl/numba-cache" in d["Environment"]
    # systemd's own exposure rating of the unit (offline: no running systemd needed), 0 best .. 10 worst
    root = unit_root(tmp_path, UNIT.read_text())
    r = subprocess.run([systemd_analyze(), "security", "--offline=yes", f"--root={root}",
                        "/etc/systemd/system/cellctl.service"], capture_output=True, text=True, timeout=60)
    m = re.search(r"Overall exposure level for cellctl\.service: (\d+\.\d+) (\w+)", r.stdout)
    assert m, r.stdout + r.stderr
    assert float(m.group(1)) <= 3.0 and m.group(2) == "OK", m.group(0)
