"""A throw-away PostgreSQL server in a temporary folder, for tests and benchmarks.

``TempPostgres`` runs Debian's server binaries (``initdb``, ``pg_ctl``; package
``postgresql``) on a fresh cluster in a temporary folder, listening on
127.0.0.1 at a free port and on a socket in that folder, with ``trust``
authentication for its one user.  PostgreSQL refuses to run as root: as root
the cluster belongs to the ``postgres`` system user (which Debian's package
creates) and the binaries run through ``runuser``.

pytest-postgresql does much the same but calls ``pg_ctl`` as the current user,
which fails as root, where CI runs (docs/decisions.md).
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

USER = "plantscan"


class PostgresUnavailable(RuntimeError):
    """No PostgreSQL server binaries here (install Debian's ``postgresql``)."""


def server_bindir() -> Path:
    """The folder of ``initdb``/``pg_ctl``: PATH first, then Debian's /usr/lib/postgresql/N/bin."""
    found = shutil.which("initdb")
    if found:
        return Path(found).resolve().parent
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"),
                      key=lambda p: int(Path(p).parent.parent.name)
                      if Path(p).parent.parent.name.isdigit() else 0)
    if not versions:
        raise PostgresUnavailable("PostgreSQL server binaries not found (no initdb on PATH or "
                                  "in /usr/lib/postgresql/*/bin): apt-get install postgresql")
    return Path(versions[-1]).parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class TempPostgres:
    """A PostgreSQL server on a new cluster in a temporary folder; ``stop()`` removes it.

    Attributes
    ----------
    port : int
    root : Path
        The temporary folder (cluster in ``data/``, socket and log beside it).
    """

    def __init__(self, root: Path | None = None) -> None:
        self.bindir = server_bindir()
        self.root = Path(root) if root else Path(tempfile.mkdtemp(prefix="plantscan-pg-"))
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        self.port = _free_port()
        self._as: list[str] = []
        if os.geteuid() == 0:
            try:
                owner = pwd.getpwnam("postgres")
            except KeyError:
                raise PostgresUnavailable("running as root and there is no 'postgres' user to "
                                          "run the server as (Debian's postgresql package "
                                          "creates it)") from None
            os.chown(self.root, owner.pw_uid, owner.pw_gid)
            self._as = ["runuser", "-u", "postgres", "--"]
        self._started = False

    def _run(self, *args: str, timeout: float = 120) -> None:
        cmd = [*self._as, *args]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                              cwd=self.root)
        if done.returncode != 0:
            log = self.log.read_text()[-2000:] if self.log.exists() else ""
            raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stdout}\n"
                               f"{done.stderr}\n{log}")

    def start(self) -> TempPostgres:
        self._run(str(self.bindir / "initdb"), "-D", str(self.data), "-U", USER,
                  "--auth=trust", "-E", "UTF8", "--no-sync", "--locale=C")
        # durable commits as on a real server (fsync on, the default)
        options = (f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 "
                   "-c max_connections=50 -c shared_buffers=32MB")
        self._run(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-l", str(self.log),
                  "-o", options, "-w", "-t", "60", "start")
        self._started = True
        return self

    def stop(self) -> None:
        if self._started:
            try:
                # immediate: no shutdown checkpoint (a throw-away cluster, deleted next)
                self._run(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-m",
                          "immediate", "-w", "stop", timeout=60)
            finally:
                self._started = False
        shutil.rmtree(self.root, ignore_errors=True)

    def url(self, dbname: str = "postgres") -> str:
        return f"postgresql://{USER}@127.0.0.1:{self.port}/{dbname}"

    def create_database(self, dbname: str) -> str:
        """Create an empty database; its URL."""
        import psycopg

        deadline = time.monotonic() + 30
        while True:
            try:
                with psycopg.connect(host="127.0.0.1", port=self.port, user=USER,
                                     dbname="postgres", autocommit=True) as conn:
                    conn.execute(f'CREATE DATABASE "{dbname}"')
                return self.url(dbname)
            except psycopg.OperationalError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def __enter__(self) -> TempPostgres:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
