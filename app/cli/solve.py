"""`python -m app solve FILE [FILE ...] [--json]`: identify the star pattern of telemetry files.

One JSON object per input file and line, in input order, all in one process
(the catalogue index is loaded once).  An invalid file gives status
``invalid`` with its validation error and does not stop the batch.  Exit
status 0 when every file was valid, 2 otherwise.

``--method`` picks the lost-in-space identifier: ``bright_pair`` (default),
``tf`` (Liebe's triangle features) or ``both``: then the bright-pair answer
fills the usual keys, the TF candidates come under ``tf_candidates`` and
``methods_agree`` says whether the two first candidates are the same
attitude (within :data:`AGREE_DEG`; also true when neither finds any).

``--prior RA,DEC,ROLL[,SIGMA_DEG]`` switches to tracking mode (Liebe's
predictional estimate): the pattern is matched near that attitude (degrees;
sigma default 1 deg) instead of searched for over the whole sky.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys

from app.cli.common import for_each_file, format_error

METHODS = ("bright_pair", "tf", "both")
#: Two first candidates closer than this (rotation angle) are the same attitude.
AGREE_DEG = 0.1


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", metavar="FILE", help="telemetry files (tubsat-snapshots/1 JSON or CSV)")
    p.add_argument("--json", action="store_true", help="one JSON object per file and line")
    p.add_argument("--candidates", type=int, default=None, metavar="N",
                   help="distinct candidates to report (default 10)")
    p.add_argument("--method", choices=METHODS, default="bright_pair",
                   help="identifier: bright_pair (default), tf (Liebe's triangle features) or both, compared")
    p.add_argument("--prior", type=parse_prior, default=None, metavar="RA,DEC,ROLL[,SIGMA_DEG]",
                   help="tracking mode from this attitude (degrees; its 1-sigma defaults to 1 deg)")


def parse_prior(text: str):
    """``RA,DEC,ROLL[,SIGMA_DEG]`` in degrees -> an :class:`app.identification.Prior`."""
    from app.attitude import rotation_from_radec_roll
    from app.identification import Prior

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers RA,DEC,ROLL[,SIGMA_DEG], got {text!r}") from None
    if len(values) not in (3, 4) or not all(map(math.isfinite, values)):
        raise argparse.ArgumentTypeError(f"expected RA,DEC,ROLL[,SIGMA_DEG] in degrees, got {text!r}")
    ra, dec, roll = values[:3]
    sigma = values[3] if len(values) == 4 else 1.0
    if not -90.0 <= dec <= 90.0 or not 0.0 < sigma <= 10.0:
        raise argparse.ArgumentTypeError("DEC must be within [-90, 90] and SIGMA_DEG within (0, 10]")
    return Prior(rotation=rotation_from_radec_roll(ra, dec, roll), sigma_deg=sigma)


def solved_to_json(solved, sky) -> dict:
    """The members of a solve result after file, sequence_id, status and error.

    ``source_stars`` gives, per snapshot and source in input order, the HIP
    number the first candidate's attitude assigns it (null: no star there),
    or is null when that candidate is not credible.
    """
    from app.extraction import extraction_to_json
    from app.identification import candidate_json, source_stars

    s = solved.solution
    ex = extraction_to_json(solved.extraction)
    return {"reference_snapshot": ex["reference_snapshot"], "sources": ex["sources"],
            "source_stars": source_stars(solved, sky),
            "candidates": [candidate_json(solved, c) for c in s.candidates],
            "elapsed_ms": round(s.elapsed_s * 1000, 2), "notes": list(solved.extraction.notes) + list(s.notes)}


def run(args: argparse.Namespace) -> int:
    from app.identification import SearchOptions, Sky, solve_sequence

    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    sky = Sky()
    options = SearchOptions() if args.candidates is None else SearchOptions(max_candidates=args.candidates)

    method = getattr(args, "method", "bright_pair")
    prior = getattr(args, "prior", None)

    def solve_one(path, sequence):
        solved = solve_sequence(sequence, sky, options=options, method="tf" if method == "tf" else "bright_pair",
                                prior=prior)
        doc = {"file": path, "sequence_id": sequence.sequence_id, "status": solved.solution.status,
               "error": None, **solved_to_json(solved, sky)}
        if method == "both" and prior is None:
            tf = solve_sequence(sequence, sky, options=options, extraction=solved.extraction,
                                pattern=solved.pattern, method="tf").solution
            doc["tf_status"] = tf.status
            doc["tf_candidates"] = [c.to_json() for c in tf.candidates]
            doc["methods_agree"] = methods_agree(solved.solution, tf)
        return doc

    def invalid(path, error):
        return {"file": path, "sequence_id": None, "status": "invalid", "error": format_error(error),
                "reference_snapshot": None, "sources": [], "candidates": []}

    return for_each_file(args.files, solve_one, invalid, args.json, print_summary)


def methods_agree(a, b, tolerance_deg: float = AGREE_DEG) -> bool:
    """True when both solutions' first candidates are one attitude, or neither has a candidate."""
    import math

    from app.attitude import rotation_angle_between

    if not a.candidates or not b.candidates:
        return not a.candidates and not b.candidates
    angle = rotation_angle_between(a.candidates[0].rotation_matrix, b.candidates[0].rotation_matrix)
    return math.degrees(angle) <= tolerance_deg


def print_summary(doc: dict) -> None:
    print(f"{doc['file']}: {doc['sequence_id'] or '-'}  {doc['status']}")
    if doc["error"]:
        print("  " + doc["error"].replace("\n", "\n  "))
        return
    print(f"  {'rank':>4} {'RA deg':>10} {'Dec deg':>9} {'roll deg':>9} {'matched':>7} {'rms as':>7} "
          f"{'dev px/pt':>9} {'P(false)':>9}  stars")
    _print_candidates(doc["candidates"])
    if "tf_candidates" in doc:
        print(f"  triangle-feature method: {doc['tf_status']}, "
              f"{'agrees' if doc['methods_agree'] else 'DISAGREES'} with the bright-pair method")
        _print_candidates(doc["tf_candidates"])


def _print_candidates(candidates: list[dict]) -> None:
    for c in candidates:
        names = ", ".join(m["name"] or f"HIP {m['hip']}" for m in c["matches"][:6])
        planets = "".join(f", {p['name']} (planet)" for p in c["planets"])
        print(f"  {c['rank']:>4} {c['ra_deg']:>10.4f} {c['dec_deg']:>9.4f} {c['roll_deg']:>9.3f} "
              f"{len(c['matches']):>7} {c['rms_arcsec']:>7.1f} {c['deviation_px_per_point']:>9.3f} "
              f"{c['false_match_probability']:>9.2g}  {names}{planets}")
