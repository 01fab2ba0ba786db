"""`python -m app solve FILE [FILE ...] [--json]`: identify the star pattern of telemetry files.

One JSON object per input file and line, in input order, all in one process
(the catalogue index is loaded once).  An invalid file gives status
``invalid`` with its validation error and does not stop the batch.  Exit
status 0 when every file was valid, 2 otherwise.

``--method`` picks the lost-in-space identifier: ``bright_pair`` (default),
``tf`` (Liebe's triangle features) or ``both``: then the bright-pair answer
fills the usual keys, the TF candidates come under ``tf_candidates`` and
``methods_agree`` says whether the two first candidates are the same
attitude (within :data:`app.workflow.files.AGREE_DEG`; also true when both
find no match).

``--prior RA,DEC,ROLL[,SIGMA_DEG]`` switches to tracking mode (Liebe's
predictional estimate): the pattern is matched near that attitude (degrees;
sigma default 1 deg) instead of searched for over the whole sky.

Image files and folders of frames are one pass each (docs/frames.md);
``--fov-deg DEG`` gives their optics when neither a sidecar nor
the FITS header does (and wins over both); ``--time ISO8601`` the time of a
pass of one frame (over its sidecar's, FITS header's and EXIF time; with no
time at all a frame is solved at an assumed one and a note says what that
costs).  A spot-list file given with ``--fov-deg`` or ``--time`` is reported
invalid (it carries its own camera and times).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys

from app.cli.annotation import Annotator, add_annotate_argument
from app.cli.common import add_fov_argument, add_time_argument, for_each_file, indented_error

#: The lost-in-space identifiers a file can be solved with, and both compared.
METHODS = ("bright_pair", "tf", "both")
#: Most candidates a file may ask for (as the API's search request: more are only chance fits).
MAX_CANDIDATES = 50


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", metavar="FILE",
                   help="telemetry files (tubsat-snapshots/1 JSON or CSV), image files (FITS, PNG, JPEG, TIFF) "
                        "or folders of frames")
    p.add_argument("--json", action="store_true", help="one JSON object per file and line")
    p.add_argument("--candidates", type=candidate_count, default=None, metavar="N",
                   help=f"distinct candidates to report, 1 to {MAX_CANDIDATES} (default 6)")
    p.add_argument("--method", choices=METHODS, default="bright_pair",
                   help="identifier: bright_pair (default), tf (Liebe's triangle features) or both, compared")
    p.add_argument("--prior", type=parse_prior, default=None, metavar="RA,DEC,ROLL[,SIGMA_DEG]",
                   help="tracking mode from this attitude (degrees; its 1-sigma defaults to 1 deg)")
    add_fov_argument(p)
    add_time_argument(p)
    add_annotate_argument(p)


def candidate_count(text: str) -> int:
    """``--candidates``: an integer from 1 to :data:`MAX_CANDIDATES` (the API's ``max_candidates`` range)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 1 <= value <= MAX_CANDIDATES:
        raise argparse.ArgumentTypeError(f"must be from 1 to {MAX_CANDIDATES}, got {value}")
    return value


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
    # The API's bounds (app.api.schemas.PriorAttitude): an RA of 434 is a typo, not 74.
    if not 0.0 <= ra < 360.0 or not -90.0 <= dec <= 90.0 or not -360.0 <= roll <= 360.0 or not 0.0 < sigma <= 10.0:
        raise argparse.ArgumentTypeError("RA must be within [0, 360), DEC within [-90, 90], ROLL within "
                                         f"[-360, 360] and SIGMA_DEG within (0, 10], got {text!r}")
    return Prior(rotation=rotation_from_radec_roll(ra, dec, roll), sigma_deg=sigma)


def run(args: argparse.Namespace) -> int:
    from app.identification import SearchOptions, Sky
    from app.workflow.files import invalid_solve_document, solve_document

    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    # Of the kernels, only a first run's compiling is news to a user (a warning); where they are, every time
    # a solve starts, is not.
    logging.getLogger("app.compiled").setLevel(logging.WARNING)
    annotate = Annotator(args.annotate, args.files)  # --annotate OUT.png: the solved frame drawn
    sky = Sky()
    # The kernels load (or, the first run after an install, compile) when the first valid file is solved
    # (solve_sequence's warm-up, one log line): a file that cannot be read is said at once.
    options = SearchOptions() if args.candidates is None else SearchOptions(max_candidates=args.candidates)

    def solve_one(path, sequence):
        doc = solve_document(path, sequence, sky, options=options,
                             method="tf" if args.method == "tf" else "bright_pair", prior=args.prior,
                             compare_tf=args.method == "both")
        return annotate(path, sequence, doc)

    status = for_each_file(args.files, solve_one, invalid_solve_document, args.json, print_summary,
                           fov_deg=args.fov_deg, time=args.time)
    return max(status, annotate.status)  # after the batch: a PNG that could not be written is an error


#: Stars named per candidate in the table (``--json`` has them all).
SHOWN_STARS = 6


def print_summary(doc) -> None:
    """A table of candidates per file (an :class:`app.workflow.documents.SolveDocument`)."""
    at = "" if doc.reference_snapshot is None else f"  (attitudes at snapshot {doc.reference_snapshot}, the reference)"
    print(f"{doc.file}: {doc.sequence_id or '-'}  {doc.status}{at}")
    if doc.error:
        print(indented_error(doc))
        return
    if doc.candidates:
        print(f"  {'rank':>4} {'RA deg':>10} {'Dec deg':>9} {'roll deg':>9} {'matched':>7} {'rms as':>7} "
              f"{'dev px/pt':>9} {'P(false)':>9}  stars")
        _print_candidates(doc.candidates)
    else:
        print("  no candidate (the notes say why)")
    best = doc.candidates[0] if doc.candidates else None
    if best is not None and best.fov_deg is not None and doc.status != "no_match":  # a chance fit's optics: noise
        from app.identification.scale_free import NOT_GIVEN

        given = not any(note.startswith(NOT_GIVEN) for note in doc.notes)
        print(f"  field of view: {best.fov_deg:.3f} deg (focal length {best.focal_length_px:.1f} px), "
              "fitted to the stars" + (" (one given is where the search began)" if given else ""))
    if best is not None and best.centre_ra_deg is not None:  # the table's RA, Dec: the optical axis
        print(f"  image centre: RA {best.centre_ra_deg:.4f} deg, Dec {best.centre_dec_deg:+.4f} deg "
              "(the table's RA, Dec are the boresight's, the optical axis)")
    for note in doc.notes:  # how the search went
        print(f"  note: {note}")
    if doc.focal_length_contradiction is not None:  # a focal length declared wrong beyond its tolerance
        print(f"  note: {doc.focal_length_contradiction.note}")
    if doc.tf_candidates is not None:
        print(f"  triangle-feature method: {doc.tf_status}, "
              f"{'agrees' if doc.methods_agree else 'DISAGREES'} with the bright-pair method")
        _print_candidates(doc.tf_candidates)


def _print_candidates(candidates) -> None:
    for c in candidates:
        more = len(c.matches) - SHOWN_STARS
        names = ", ".join(m.name or f"HIP {m.hip}" for m in c.matches[:SHOWN_STARS]) + (f", +{more} more" if more > 0 else "")
        planets = "".join(f", {p.name} (planet)" for p in c.planets)
        rms = float("nan") if c.rms_arcsec is None else c.rms_arcsec
        print(f"  {c.rank:>4} {c.ra_deg:>10.4f} {c.dec_deg:>9.4f} {c.roll_deg:>9.3f} "
              f"{c.n_matched:>7} {rms:>7.1f} {c.deviation_px_per_point:>9.3f} "
              f"{c.false_match_probability:>9.2g}  {names}{planets}")
