"""`python -m app solve FILE [FILE ...] [--json]`: identify the star pattern of telemetry files.

One JSON object per input file and line, in input order, all in one process
(the catalogue index is loaded once).  An invalid file gives status
``invalid`` with its validation error and does not stop the batch.  Exit
status 0 when every file was valid, 2 otherwise.
"""

from __future__ import annotations

import argparse
import logging
import sys

from app.cli.common import for_each_file, format_error


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", metavar="FILE", help="telemetry files (tubsat-snapshots/1 JSON or CSV)")
    p.add_argument("--json", action="store_true", help="one JSON object per file and line")
    p.add_argument("--candidates", type=int, default=None, metavar="N",
                   help="distinct candidates to report (default 10)")


def solved_to_json(solved) -> dict:
    """The members of a solve result after file, sequence_id, status and error."""
    from app.extraction import extraction_to_json

    s = solved.solution
    ex = extraction_to_json(solved.extraction)
    return {"reference_snapshot": ex["reference_snapshot"], "sources": ex["sources"],
            "candidates": [c.to_json() for c in s.candidates],
            "elapsed_ms": round(s.elapsed_s * 1000, 2), "notes": list(solved.extraction.notes) + list(s.notes)}


def run(args: argparse.Namespace) -> int:
    from app.identification import SearchOptions, Sky, solve_sequence

    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    sky = Sky()
    options = SearchOptions() if args.candidates is None else SearchOptions(max_candidates=args.candidates)

    def solve_one(path, sequence):
        solved = solve_sequence(sequence, sky, options=options)
        return {"file": path, "sequence_id": sequence.sequence_id, "status": solved.solution.status,
                "error": None, **solved_to_json(solved)}

    def invalid(path, error):
        return {"file": path, "sequence_id": None, "status": "invalid", "error": format_error(error),
                "reference_snapshot": None, "sources": [], "candidates": []}

    return for_each_file(args.files, solve_one, invalid, args.json, print_summary)


def print_summary(doc: dict) -> None:
    print(f"{doc['file']}: {doc['sequence_id'] or '-'}  {doc['status']}")
    if doc["error"]:
        print("  " + doc["error"].replace("\n", "\n  "))
        return
    print(f"  {'rank':>4} {'RA deg':>10} {'Dec deg':>9} {'roll deg':>9} {'matched':>7} {'rms as':>7} "
          f"{'dev px/pt':>9} {'P(false)':>9}  stars")
    for c in doc["candidates"]:
        names = ", ".join(m["name"] or f"HIP {m['hip']}" for m in c["matches"][:6])
        planets = "".join(f", {p['name']} (planet)" for p in c["planets"])
        print(f"  {c['rank']:>4} {c['ra_deg']:>10.4f} {c['dec_deg']:>9.4f} {c['roll_deg']:>9.3f} "
              f"{len(c['matches']):>7} {c['rms_arcsec']:>7.1f} {c['deviation_px_per_point']:>9.3f} "
              f"{c['false_match_probability']:>9.2g}  {names}{planets}")
