"""A throw-away PostgreSQL server for the historian's tests (initdb/pg_ctl in a temp dir, on a
free loopback port); the ``pg`` fixture in conftest.py starts one per test module."""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
import uuid
from pathlib import Path

from runtime_support import free_port


def pg_bindir() -> Path | None:
    """The directory of PostgreSQL's ``initdb`` and ``pg_ctl`` (newest installed), or ``None``."""
    found = shutil.which("initdb")
    if found:
        return Path(found).resolve().parent
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(p.split("/")[-3]))
    return Path(versions[-1]).parent if versions else None


class PgServer:
    """A throw-away PostgreSQL cluster on a free loopback port (run as `postgres` when we are root)."""

    def __init__(self, bindir: Path):
        self.bindir, self.port = bindir, free_port()
        self.base = Path(tempfile.mkdtemp(prefix="pmsm-pg-"))
        self.data = self.base / "data"
        self.as_postgres = os.geteuid() == 0
        if self.as_postgres:
            shutil.chown(self.base, "postgres", "postgres")
        self._pg("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres", "-E", "UTF8", "--no-locale",
                 "--no-sync")

    def _pg(self, tool, *args):
        cmd = [str(self.bindir / tool), *args]
        runuser = shutil.which("runuser") or "/usr/sbin/runuser"  # util-linux; sbin may be off PATH
        cmd = [runuser, "-u", "postgres", "--", *cmd] if self.as_postgres else cmd
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=self.base)  # a dir postgres may enter
        assert r.returncode == 0, f"{tool}: {r.stdout}{r.stderr}"

    def start(self):
        self._pg("pg_ctl", "-D", str(self.data), "-l", str(self.base / "log"), "-w", "-o",
                 f"-k {self.base} -p {self.port} -h 127.0.0.1 -c fsync=off -c full_page_writes=off", "start")

    def stop(self):
        self._pg("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "stop")

    def remove(self):
        """Stop the server if it runs, and delete its directory."""
        try:
            self.stop()
        except AssertionError:
            pass  # already stopped (by a test that stops it)
        shutil.rmtree(self.base, ignore_errors=True)

    def dsn(self, dbname="postgres") -> str:
        return f"host=127.0.0.1 port={self.port} user=postgres dbname={dbname}"

    def create_database(self) -> str:
        """A new empty database; returns its DSN."""
        import psycopg

        name = f"h_{uuid.uuid4().hex[:10]}"
        with psycopg.connect(self.dsn(), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.dsn(name)
