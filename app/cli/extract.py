"""`python -m app extract FILE [FILE ...] [--json]`: tracked stars vs ghosts and hot pixels.

One result per file, in input order.  With ``--json`` each is one line::

    {"file", "sequence_id", "status": "ok"|"invalid", "error",
     "reference_snapshot", "sources", "rejected", "tracks", "pattern",
     "seed_pattern", "noise_px", "notes"}

``sources`` holds, per snapshot, the track id (or null) of every input
source in input order, ``rejected`` the reason (``ghost``, ``hot_pixel``,
``outlier``) or null; snapshot numbers are 0-based positions in the file.
An invalid file gets status ``invalid``, its validation error and null
members, and the batch goes on.  Exit status 0 when every file was valid,
2 otherwise.

Image files and folders of frames are one pass each (docs/frames.md);
``--fov-deg DEG`` gives their optics when neither a sidecar nor
the FITS header does (and wins over both); ``--time ISO8601`` the time of a
pass of one frame (over its sidecar's, FITS header's and EXIF time).  A
spot-list file given with ``--fov-deg`` or ``--time`` is reported invalid
(it carries its own camera and times).
"""

from __future__ import annotations

import argparse
from collections import Counter

from app.cli.common import add_fov_argument, add_time_argument, for_each_file, indented_error


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", metavar="FILE",
                   help="telemetry files (tubsat-snapshots/1 JSON or CSV), image files (FITS, PNG, JPEG, TIFF) "
                        "or folders of frames")
    p.add_argument("--json", action="store_true", help="one JSON object per file, one per line")
    add_fov_argument(p)
    add_time_argument(p)


def run(args: argparse.Namespace) -> int:
    from app.workflow.documents import ExtractDocument
    from app.workflow.files import extract_document

    def invalid(path, message):
        return ExtractDocument(file=path, sequence_id=None, status="invalid", error=message)

    return for_each_file(args.files, extract_document, invalid, args.json, print_summary, fov_deg=args.fov_deg,
                         time=args.time)


def print_summary(doc) -> None:
    """A few readable lines per file (an :class:`app.workflow.documents.ExtractDocument`)."""
    if doc.status != "ok":
        print(f"{doc.file}: invalid\n{indented_error(doc)}")
        return
    n_sources = sum(len(s) for s in doc.sources)
    reasons = Counter(r for per in doc.rejected for r in per if r is not None)
    rejected = ", ".join(f"{n} {reason}" for reason, n in sorted(reasons.items())) or "none"
    print(f"{doc.file}: {doc.sequence_id}  {len(doc.sources)} snapshots, {n_sources} sources, "
          f"{len(doc.tracks)} tracks; rejected: {rejected}")
    print(f"  reference snapshot {doc.reference_snapshot}, noise {doc.noise_px:.3f} px; "
          f"pattern of {len(doc.pattern)} points (seed's pattern: {len(doc.seed_pattern)})")
    for point in doc.pattern:
        x = "-" if point.x is None else f"{point.x:8.2f}"
        y = "-" if point.y is None else f"{point.y:8.2f}"
        print(f"    track {point.track:>3}  x {x}  y {y}  brightness {point.brightness}  seen {point.sightings}x")
    for note in doc.notes:
        print(f"  note: {note}")
