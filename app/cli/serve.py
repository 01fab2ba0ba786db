"""`python -m app serve [--host 127.0.0.1] [--port 8000] [--db PATH]`: the REST API and the console.

One uvicorn worker serves the API under /api, the console (static/) at /
and the OpenAPI documentation at /docs.  The catalogue and the bright-pair
index are loaded before the server starts listening (the first start builds
the index and logs its counts).  Bound to anything but loopback, every write
needs a bearer token (STARID_TOKENS or STARID_TOKENS_FILE) and the server
refuses to start without one.
"""

from __future__ import annotations

import argparse
import logging
import sys


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"port must be 1..65535, not {value}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; any other needs bearer tokens)")
    p.add_argument("--port", type=_port, default=8000, help="TCP port (default 8000)")
    p.add_argument("--db", metavar="PATH", default=None,
                   help="SQLite database file (default: STARID_DB, DATABASE_URL or "
                        "~/.local/share/starid/starid.sqlite3)")
    p.add_argument("--viewer-port", type=_port, default=None,
                   help="port of the 3D view (viser, always on 127.0.0.1; default: --port + 1, "
                        "or the next free port)")
    p.add_argument("--no-viewer", action="store_true", help="do not start the 3D view")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"),
                   help="server log level (default info)")


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from app.api import create_app
    from app.storage import StorageError
    from app.workflow import build_context
    from app.workflow.access import TokenConfigError

    logging.basicConfig(level=getattr(logging, args.log_level.upper()),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        context = build_context(database=args.db, host=args.host)
    except (TokenConfigError, StorageError, ValueError) as exc:
        print(f"serve: {exc}", file=sys.stderr)
        return 2
    try:
        if not args.no_viewer:
            from app.viewer import start_viewer

            # The 3D view is optional: start_viewer logs and returns None when viser cannot start.
            viewer_port = args.viewer_port or (args.port % 65535) + 1
            context.viewer = start_viewer(context, viewer_port)
        app = create_app(context)
        logging.getLogger("app.serve").info("serving on http://%s:%d (API /api, docs /docs)",
                                            args.host, args.port)
        uvicorn.run(app, host=args.host, port=args.port, workers=1, log_level=args.log_level,
                    log_config=None)
    finally:
        context.close()
    return 0
