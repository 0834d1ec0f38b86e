"""Shared test settings. ``PMSM_SLOW=full`` selects the long form of tests marked ``slow``;
``make test`` runs them in their short form."""

import fcntl
import os
import tempfile

import pytest


@pytest.fixture(scope="session")
def full_form() -> bool:
    return os.environ.get("PMSM_SLOW", "").lower() == "full"


@pytest.fixture(scope="module")
def pg():
    """A PostgreSQL server of its own for the test module (tests/pg_support.py); skips without one."""
    from pg_support import PgServer, pg_bindir

    bindir = pg_bindir()
    if bindir is None:
        pytest.skip("PostgreSQL's initdb is not installed (Debian: apt-get install postgresql); .ci/run installs it")
    server = PgServer(bindir)
    server.start()
    yield server
    server.remove()


@pytest.fixture
def demo_ports():
    """The demo's fixed ports (Modbus 5020, zenoh 7447: CONTRACT section 6) for one test at a time,
    across the suite's parallel workers (pytest-xdist)."""
    with open(os.path.join(tempfile.gettempdir(), "pmsm-agent-tests-demo-ports.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield
