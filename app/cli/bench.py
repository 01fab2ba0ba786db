"""`python -m app bench [--suite NAME] [--n N] [--seed S] [--think S] [--frames DIR] [--method M] [--json]`:
benchmark figures.

Suites: ``extraction`` (tracked stars kept, ghosts and hot pixels
rejected, time per sequence), ``identification`` (top-1/top-5
correct, wrong "identified" answers, attitude errors, time per sequence and
the seed's deviation table; ``--method tf`` solves by Liebe's triangle features instead of the
default bright pairs), ``load`` (the real server under 20
concurrent clients; here ``--n`` is the duration in seconds, default 30, and
``--think`` each client's pause between loops, default 1 s, 0 for saturation;
``--adversarial`` adds two clients sending worst-case files).
``seeds`` (also ``--seeds``: Liebe's Tables 2 and 3 and Fig. 2,
see :mod:`app.bench.seeds`).  ``camera`` (identification with
wrong focal lengths and undeclared distortion, and calibration accuracy
from 20, 50 and 200 sequences, see :mod:`app.bench.camera`).  ``batch``
(sequences per second of ``python -m app batch`` with 1 and 2 Dask
workers, see :mod:`app.bench.batch`); ``load`` also takes ``--servers 2
--database postgresql://...`` (two servers on one shared archive).
``calibration`` (the pulls of many calibrations: are the stated sigmas
honest and the fit centred? ``--n`` trials of 20 sequences, default 60; see
:mod:`app.bench.calibration`).
``real`` (real star-camera frames against astrometry.net's WCS, side by side with
cedar-solve; ``--frames DIR``, default ``$STARID_REAL_FRAMES`` or ``../shared/real-frames``;
``--time-from-reference`` gives each frame its reference's time in a sidecar; ``--n`` the first N
frames; see :mod:`app.bench.real`).  ``variants`` (each real frame copied five ways that keep its
sky: twice and half the sampling, turned, cropped off-centre, a dark foreground; see
:mod:`app.bench.variants`).  ``floor`` (the search's own time: the default against searches without
the operator's alternatives, the optics fit and the image centre; see :mod:`app.bench.floor`).
``wide`` (simulated photographs through wide-angle lenses, 40-105 deg, with their field of view, one 5 %
off, only their lens in EXIF, and none; ``--n`` photographs a field, default 8; see :mod:`app.bench.wide`).
``trails`` (the same photographs with every star trailed 0-20 px, as from a fixed tripod; ``--n`` a field of
view and trail, default 4; see :mod:`app.bench.trails`).
Every figure is measured now, on this machine, in one process (the load
suite adds the server's), from simulated sequences drawn with ``--seed``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys
import time

SUITES = ("extraction", "identification", "sequence", "load", "seeds", "camera", "peer", "frames", "batch",
          "calibration", "real", "variants", "floor", "wide", "trails")
#: The lost-in-space methods the identification suite can measure (app.identification.methods.METHODS).
IDENTIFICATION_METHODS = ("bright_pair", "tf")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--suite", choices=SUITES + ("all",), default="all", help="which benchmark (default: all)")
    p.add_argument("--seeds", dest="suite", action="store_const", const="seeds",
                   help="Liebe's tables 2 and 3 and Fig. 2 (= --suite seeds; --n trials per situation, default 500)")
    p.add_argument("--n", type=int, default=None, metavar="N",
                   help="sequences per table row (default: 100 identification, 300 extraction); "
                        "for the load suite, seconds of load (default 30)")
    p.add_argument("--seed", type=int, default=1, help="random seed of the simulated data (default 1)")
    p.add_argument("--adversarial", action="store_true",
                   help="load suite: two more clients send worst-case files (64 snapshots x 64 sources) "
                        "without pause; the target still counts the ordinary clients")
    p.add_argument("--servers", type=int, default=1, metavar="N",
                   help="load suite: N servers on one PostgreSQL archive (needs --database)")
    p.add_argument("--database", default=None, metavar="URL",
                   help="load suite: a postgresql:// URL; the run makes a fresh database on that server")
    p.add_argument("--think", type=float, default=None, metavar="SECONDS",
                   help="load suite: each client's pause between its loops (default 1; 0 = saturation)")
    p.add_argument("--frames", default=None, metavar="DIR",
                   help="real and variants suites: the folder of NAME.png + NAME.json frames (default $STARID_REAL_FRAMES, "
                        "else ../shared/real-frames beside the repository)")
    p.add_argument("--time-from-reference", action="store_true",
                   help="real suite: a sidecar gives each frame its reference's time_approximate (default: no time)")
    p.add_argument("--method", choices=IDENTIFICATION_METHODS, default="bright_pair",
                   help="identification suite: the lost-in-space method that solves the sequences (default "
                        "bright_pair; tf: Liebe's triangle features)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    if args.n is not None and args.n < 1:
        print("error: --n must be at least 1", file=sys.stderr)
        return 2
    if args.think is not None and not (0 <= args.think <= 60):
        print("error: --think must be between 0 and 60 seconds", file=sys.stderr)
        return 2
    if args.servers < 1 or (args.servers > 1 and not args.database):
        print("error: --servers must be at least 1, and several servers need --database postgresql://...",
              file=sys.stderr)
        return 2
    if args.frames is not None and not os.path.isdir(args.frames):
        print(f"error: --frames {args.frames}: not a folder", file=sys.stderr)
        return 2
    suites = SUITES if args.suite == "all" else (args.suite,)
    from app.compiled import warm_up
    from app.workflow.compute import KERNEL_MODULES

    for kernels in KERNEL_MODULES:  # every kernel loaded before any clock starts (a solve loads them as used)
        importlib.import_module(kernels)
    warm_up()
    results = {}
    for name in suites:
        module = importlib.import_module(f"app.bench.{name}")
        t0 = time.perf_counter()
        kwargs = {"seed": args.seed}
        if args.n is not None:
            kwargs["n_sequences"] = args.n
        if name == "load" and args.think is not None:
            kwargs["think_s"] = args.think
        if name == "load" and args.adversarial:
            kwargs["adversarial"] = module.ADVERSARIAL_CLIENTS
        if name == "load":
            kwargs.update(servers=args.servers, database=args.database)
        if name == "identification":
            kwargs["method"] = args.method
        if name == "real":
            kwargs.update(frames_dir=args.frames, time_from_reference=args.time_from_reference)
        if name == "variants":
            kwargs["frames_dir"] = args.frames
        results[name] = module.run(**kwargs)
        results[name]["wall_s"] = round(time.perf_counter() - t0, 1)
        if not args.json:
            print(f"== {name} ({results[name]['wall_s']} s) ==")
            print(module.format_table(results[name]))
            print()
    if args.json:
        print(json.dumps(results, allow_nan=False))
    return 0
