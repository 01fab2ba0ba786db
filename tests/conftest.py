"""Shared fixtures: one catalogue index and Sky for the whole test session."""

from __future__ import annotations

from pathlib import Path

import pytest

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
