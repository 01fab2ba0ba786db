"""`python -m app serve [--host 127.0.0.1] [--port 8000] [--db PATH|URL]`: the REST API and the console.

One uvicorn worker serves the API under /api, the console (static/) at /
and the OpenAPI documentation at /docs.  The port is taken first, before
the catalogue loads, so that a busy port fails at once with a message
naming ``--port`` instead of after the seconds of loading; the catalogue and
the bright-pair index are then loaded before the server starts answering
(the first start builds the index and logs its counts), and the log names
the database and the default camera.  Bound to anything but loopback,
every write needs a bearer token (STARID_TOKENS or STARID_TOKENS_FILE) and
the server refuses to start without one.
"""

from __future__ import annotations

import argparse
import errno
import logging
import signal
import socket
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
    p.add_argument("--db", metavar="PATH|URL", default=None,
                   help="the archive: a SQLite file, or postgresql://user@host:port/dbname to share one archive "
                        "between servers (default: STARID_DB, DATABASE_URL or ~/.local/share/starid/starid.sqlite3)")
    p.add_argument("--viewer-port", type=_port, default=None,
                   help="port of the 3D view (viser, always on 127.0.0.1; default: --port + 1, "
                        "or the next free port)")
    p.add_argument("--no-viewer", action="store_true", help="do not start the 3D view")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"),
                   help="server log level (default info)")


def bind_port(host: str, port: int) -> socket.socket:
    """A socket bound to ``host:port`` (as uvicorn binds it); OSError with a sentence naming the option to change.

    Bound before anything slow happens and handed to uvicorn, so the port
    cannot be taken by someone else between the check and the start.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # IPPROTO_TCP, not 0: asyncio turns Nagle's algorithm off only on sockets that say they are TCP, and
    # with it on every answer waits ~40 ms for a delayed ACK.
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
        # Listening takes the port: with SO_REUSEADDR two processes may both bind it, only one listen.
        # Connections made while the catalogue loads wait in the backlog until the server answers.
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise OSError(exc.errno, f"port {port} on {host} is already in use (another server?): "
                                     f"stop it or choose another port with --port") from None
        if exc.errno == errno.EACCES:
            raise OSError(exc.errno, f"no permission to listen on port {port}: choose one above 1023 "
                                     f"with --port") from None
        raise OSError(exc.errno, f"cannot listen on {host}:{port} ({exc.strerror or exc}): check --host "
                                 f"and --port") from None
    sock.set_inheritable(False)
    return sock


def describe_camera(name: str) -> str:
    """The default camera in one line: name, sensor, focal length, field of view, magnitude limit."""
    from app.camera import CAMERAS

    camera = CAMERAS.get(name)
    if camera is None:
        return f"{name!r} (unknown: files without a camera block are refused)"
    fov_x, fov_y = camera.fov_deg
    return (f"{name} ({camera.width}x{camera.height} px, f = {camera.focal_length_px:g} px, "
            f"field {fov_x:.1f} x {fov_y:.1f} deg, magnitude limit {camera.limiting_magnitude:g})")


def run(args: argparse.Namespace) -> int:
    # The port first, before the seconds of imports and catalogue loading.
    try:
        sock = bind_port(args.host, args.port)
    except OSError as exc:
        print(f"serve: {exc.strerror}", file=sys.stderr)
        return 2
    import uvicorn

    from app.api import create_app
    from app.storage import StorageError
    from app.workflow import build_context
    from app.workflow.access import TokenConfigError

    logging.basicConfig(level=getattr(logging, args.log_level.upper()),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    log = logging.getLogger("app.serve")
    try:
        context = build_context(database=args.db, host=args.host)
    except (TokenConfigError, StorageError, ValueError) as exc:
        sock.close()
        print(f"serve: {exc}", file=sys.stderr)
        return 2
    log.info("database: %s", context.storage.path)
    log.info("default camera (files without a camera block): %s", describe_camera(context.settings.default_camera))
    log.info("limits: uploads up to %d bytes; searches and uploads answered within %g s (STARID_SEARCH_TIMEOUT_S)",
             context.settings.max_upload_bytes, context.settings.search_timeout_s)
    try:
        if not args.no_viewer:
            from app.viewer import start_viewer

            # The 3D view is optional: start_viewer logs and returns None when viser cannot start.
            viewer_port = args.viewer_port or (args.port % 65535) + 1
            context.viewer = start_viewer(context, viewer_port)
        app = create_app(context)
        log.info("serving on http://%s:%d (API /api, docs /docs)", args.host, args.port)
        config = uvicorn.Config(app, host=args.host, port=args.port, workers=1, log_level=args.log_level,
                                log_config=None)
        # uvicorn stops gracefully on SIGTERM and then raises the signal again with the handler it found;
        # the default one would end the process before the workers are stopped and the archive closed.
        signal.signal(signal.SIGTERM, _stop_requested)
        uvicorn.Server(config).run(sockets=[sock])
    except StopRequested:
        log.info("stopped (SIGTERM)")
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM during the clean-up ends it at once
        context.close()
        sock.close()
    return 0


class StopRequested(Exception):
    """SIGTERM arrived: the server has stopped serving, the clean-up follows."""


def _stop_requested(signum, frame) -> None:
    raise StopRequested()
