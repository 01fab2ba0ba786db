"""Shared fixtures: one catalogue index and Sky for the whole test session."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

# CI (CI=true) replays the same examples every run, so a landing never hangs on
# a random draw; locally each run explores new ones.
settings.register_profile("ci", derandomize=True, database=None)
if os.environ.get("CI"):
    settings.load_profile("ci")

REPO = Path(__file__).resolve().parent.parent
SAMPLE_DIR = REPO / "sample_telemetry"


@pytest.fixture(scope="session")
def sky():
    """The identification context (catalogue + bright-pair index), built or loaded once."""
    from app.identification import Sky

    return Sky()


@pytest.fixture(scope="session")
def sample_dir() -> Path:
    return SAMPLE_DIR


@pytest.fixture(scope="session")
def postgres():
    """One real PostgreSQL server for the whole session (Debian's package, a temporary directory, a
    free port; see tests/pg_server.py).  Its absence fails the tests that need it, with what to install."""
    from pg_server import PostgresServer, PostgresUnavailable

    try:
        server = PostgresServer().start()
    except PostgresUnavailable as exc:
        pytest.fail(str(exc), pytrace=False)
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def postgres_url(postgres) -> str:
    """The URL of an empty database of its own on the session's PostgreSQL server."""
    return postgres.new_database()


@pytest.fixture(params=["sqlite", "postgresql"])
def archive_url(request, tmp_path) -> str:
    """An empty archive of each backend: a SQLite file path, or a fresh PostgreSQL database's URL."""
    if request.param == "sqlite":
        return str(tmp_path / "archive.sqlite3")
    return request.getfixturevalue("postgres").new_database()
