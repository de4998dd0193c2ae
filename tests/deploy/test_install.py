"""deploy/install.sh into a fresh directory tree (``--root``): user, copy, venv, config, data, unit.

The tree starts as a Debian base system would (user/group databases, the system's unit files);
``--no-deps`` installs cellctl alone into the new venv (building it from the copy with the
configured package index), and the installed command is then run with this suite's dependencies
on ``PYTHONPATH`` — the code it runs is the installed copy, which the test checks.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sysconfig
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.deploy.conftest import base_root, verify_unit

INSTALL = REPO / "deploy" / "install.sh"
PREFIX = "/srv/cellctl"  # not the default, so the unit's paths must follow it


@dataclass
class Installed:
    root: Path
    result: subprocess.CompletedProcess[str]

    def at(self, path: str) -> Path:
        return self.root / path.lstrip("/")


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Installed]:
    root = base_root(tmp_path_factory.mktemp("install") / "root")
    r = subprocess.run(["bash", str(INSTALL), "--root", str(root), "--prefix", PREFIX, "--no-deps"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    yield Installed(root, r)


def passwd_entry(root: Path, name: str) -> list[str]:
    for line in (root / "etc" / "passwd").read_text().splitlines():
        if line.split(":")[0] == name:
            return line.split(":")
    raise AssertionError(f"no user {name} in {root}/etc/passwd")


AS_ROOT = os.geteuid() == 0
"""useradd --root and chown need root; as another user install.sh says it skipped them."""


def test_service_user_is_created(installed: Installed) -> None:
    if not AS_ROOT:
        assert "skipped creating user cellctl" in installed.result.stderr
        return
    name, _, uid, gid, _, home, shell = passwd_entry(installed.root, "cellctl")
    assert 0 < int(uid) < 1000  # a system user
    assert home == "/var/lib/cellctl" and shell == "/usr/sbin/nologin"
    groups = {ln.split(":")[0]: ln.split(":")[2] for ln in (installed.root / "etc/group").read_text().splitlines()}
    assert groups["cellctl"] == gid


def test_project_copy_and_venv(installed: Installed) -> None:
    dest = installed.at(PREFIX)
    for rel in ("pyproject.toml", "README.md", "cellctl/__init__.py", "drivers/registry.py",
                "calibration/geometry.py", "deploy/cellctl.service", "deploy/examples/real-cell.yaml"):
        assert (dest / rel).is_file(), rel
    for unwanted in (".git", "tests", "build", "cellctl.egg-info"):
        assert not (dest / unwanted).exists(), unwanted
    assert not [p for p in dest.rglob("__pycache__") if ".venv" not in p.parts]
    exe = dest / ".venv" / "bin" / "cellctl"
    assert exe.is_file() and os.access(exe, os.X_OK)
    assert f"{dest}/.venv/bin/python" in "".join(exe.read_text().splitlines()[:3])  # the new venv's python
    # a real (non-editable) install: the package lives in the venv's site-packages
    site = list((dest / ".venv" / "lib").glob("python3*/site-packages"))
    assert len(site) == 1 and (site[0] / "cellctl" / "metrics.py").is_file()
    assert not list(site[0].glob("__editable__*"))


def test_installed_command_checks_the_installed_config(installed: Installed) -> None:
    dest = installed.at(PREFIX)
    env = {**os.environ, "PYTHONPATH": sysconfig.get_paths()["purelib"]}  # this suite's dependencies
    config = installed.at("/etc/cellctl/cell.yaml")
    r = subprocess.run([str(dest / ".venv/bin/cellctl"), "config", "check", "--config", str(config)],
                       capture_output=True, text=True, timeout=120, env=env, cwd=installed.root)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["cell_id"] == "virtual-cell"
    r = subprocess.run([str(dest / ".venv/bin/python"), "-c", "import cellctl; print(cellctl.__file__)"],
                       capture_output=True, text=True, timeout=120, env=env, cwd=installed.root)
    assert r.stdout.strip().startswith(str(dest / ".venv")), r.stdout + r.stderr  # the installed copy ran


def test_config_tls_and_data_directories(installed: Installed) -> None:
    uid, gid = passwd_entry(installed.root, "cellctl")[2:4] if AS_ROOT else (str(os.geteuid()), str(os.getegid()))
    config = installed.at("/etc/cellctl/cell.yaml")
    assert config.read_text() == (REPO / "deploy" / "examples" / "virtual-cell.yaml").read_text()
    st = config.stat()
    owner = 0 if AS_ROOT else int(uid)
    assert stat.S_IMODE(st.st_mode) == 0o640 and (st.st_uid, st.st_gid) == (owner, int(gid))
    tls = installed.at("/etc/cellctl/tls").stat()
    assert stat.S_IMODE(tls.st_mode) == 0o750 and (tls.st_uid, tls.st_gid) == (owner, int(gid))
    data = installed.at("/var/lib/cellctl").stat()
    assert stat.S_IMODE(data.st_mode) == 0o750 and (data.st_uid, data.st_gid) == (int(uid), int(gid))


def test_unit_is_installed_for_the_prefix_and_verifies(installed: Installed) -> None:
    unit = installed.at("/etc/systemd/system/cellctl.service")
    assert unit.read_text() == (REPO / "deploy" / "cellctl.service").read_text().replace("/opt/cellctl", PREFIX)
    assert f"ExecStart={PREFIX}/.venv/bin/cellctl serve --config /etc/cellctl/cell.yaml" in unit.read_text()
    r = verify_unit(installed.root, "/etc/systemd/system/cellctl.service")  # ExecStart is the installed venv's
    assert r.returncode == 0 and r.stdout.strip() == "" and r.stderr.strip() == "", r.stdout + r.stderr
    # no systemd manager in a --root install: said, not attempted
    assert "skipped daemon-reload and enable" in installed.result.stderr


NUMBA_CACHE = "/var/lib/cellctl/numba-cache"
"""Where the service's compiled loops are cached: the unit's NUMBA_CACHE_DIR, which install.sh warms."""


def test_the_numba_cache_is_the_units_and_its_warm_up_is_named(installed: Installed) -> None:
    unit = (REPO / "deploy" / "cellctl.service").read_text().splitlines()
    assert f"Environment=NUMBA_CACHE_DIR={NUMBA_CACHE}" in unit  # the folder the service reads
    cache = installed.at(NUMBA_CACHE).stat()
    uid, gid = passwd_entry(installed.root, "cellctl")[2:4] if AS_ROOT else (str(os.geteuid()), str(os.getegid()))
    assert stat.S_IMODE(cache.st_mode) == 0o750 and (cache.st_uid, cache.st_gid) == (int(uid), int(gid))
    # a --root tree is not warmed (numba keys its cache by the modules' paths): the command is named
    said = installed.result.stderr
    assert "skipped the warm-up (--root)" in said, said
    assert (f"runuser -u cellctl -- env NUMBA_CACHE_DIR={NUMBA_CACHE} CELLCTL_DATA_DIR=/var/lib/cellctl "
            f"{PREFIX}/.venv/bin/cellctl warm-up") in said, said
    assert not any(installed.at(NUMBA_CACHE).iterdir())


def test_bad_invocations_say_what_to_do(tmp_path: Path) -> None:
    cases = [
        (["--prefix", "relative/dir"], "--prefix must be an absolute path"),
        (["--root", str(tmp_path / "absent")], "no such directory"),
        (["--frobnicate"], "unknown option --frobnicate"),
        (["--root", str(tmp_path), "--python", "/nonexistent/python3"], "cellctl needs Python >= 3.11"),
    ]
    for args, expected in cases:
        r = subprocess.run(["bash", str(INSTALL), *args], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and expected in r.stderr, (args, r.stderr)
    assert not list(tmp_path.iterdir())  # nothing was installed by a refused run
    r = subprocess.run(["bash", str(INSTALL), "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "--root DIR" in r.stdout and "Usage:" in r.stdout
    assert "--no-warm-up" in r.stdout and "cellctl warm-up" in r.stdout
