"""`python -m app calibrate FILE... [--json] [--fit f,cx,cy,k1]`: one camera fitted over many sequences.

Every file is identified; the identified ones give their stars, snapshot by
snapshot, and one camera (focal length, principal point, k1 by default; add
k2 with ``--fit``) is fitted over all of them with the attitudes free and
outliers rejected (:mod:`app.workflow.calibrate`).  Prints the fitted camera
with its 1-sigma, or with ``--json`` one object::

    {"camera": {...the keys of the telemetry camera object...}, "sigma": {...},
     "covariance": {"names": [...], "matrix": [[...]]}, "sequences_used": N,
     "observations_used": S, "stars_used": M, "stars_rejected": K,
     "rms_px_before": x, "rms_px_after": y, "chi2_reduced": c}

The camera object can be pasted into the telemetry files' camera block.
Exit status 0 on success, 2 when the files cannot fix a camera (fewer than
three identified sequences, invalid files only, ...) or when some files were
invalid (the camera is then fitted over the others, and printed).
"""

from __future__ import annotations

import argparse
import logging
import sys

FITTABLE = ("f", "focal_length_px", "cx", "cy", "k1", "k2")


def _parameters(text: str) -> tuple[str, ...]:
    names = tuple(p.strip() for p in text.split(",") if p.strip())
    unknown = [p for p in names if p not in FITTABLE]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"expected a comma-separated subset of f, cx, cy, k1, k2; got {text!r}")
    return names


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", metavar="FILE", help="telemetry files of one camera (JSON or CSV)")
    p.add_argument("--json", action="store_true", help="print the calibration as one JSON object")
    p.add_argument("--fit", type=_parameters, default=None, metavar="PARAMS",
                   help="parameters to fit (default f,cx,cy,k1; k2 is barely determined on narrow fields)")


def run(args: argparse.Namespace) -> int:
    from app.identification import SearchOptions, Sky
    from app.workflow.calibrate import calibrate_files
    from app.workflow.errors import WorkflowError
    from app.cli.common import command_line_inputs
    from app.workflow.files import telemetry_files

    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    sky = Sky()
    invalid = []

    def valid_files():
        for path, sequence, error in telemetry_files(command_line_inputs(args.files)):
            if error is None:
                yield path, sequence
            else:
                invalid.append(path)
                print(f"{path}: invalid, left out\n  {error}", file=sys.stderr)

    try:
        document, report = calibrate_files(valid_files(), sky, SearchOptions(), args.fit)
    except WorkflowError as exc:
        print(f"calibrate: {exc.detail}", file=sys.stderr)
        return 2
    for path, what in report:
        print(f"{path}: {what}", file=sys.stderr)
    # As solve and extract: the camera is fitted over the valid files, and invalid ones make the status 2.
    status = 2 if invalid else 0
    if args.json:
        print(document.model_dump_json())
        return status
    print(f"camera fitted over {document.sequences_used} sequences ({document.observations_used} snapshots, "
          f"{document.stars_used} stars, {document.stars_rejected} rejected); "
          f"rms {document.rms_px_before:.3f} px with the declared camera -> {document.rms_px_after:.3f} px")
    for name, sigma in document.sigma.items():
        print(f"  {name:<16} {document.camera[name]:>14.6f}  +- {sigma:.3g}")
    return status
