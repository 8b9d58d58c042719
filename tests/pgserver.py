"""A throwaway PostgreSQL server for tests: ``initdb`` and ``pg_ctl`` in a temporary
folder, on a free loopback port, password authentication (scram-sha-256) only.

``initdb`` refuses to run as root (CI runs as root), so there the server's programs run
as ``nobody`` (``runuser``) with the folder handed over to that user."""

from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest

from tests.conftest import require_program


def _bin_dir() -> str:
    """Where initdb is: on PATH (as .ci/run arranges), else Debian's versioned folder."""
    found = shutil.which("initdb")
    if found:
        return str(Path(found).parent)
    candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    if candidates:
        return str(Path(candidates[-1]).parent)
    return str(Path(require_program("initdb")).parent)   # skips, or fails under CI


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


STATION_PASSWORD = "St4tion-pw-71c2"   # every station role's in these tests


class PgServer:
    """Start with :meth:`start`, stop with :meth:`stop`; ``url(password)`` names a database."""

    def __init__(self, root: Path, user: str, password: str) -> None:
        self.root, self.user, self.password = root, user, password
        self.bin = _bin_dir()
        self.data, self.sockets = root / "data", root / "sockets"
        self.port = _free_port()
        self._as: list[str] = []
        if os.geteuid() == 0:
            self._as = [require_program("runuser"), "-u", "nobody", "--"]

    def _run(self, *args: str) -> None:
        r = subprocess.run([*self._as, *args], capture_output=True, text=True, timeout=120)
        if r.returncode != 0:
            raise RuntimeError(f"{args[0]} failed ({r.returncode}): {r.stderr or r.stdout}")

    def start(self) -> PgServer:
        self.sockets.mkdir(parents=True)
        pwfile = self.root / "pw"
        pwfile.write_text(self.password + "\n")
        if self._as:
            for p in (self.root, self.sockets, pwfile):
                shutil.chown(p, "nobody")
        self._run(f"{self.bin}/initdb", "-D", str(self.data), "-U", self.user, "--pwfile", str(pwfile),
                  "--auth", "scram-sha-256", "-E", "UTF8", "--no-sync")
        pwfile.unlink()
        self.resume()
        return self

    def resume(self) -> None:
        """Start the stopped server again (same folder, same port)."""
        self._run(f"{self.bin}/pg_ctl", "-D", str(self.data), "-l", str(self.root / "server.log"), "-w", "-t", "60",
                  "-o", f"-p {self.port} -k {self.sockets} -c listen_addresses=127.0.0.1 -c fsync=off", "start")

    def stop(self) -> None:
        if (self.data / "postmaster.pid").exists():
            self._run(f"{self.bin}/pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")

    def create_database(self, name: str) -> str:
        """A new empty database of this server (a test's own, apart from the module's other
        tests that share the server); its URL, without the password."""
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user=self.user, password=self.password,
                             dbname="postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(database=name)

    def url(self, password: str | None = None, database: str = "postgres", user: str | None = None) -> str:
        user = user or self.user
        auth = f"{user}:{password}" if password else user
        return f"postgresql://{auth}@127.0.0.1:{self.port}/{database}"

    def records_database(self, name: str, station_role: str = "station") -> str:
        """A new database with the QC schema made by the administrator (this server's
        superuser, who owns it) and ``station_role`` (made once, password
        :data:`STATION_PASSWORD`) granted INSERT and SELECT: a station's URL of it."""
        import psycopg

        from rig.qc.records import init_schema

        admin = self.create_database(name)
        with psycopg.connect(host="127.0.0.1", port=self.port, user=self.user, password=self.password,
                             dbname="postgres", autocommit=True) as conn:
            if not conn.execute("SELECT 1 FROM pg_roles WHERE rolname = %s", (station_role,)).fetchone():
                conn.execute(f"CREATE ROLE \"{station_role}\" LOGIN PASSWORD '{STATION_PASSWORD}'")
        init_schema(admin, (station_role,), password=self.password)
        return self.url(database=name, user=station_role)


@pytest.fixture(scope="module")
def pg_server():
    """A server with user ``qc``.  Its folder is made in the system's temporary folder,
    not pytest's (private to root, so ``nobody`` could not enter it)."""
    root = Path(tempfile.mkdtemp(prefix="qc-pg-"))
    os.chmod(root, 0o755)
    server = PgServer(root, "qc", "Pg-s3cret-9f4e")
    try:
        server.start()
        yield server
    finally:
        server.stop()
        shutil.rmtree(root, ignore_errors=True)
