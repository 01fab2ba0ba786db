"""`python -m app COMMAND ...`: thin command-line layer over the stages.

Each command lives in its own module under ``app.cli`` with two functions,
``add_arguments(parser)`` and ``run(args) -> exit status``; modules are
imported only when their command runs, so ``extract`` never pays for the
server's imports.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = {
    "extract": "tell tracked stars from ghosts and hot pixels in telemetry files",
    "solve": "identify the star pattern and the attitude of telemetry files",
    "simulate": "write simulated telemetry sequences with truth files",
    "bench": "run the benchmarks and print their figures",
    "serve": "start the REST API, the browser console and the 3D view",
    "upload": "upload telemetry files to a running server",
    "calibrate": "fit the camera (focal length, principal point, distortion) over many sequences",
    "batch": "extract and identify many sequences on a Dask cluster, into the archive or JSON lines",
}


def build_parser(load_arguments: bool = True, argv: list[str] | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m app", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_text in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if load_arguments and (argv is None or (argv and argv[0] == name)):
            module = importlib.import_module(f"app.cli.{name}")
            module.add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv=argv)
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    module = importlib.import_module(f"app.cli.{args.command}")
    try:
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # e.g. `python -m app solve ... | head`
        return 0
