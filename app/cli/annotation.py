"""``solve IMAGE --annotate OUT.png``: the solved frame written as an annotated PNG.

The frame at its own size, stretched as the console's previews are, with the first candidate's
identified stars circled and named, the constellation figures, the detected sources no star explains
(squares), an RA/Dec grid and a title line (:mod:`app.workflow.annotate`).  One FILE only: several
would all want OUT (a folder holding both frames and spot lists annotates its first input, the frames,
and says so).  A spot list, which has no image, is drawn on black.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def add_annotate_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--annotate", type=annotation_path, default=None, metavar="OUT.png",
                   help="also write the solved frame as a PNG: the identified stars named, constellation lines, the "
                        "unmatched sources as squares, an RA/Dec grid and a title (one FILE only)")


def annotation_path(text: str) -> Path:
    """``--annotate``: a PNG file to write, in a folder that exists."""
    path = Path(text)
    if path.suffix.lower() != ".png":
        raise argparse.ArgumentTypeError(f"must name a .png file, got {text!r}")
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a folder: name the .png file to write")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"no folder {str(folder)!r} to write {path.name!r} in")
    return path


class Annotator:
    """Wraps the solve of each input: writes OUT for the first solved input (``out`` None: does nothing).
    ``status`` is 2 when OUT could not be written, else 0."""

    def __init__(self, out: Path | None, files: list[str]):
        if out is not None and len(files) != 1:
            print(f"solve: --annotate {out} takes one FILE (an image or a folder of frames), got {len(files)}: "
                  "run solve once per image", file=sys.stderr)
            raise SystemExit(2)
        self.out = out
        self.written: str | None = None
        self.status = 0

    def __call__(self, path: str, sequence, doc):
        if self.out is None:
            return doc
        if self.written is not None:
            print(f"--annotate: {self.out} is of {self.written}; {path} is not annotated", file=sys.stderr)
            return doc
        from app.workflow.annotate import annotate_solve

        png = annotate_solve(path, sequence, doc)
        temporary = self.out.with_name(f".{self.out.name}.{os.getpid()}.tmp")
        try:
            temporary.write_bytes(png)
            temporary.replace(self.out)
        except OSError as exc:
            temporary.unlink(missing_ok=True)
            print(f"--annotate: cannot write {self.out}: {exc.strerror or type(exc).__name__}", file=sys.stderr)
            self.status = 2
            return doc
        self.written = path
        print(f"--annotate: wrote {self.out} ({path} with the first candidate's stars named)", file=sys.stderr)
        return doc
