"""What the file-processing commands share: the batch loop over telemetry files."""

from __future__ import annotations

import logging
import sys
from typing import Callable

from app.workflow.documents import Document
from app.workflow.files import telemetry_files


def for_each_file(paths: list[str], process: Callable[[str, object], Document],
                  invalid: Callable[[str, str], Document], as_json: bool,
                  print_summary: Callable[[Document], None]) -> int:
    """Run ``process(path, sequence)`` on every telemetry file, in input order.

    A file that does not parse gives ``invalid(path, message)`` and the batch
    goes on.  So does a file that parses but cannot be processed: the
    parser's bounds should make that impossible, but a batch of a thousand
    files must not be lost to a bug triggered by one of them, so the
    failure is reported as that file's error (the traceback only in the
    debug log) instead of ending the command.  With ``as_json`` each result
    is one line of JSON on stdout.  Returns the exit status: 0 if every file
    was valid, 2 otherwise.
    """
    status = 0
    for path, sequence, error in telemetry_files(paths):
        if error is not None:
            doc = invalid(path, str(error))
            status = 2
        else:
            try:
                doc = process(path, sequence)
            except Exception as exc:  # noqa: BLE001 - one file's failure must not end the batch
                logging.getLogger(__name__).debug("processing %s failed", path, exc_info=True)
                doc = invalid(path, f"{path}: could not be processed ({type(exc).__name__}: {exc}); the file "
                                    "passed validation, so this is a bug: please report it with the file")
                status = 2
        if as_json:
            sys.stdout.write(doc.model_dump_json() + "\n")
            sys.stdout.flush()
        else:
            print_summary(doc)
    return status
