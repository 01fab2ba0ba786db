"""Running ``python -m app serve`` as a child process: for benchmarks and end-to-end tests.

A real server on loopback, on its own database and a free port, with its
output in a log file that errors quote.
"""

from __future__ import annotations

import http.client
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: The catalogue and index load before the server listens; a cold first start builds the index.
STARTUP_TIMEOUT_S = 300.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(db: Path, port: int, log_path: Path, extra_args: tuple[str, ...] = (),
                 env: dict[str, str] | None = None) -> subprocess.Popen:
    """``python -m app serve`` on loopback (no token needed) with its output appended to ``log_path``.

    ``env`` adds to (or overrides) the environment the server inherits.
    """
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    for name in ("STARID_TOKENS", "STARID_TOKENS_FILE", "DATABASE_URL", "STARID_DB"):
        env.pop(name, None)  # a loopback server of its own, on its own database
    with Path(log_path).open("ab") as log:
        return subprocess.Popen([sys.executable, "-m", "app", "serve", "--port", str(port), "--db", str(db),
                                 *extra_args], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)


def wait_ready(port: int, process: subprocess.Popen, log_path: Path, timeout_s: float = STARTUP_TIMEOUT_S) -> None:
    """Poll ``/api/health`` until it answers 200; RuntimeError with the log if the server dies or stalls."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"the server exited with {process.returncode}:\n{tail(log_path)}")
        try:
            connection = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
            connection.request("GET", "/api/health")
            if connection.getresponse().status == 200:
                connection.close()
                return
            connection.close()
        except OSError:
            pass
        time.sleep(0.25)
    raise RuntimeError(f"the server did not answer within {timeout_s:.0f} s:\n{tail(log_path)}")


def stop_server(process: subprocess.Popen) -> None:
    """SIGTERM (uvicorn shuts down cleanly), SIGKILL if it has not gone after 20 s."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=20)


def kill_server(process: subprocess.Popen) -> None:
    """SIGKILL: no shutdown of any kind (what durability is tested against)."""
    if process.poll() is None:
        process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)


def tail(path: Path, n_chars: int = 4000) -> str:
    try:
        return Path(path).read_text(errors="replace")[-n_chars:]
    except OSError:
        return "(no server log)"
