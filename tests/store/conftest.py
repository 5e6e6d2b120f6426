"""Fixtures of the store tests: every store test runs on SQLite and on a real PostgreSQL.

The PostgreSQL server is Debian's, started once per session on a throw-away
cluster in a temporary folder (``plantscan_store.pgserver``); each test gets
its own new database.  Without the server binaries the PostgreSQL half is
skipped, except in CI (``CI`` set), where it fails: CI must test both.
"""

from __future__ import annotations

import os
import sys
import uuid
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))


@pytest.fixture(scope="session")
def pg_server():
    from plantscan_store.pgserver import PostgresUnavailable, TempPostgres

    try:
        server = TempPostgres().start()
    except PostgresUnavailable as exc:
        if os.environ.get("CI"):
            pytest.fail(f"CI must test the PostgreSQL store: {exc}")
        pytest.skip(str(exc))
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def store_target(request, tmp_path) -> str:
    """A new, empty store: a SQLite file, or a new database on the session's server."""
    if request.param == "sqlite":
        return str(tmp_path / "results.sqlite")
    server = request.getfixturevalue("pg_server")
    return server.create_database(f"t_{uuid.uuid4().hex[:12]}")


@pytest.fixture
def store(store_target):
    from plantscan_store import Store

    s = Store(store_target)
    try:
        yield s
    finally:
        s.close()
