"""A throwaway PostgreSQL server for tests: Debian's ``postgresql`` binaries, a cluster in a temp
dir, listening on 127.0.0.1 at a free port with its unix socket inside the temp dir.

initdb and postgres refuse to run as root, so as root (CI) the cluster belongs to ``nobody`` and
its programs run through ``runuser``.

``initdb`` (about 0.9 s of CPU) runs once per test run, not once per cluster: when the run's pytest process
has set :data:`TEMPLATE` (``tests/conftest.py``), the first cluster's ``initdb`` writes a template data dir
there (under a lock: the xdist workers share it) and every cluster of the run starts from a copy of it. Each
cluster is still its own server with its own data dir and port.
"""

from __future__ import annotations

import fcntl
import glob
import os
import pwd
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import psycopg

from tests.support.ports import free_port

SUPERUSER = "postgres"
TEMPLATE = "CELLCTL_TEST_PG_TEMPLATE"
"""A folder (readable by the cluster's owner) where the run keeps one ``initdb`` output to copy, set by the
run's pytest process, which removes it at the end (``make_template_dir``, ``remove_template_dir``)."""
INITDB_ARGS = ("-U", SUPERUSER, "-A", "trust", "-E", "UTF8", "--locale=C", "--no-sync", "--no-instructions")


def _cluster_owner() -> pwd.struct_passwd | None:
    """``nobody`` as root (initdb and postgres refuse to run as root), else None (this user)."""
    return pwd.getpwnam("nobody") if os.geteuid() == 0 else None


def make_template_dir() -> str:
    """A new empty folder for the run's ``initdb`` template, owned by the clusters' owner (in /tmp as root)."""
    owner = _cluster_owner()
    folder = tempfile.mkdtemp(prefix="cellctl-pg-template-", dir="/tmp" if owner else None)
    if owner is not None:
        os.chown(folder, owner.pw_uid, owner.pw_gid)
    return folder


def remove_template_dir(folder: str) -> None:
    shutil.rmtree(folder, ignore_errors=True)


def pg_bin_dir() -> Path:
    dirs = sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda d: int(Path(d).parent.name))
    if not dirs:
        raise RuntimeError("PostgreSQL server binaries not found under /usr/lib/postgresql/*/bin; "
                           "install Debian's postgresql package (deploy/install-system-deps.sh)")
    return Path(dirs[-1])


class PostgresCluster:
    """Start with :meth:`start`, always :meth:`stop` (it also removes the temp dir)."""

    def __init__(self) -> None:
        self.bin = pg_bin_dir()
        self._as_root = os.geteuid() == 0
        # as root the cluster belongs to nobody, who must reach it: /tmp, not a root-only $TMPDIR
        self.root = Path(tempfile.mkdtemp(prefix="cellctl-pg-", dir="/tmp" if self._as_root else None))
        self.data = self.root / "data"
        self.sock = self.root / "sock"
        self.log = self.root / "server.log"
        self.port = 0
        user = _cluster_owner()
        if user is not None:
            self.sock.mkdir()
            for p in (self.root, self.sock):
                os.chown(p, user.pw_uid, user.pw_gid)
        else:
            self.sock.mkdir()

    def _run(self, *argv: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
        cmd = list(argv)
        if self._as_root:
            cmd = ["runuser", "-u", "nobody", "--", *cmd]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=self.root,
                              env={"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "LC_ALL": "C"})

    def _initdb(self, data: Path) -> None:
        r = self._run(str(self.bin / "initdb"), "-D", str(data), *INITDB_ARGS)
        if r.returncode != 0:
            raise RuntimeError(f"initdb failed: {r.stderr.strip()[-2000:]}")

    def _make_data_dir(self) -> None:
        """The cluster's data dir: a copy of the run's ``initdb`` template (made now by the first cluster
        that needs it), or its own ``initdb`` when the run keeps none."""
        folder = os.environ.get(TEMPLATE, "")
        if not folder or not os.path.isdir(folder):
            self._initdb(self.data)
            return
        template = Path(folder) / f"data-{self.bin.parent.name}"
        with open(Path(folder) / "lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # one initdb for the run's processes; the others wait for it
            if not (template / "PG_VERSION").exists():
                shutil.rmtree(template, ignore_errors=True)  # a half-written one (an initdb that failed)
                self._initdb(template)
        r = self._run("cp", "-a", str(template), str(self.data))  # as the owner: the copy is the owner's, 0700
        if r.returncode != 0:
            raise RuntimeError(f"copying the initdb template failed: {r.stderr.strip()[-2000:]}")

    def start(self) -> None:
        self._make_data_dir()
        last = ""
        for _ in range(3):  # the port may be taken between choosing and binding
            self.port = free_port()
            r = self._pg_ctl_start()
            if r.returncode == 0:
                self._wait_ready()
                return
            last = (self.log.read_text()[-2000:] if self.log.exists() else "") + r.stderr
        raise RuntimeError(f"pg_ctl start failed: {last.strip()}")

    def _pg_ctl_start(self) -> subprocess.CompletedProcess[str]:
        opts = (f"-c listen_addresses=127.0.0.1 -p {self.port} -k {self.sock} "
                "-c fsync=off -c synchronous_commit=off -c full_page_writes=off -c max_connections=60")
        return self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60",
                         "-o", opts, "start", timeout_s=90)

    def pause(self) -> None:
        """Shut the server down, keeping its data (an outage of the plant's database)."""
        r = self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "fast", "-w", "stop")
        if r.returncode != 0:
            raise RuntimeError(f"pg_ctl stop failed: {r.stderr.strip()}")

    def resume(self) -> None:
        """Start the paused server again on the same port."""
        r = self._pg_ctl_start()
        if r.returncode != 0:
            raise RuntimeError(f"pg_ctl start failed: {r.stderr.strip()}")
        self._wait_ready()

    def _wait_ready(self, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                with psycopg.connect(self.dsn("postgres"), connect_timeout=2):
                    return
            except psycopg.OperationalError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)

    def dsn(self, dbname: str) -> str:
        return f"host=127.0.0.1 port={self.port} user={SUPERUSER} dbname={dbname}"

    def url(self, dbname: str) -> str:
        """A SQLAlchemy URL of database ``dbname`` on this server."""
        return f"postgresql+psycopg://{SUPERUSER}@127.0.0.1:{self.port}/{dbname}"

    def create_database(self, name: str) -> str:
        with psycopg.connect(self.dsn("postgres"), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def drop_database(self, name: str) -> None:
        with psycopg.connect(self.dsn("postgres"), autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

    def stop(self) -> None:
        try:
            if (self.data / "postmaster.pid").exists():
                self._run(str(self.bin / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)
