"""`python -m app simulate OUTDIR --n N --seed S`: simulated telemetry with truth files.

Writes ``<id>.json`` (tubsat-snapshots/1) or, with ``--csv``, ``<id>.csv``,
and ``<id>.truth.json`` for each sequence; prints the paths written.
The same arguments give the same files byte for byte.

``--frames fits|png`` renders whole frames instead of spot lists: ``<id>.fits``
(one image extension per frame; times and optics in the headers) or a folder ``<id>/`` of
16-bit PNGs with its ``frames.json`` sidecar, plus ``<id>.truth.json`` (every drawn star's exact
position, flux and SNR, the hot pixels, the trail).  ``--frames-per-pass`` frames each
(default 4), ``--trail`` puts a satellite trail in one of them.

``--focal-error``, ``--k1``, ``--k2``, ``--corner-distortion``, ``--cx-offset``,
``--cy-offset``: the true optics differ from the camera the files declare
(the truth file says how, under ``true_camera``).
"""

from __future__ import annotations

import argparse
import sys
from datetime import datetime, timezone
from pathlib import Path

from app.camera import CAMERAS
from app.planets import PLANETS
from app.simulate import SCENARIOS


def _start_time(text: str) -> datetime:
    try:
        t = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not an ISO 8601 time: {text!r}") from exc
    return t.replace(tzinfo=timezone.utc) if t.tzinfo is None else t.astimezone(timezone.utc)


def _int_at_least(minimum: int):
    """An argparse type: an integer no smaller than ``minimum``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from exc
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}")
        return value
    return parse


_positive_int = _int_at_least(1)
_seed = _int_at_least(0)


def _finite_float(text: str) -> float:
    """An argparse type: a finite decimal number (limits are checked by app.simulate.true_optics)."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from exc
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "scenarios:\n" + "\n".join(f"  {k:<11} {v}" for k, v in SCENARIOS.items())
    parser.add_argument("outdir", type=Path, help="directory to write into (created if missing)")
    parser.add_argument("--n", type=_positive_int, default=1, help="number of sequences (default 1)")
    parser.add_argument("--seed", type=_seed, default=0, help="random seed (default 0)")
    parser.add_argument("--camera", choices=list(CAMERAS), default=None,
                        help="camera model; default: cycle through " + ", ".join(CAMERAS))
    parser.add_argument("--scenario", choices=list(SCENARIOS), default="nominal",
                        help="what the sequence shows (default nominal; see below)")
    parser.add_argument("--planet", choices=list(PLANETS), default=None,
                        help="the planet of the 'planet' scenario (default: a bright one away from the Sun)")
    parser.add_argument("--start-time", type=_start_time, default=None,
                        help="UTC time of the first snapshot, ISO 8601 (default random in 1990-2030)")
    parser.add_argument("--name", default=None,
                        help="sequence id and file name (NAME.json, or NAME-0000.json ... when --n > 1)")
    parser.add_argument("--csv", action="store_true", help="write the CSV form instead of JSON")
    frames = parser.add_argument_group("full frames", "rendered images instead of spot lists")
    frames.add_argument("--frames", choices=("fits", "png"), default=None,
                        help="render frames: one multi-extension FITS per pass, or a folder of PNGs + frames.json")
    frames.add_argument("--frames-per-pass", type=_int_at_least(1), default=4, metavar="N",
                        help="frames per pass, 1 to 64 (default 4)")
    frames.add_argument("--trail", action="store_true", help="a satellite trail crosses one frame of each pass")
    optics = parser.add_argument_group(
        "true optics", "the sky is projected with these while the files declare the nominal camera")
    optics.add_argument("--focal-error", type=_finite_float, default=0.0, metavar="F",
                        help="true focal length = declared * (1 + F); F in -0.2..0.2 (0.03: 3 %% long)")
    distortion = optics.add_mutually_exclusive_group()
    distortion.add_argument("--k1", type=_finite_float, default=None, metavar="K",
                            help="true radial distortion k1 (|K| <= 1); k1 r^2 is the fraction the corner "
                                 "moves, r = half-diagonal / f (20 deg camera: 1 %% is k1 = 0.20)")
    distortion.add_argument("--corner-distortion", type=_finite_float, default=None, metavar="P",
                            help="k1 such that the sensor corner moves by the fraction P of its radius "
                                 "(0.01: 1 %%), computed for each camera")
    optics.add_argument("--k2", type=_finite_float, default=None, metavar="K", help="true k2 (|K| <= 1)")
    optics.add_argument("--cx-offset", type=_finite_float, default=0.0, metavar="PX",
                        help="true principal point x = declared cx + PX")
    optics.add_argument("--cy-offset", type=_finite_float, default=0.0, metavar="PX",
                        help="true principal point y = declared cy + PX")


def run(args: argparse.Namespace) -> int:
    from app.simulate import write_simulation

    if args.frames:
        return _run_frames(args)

    try:
        paths = write_simulation(args.outdir, args.n, args.seed, args.camera, args.scenario,
                                 name=args.name, csv=args.csv, planet=args.planet,
                                 start_time=args.start_time, focal_error=args.focal_error,
                                 k1=args.k1, k2=args.k2, corner_distortion=args.corner_distortion,
                                 cx_offset=args.cx_offset, cy_offset=args.cy_offset)
    except ImportError:
        print("error: the CSV writer (app.telemetry.formats.dump_csv) is not available", file=sys.stderr)
        return 2
    except (OSError, ValueError) as exc:
        print(f"error: {_message(exc)}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0


def _run_frames(args: argparse.Namespace) -> int:
    """``--frames``: rendered passes (scenario, planet, CSV and k2/offsets do not apply to frames)."""
    from app.simulate import write_frames

    if args.csv or args.k2 is not None or args.cx_offset or args.cy_offset or args.corner_distortion is not None:
        print("error: --frames takes --focal-error and --k1 for the true optics; not --csv, --k2, "
              "--corner-distortion or the principal point offsets", file=sys.stderr)
        return 2
    try:
        paths = write_frames(args.outdir, args.n, args.seed, args.camera, form=args.frames,
                             n_frames=args.frames_per_pass, name=args.name, start_time=args.start_time,
                             trail=args.trail, focal_error=args.focal_error, k1=args.k1)
    except (OSError, ValueError) as exc:
        print(f"error: {_message(exc)}", file=sys.stderr)
        return 2
    for path in paths:
        print(path)
    return 0


def _message(exc: Exception) -> str:
    """What went wrong, for the operator: an OS error as "cannot write PATH: reason", without its errno."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"cannot write {exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    return str(exc)
