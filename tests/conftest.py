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
