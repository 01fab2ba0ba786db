"""A throw-away PostgreSQL server for the tests: Debian's ``postgresql`` package, a temporary
directory, a free port on 127.0.0.1.

:class:`PostgresServer` runs ``initdb`` and ``pg_ctl`` from ``/usr/lib/postgresql/*/bin`` (the
newest version there, or ``$STARID_PG_BIN``).  PostgreSQL refuses to run as root, so when the tests
run as root the server runs as the ``postgres`` user (``runuser -u postgres --``) in a directory
that user owns.  ``pg_ctl start -w`` returns once the server accepts connections, and
:meth:`PostgresServer.stop` stops it (``-m fast``) and removes its directory.

Authentication is ``trust`` on 127.0.0.1 only (a test server that lives as long as the test
session).  :meth:`PostgresServer.new_database` creates an empty database per test, so every test
starts from a fresh archive while the whole session shares one server process.

Missing binaries raise :class:`PostgresUnavailable` with what to install; the fixtures turn that
into a test failure, never a skip.
"""

from __future__ import annotations

import glob
import itertools
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

#: The superuser of the test cluster.
SUPERUSER = "postgres"
INSTALL_HINT = ("Debian's PostgreSQL server is needed by the tests: `apt-get install postgresql` "
                "(tests/setup_and_run.sh installs it), or set STARID_PG_BIN to a directory holding "
                "initdb and pg_ctl")


class PostgresUnavailable(RuntimeError):
    """No PostgreSQL server binaries, or the server would not start."""


def find_bin_dir() -> Path:
    """The directory of ``initdb`` and ``pg_ctl``: $STARID_PG_BIN, else the newest /usr/lib/postgresql/*/bin."""
    explicit = os.environ.get("STARID_PG_BIN")
    candidates = [Path(explicit)] if explicit else sorted(
        (Path(p) for p in glob.glob("/usr/lib/postgresql/*/bin")),
        key=lambda p: [int(v) if v.isdigit() else 0 for v in p.parent.name.split(".")], reverse=True)
    for directory in candidates:
        if (directory / "initdb").exists() and (directory / "pg_ctl").exists():
            return directory
    raise PostgresUnavailable(f"no initdb/pg_ctl found (looked in {explicit or '/usr/lib/postgresql/*/bin'}). "
                              + INSTALL_HINT)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresServer:
    """One PostgreSQL server in a temporary directory; see the module docstring."""

    def __init__(self) -> None:
        self.bin_dir = find_bin_dir()
        self._as_postgres = os.geteuid() == 0
        self.root = Path(tempfile.mkdtemp(prefix="starid-pg-"))
        self.data_dir = self.root / "data"
        self.log_path = self.root / "server.log"
        self.port: int | None = None
        self._names = itertools.count(1)
        if self._as_postgres:
            try:
                account = pwd.getpwnam("postgres")
            except KeyError:
                raise PostgresUnavailable("running as root needs the `postgres` user to own the server; "
                                          + INSTALL_HINT) from None
            os.chown(self.root, account.pw_uid, account.pw_gid)
        os.chmod(self.root, 0o700)

    def _run(self, *args: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess:
        command = [str(self.bin_dir / args[0]), *args[1:]]
        if self._as_postgres:
            command = ["runuser", "-u", "postgres", "--", *command]
        run = subprocess.run(command, capture_output=True, text=True, timeout=timeout, cwd=self.root)
        if check and run.returncode != 0:
            raise PostgresUnavailable(f"{' '.join(args[:2])} failed ({run.returncode}):\n{run.stdout[-2000:]}"
                                      f"{run.stderr[-2000:]}\n{self.log_tail()}")
        return run

    def start(self) -> "PostgresServer":
        self._run("initdb", "-D", str(self.data_dir), "-U", SUPERUSER, "--auth=trust", "-E", "UTF8",
                  "--locale=C.UTF-8", "--no-instructions")
        # A port that is free now can be taken before the server binds it: try a few.
        for _attempt in range(5):
            port = _free_port()
            options = (f"-c listen_addresses=127.0.0.1 -c port={port} -c unix_socket_directories={self.root} "
                       "-c max_connections=200 -c shared_buffers=64MB -c timezone=UTC -c log_min_messages=warning")
            run = self._run("pg_ctl", "start", "-w", "-t", "60", "-D", str(self.data_dir), "-l", str(self.log_path),
                            "-o", options, check=False)
            if run.returncode == 0:
                self.port = port
                return self
            if "could not bind" not in self.log_tail() and "already in use" not in self.log_tail():
                break
        raise PostgresUnavailable(f"the PostgreSQL server did not start:\n{run.stdout[-1500:]}{run.stderr[-1500:]}"
                                  f"\n{self.log_tail()}")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{SUPERUSER}@127.0.0.1:{self.port}/{database}"

    def new_database(self, prefix: str = "t") -> str:
        """An empty database of its own; its URL."""
        import psycopg

        name = f"{prefix}_{os.getpid()}_{next(self._names)}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def restart(self) -> None:
        """Stop the server (fast: every connection is cut) and start it again on the same port."""
        self._run("pg_ctl", "restart", "-w", "-t", "60", "-m", "fast", "-D", str(self.data_dir), "-l",
                  str(self.log_path))

    def log_tail(self, n_chars: int = 3000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-n_chars:]
        except OSError:
            return "(no server log)"

    def stop(self) -> None:
        if self.port is not None and self.data_dir.exists():
            self._run("pg_ctl", "stop", "-w", "-m", "fast", "-D", str(self.data_dir), check=False)
            self.port = None
        shutil.rmtree(self.root, ignore_errors=True)
