"""The layering contracts of pyproject.toml ([tool.importlinter]): interfaces -> workflow -> stages ->
primitives, no import cycles inside a package, and no HTTP or 3D-view library below the interfaces.
Checked by import-linter over the real import graph."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_import_linter_contracts_are_kept():
    lint = Path(sys.executable).with_name("lint-imports")
    run = subprocess.run([str(lint), "--no-cache"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert "3 kept, 0 broken" in run.stdout

