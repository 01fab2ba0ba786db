"""What the file-processing commands share: the batch loop over telemetry files, ``--fov-deg`` and ``--time``."""

from __future__ import annotations

import argparse
import logging
import sys
from datetime import datetime
from typing import Callable

# One parser, one wording (upload.py needs only the standard library).
from app.cli.upload import TIME_HELP, fov_deg, truth_note, utc_time
from app.workflow.documents import Document
from app.workflow.files import input_files, telemetry_files


FOV_HELP = ("horizontal field of view of image files and folders of frames, degrees (0.1 to 120, known to "
            "+-5 %%); wins over a sidecar's camera or fov_deg and the FITS header's optics. Refused for "
            "spot-list files, which carry their own camera (that file is reported invalid)")


def add_fov_argument(p: argparse.ArgumentParser, help_text: str = FOV_HELP) -> None:
    p.add_argument("--fov-deg", type=fov_deg, default=None, metavar="DEG", help=help_text)


def add_time_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--time", type=utc_time, default=None, metavar="ISO8601", help=TIME_HELP)


def command_line_inputs(paths: list[str]) -> list[str]:
    """The inputs of files and folders named on the command line (:func:`app.workflow.files.input_files`),
    saying on stderr how many simulator truth files were left out."""
    inputs, truth = input_files(paths)
    if truth:
        print(truth_note(len(truth)), file=sys.stderr)
    return inputs


def indented_error(doc) -> str:
    """A document's error under its file's line: indented, without the file's name again (the message
    names it, to stand alone in --json)."""
    return "  " + doc.error.removeprefix(f"{doc.file}: ").replace("\n", "\n  ")


def for_each_file(paths: list[str], process: Callable[[str, object], Document],
                  invalid: Callable[[str, str], Document], as_json: bool,
                  print_summary: Callable[[Document], None], *, fov_deg: float | None = None,
                  time: datetime | None = None) -> int:
    """Run ``process(path, sequence)`` on every telemetry file, in input order (folders: their telemetry
    files, or their frames as one pass; see :func:`command_line_inputs`).

    A file that does not parse gives ``invalid(path, message)`` and the batch
    goes on.  So does a file that parses but cannot be processed: the
    parser's bounds should make that impossible, but a batch of a thousand
    files must not be lost to a bug triggered by one of them, so the
    failure is reported as that file's error (the traceback only in the
    debug log) instead of ending the command.  With ``as_json`` each result
    is one line of JSON on stdout.  ``fov_deg`` is the optics of image inputs,
    ``time`` the time of a pass of one frame (a spot-list file given with
    either is invalid: see :func:`app.workflow.files.telemetry_files`).  Returns the exit status: 0
    if every file was valid, 2 otherwise.
    """
    status = 0
    for path, sequence, error in telemetry_files(command_line_inputs(paths), fov_deg=fov_deg, time=time):
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
