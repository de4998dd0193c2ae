"""Helpers of the deployment tests: a minimal Debian-like root tree and systemd-analyze."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

SYSTEM_UNITS = Path("/usr/lib/systemd/system")
BASE_PASSWD = "root:x:0:0:root:/root:/bin/bash\n"
BASE_GROUP = "root:x:0:\ndialout:x:20:\nplugdev:x:46:\n"


def systemd_analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None or not SYSTEM_UNITS.is_dir():
        pytest.fail("systemd-analyze and the system units are missing: install the Debian package systemd "
                    "(bash deploy/install-system-deps.sh)")
    return exe


def base_root(root: Path) -> Path:
    """What a fresh Debian base system has that install.sh and systemd-analyze rely on: the user
    and group databases and the system's unit files (copied from this machine)."""
    (root / "etc").mkdir(parents=True, exist_ok=True)
    (root / "etc" / "passwd").write_text(BASE_PASSWD)
    (root / "etc" / "group").write_text(BASE_GROUP)
    (root / "etc" / "shadow").write_text("root:*:19000:0:99999:7:::\n")
    (root / "etc" / "gshadow").write_text("root:*::\n")
    for name in ("shadow", "gshadow"):
        (root / "etc" / name).chmod(0o640)
    (root / "usr" / "lib" / "systemd").mkdir(parents=True, exist_ok=True)
    shutil.copytree(SYSTEM_UNITS, root / "usr" / "lib" / "systemd" / "system", symlinks=True)
    return root


def verify_unit(root: Path, unit_path_in_root: str) -> subprocess.CompletedProcess[str]:
    """``systemd-analyze verify`` of a unit installed in ``root`` (its ExecStart is looked up there)."""
    return subprocess.run([systemd_analyze(), "verify", f"--root={root}", unit_path_in_root],
                          capture_output=True, text=True, timeout=60)
