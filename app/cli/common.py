"""What the file-processing commands share: the batch loop and error formatting."""

from __future__ import annotations

import json
import sys
from typing import Callable


def format_error(error: Exception) -> str:
    """A validation error as one readable message (location: reason per problem)."""
    return str(error)


def for_each_file(paths: list[str], process: Callable, invalid: Callable, as_json: bool,
                  print_summary: Callable[[dict], None]) -> int:
    """Run ``process(path, sequence)`` on every telemetry file, in input order.

    A file that does not parse gives ``invalid(path, error)`` and the batch
    goes on.  With ``as_json`` each result is one line of JSON on stdout.
    Returns the exit status: 0 if every file was valid, 2 otherwise.
    """
    from app.telemetry.errors import TelemetryError
    from app.telemetry.formats import load_telemetry_file

    status = 0
    for path in paths:
        try:
            sequence = load_telemetry_file(path)
        except TelemetryError as exc:
            doc = invalid(path, exc)
            status = 2
        else:
            doc = process(path, sequence)
        if as_json:
            sys.stdout.write(json.dumps(doc, allow_nan=False) + "\n")
            sys.stdout.flush()
        else:
            print_summary(doc)
    return status
