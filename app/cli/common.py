"""What the file-processing commands share: the batch loop over telemetry files."""

from __future__ import annotations

import sys
from typing import Callable

from app.workflow.documents import Document
from app.workflow.files import telemetry_files


def for_each_file(paths: list[str], process: Callable[[str, object], Document],
                  invalid: Callable[[str, str], Document], as_json: bool,
                  print_summary: Callable[[Document], None]) -> int:
    """Run ``process(path, sequence)`` on every telemetry file, in input order.

    A file that does not parse gives ``invalid(path, message)`` and the batch
    goes on.  With ``as_json`` each result is one line of JSON on stdout.
    Returns the exit status: 0 if every file was valid, 2 otherwise.
    """
    status = 0
    for path, sequence, error in telemetry_files(paths):
        if error is not None:
            doc = invalid(path, str(error))
            status = 2
        else:
            doc = process(path, sequence)
        if as_json:
            sys.stdout.write(doc.model_dump_json() + "\n")
            sys.stdout.flush()
        else:
            print_summary(doc)
    return status
