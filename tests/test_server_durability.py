"""The real server process: what it acknowledged survives SIGKILL and a restart, byte for byte."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parent.parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(db: Path, port: int, log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("STARID_TOKENS", None)
    env.pop("STARID_TOKENS_FILE", None)
    return subprocess.Popen([sys.executable, "-m", "app", "serve", "--port", str(port), "--db", str(db)],
                            cwd=REPO, env=env, stdout=log.open("ab"), stderr=subprocess.STDOUT)


def _wait_ready(base: str, process: subprocess.Popen, log: Path, timeout_s: float = 90.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"the server exited with {process.returncode}:\n{log.read_text()}")
        try:
            if httpx.get(f"{base}/api/health", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise AssertionError(f"the server did not answer within {timeout_s} s:\n{log.read_text()}")


def _kill(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)


def test_confirmation_and_apm_survive_sigkill(tmp_path, sample_dir):
    db = tmp_path / "durable.sqlite3"
    log = tmp_path / "server.log"
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    server = _start(db, port, log)
    try:
        _wait_ready(base, server, log)
        data = (sample_dir / "04-big-dipper.json").read_bytes()
        r = httpx.post(f"{base}/api/sequences", files={"file": ("04-big-dipper.json", data, "application/json")},
                       timeout=60)
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        r = httpx.post(f"{base}/api/sequences/{sid}/search", json={}, timeout=60)
        assert r.status_code == 200 and r.json()["candidates"], r.text
        r = httpx.post(f"{base}/api/sequences/{sid}/confirm",
                       json={"rank": 1, "operator": "night shift", "comment": "Big Dipper"}, timeout=60)
        assert r.status_code == 201, r.text
        confirmed = r.json()
        apm = httpx.get(f"{base}/api/attitudes/{confirmed['id']}/apm", timeout=30).content
        aem = httpx.get(f"{base}/api/sequences/{sid}/aem", timeout=30).content
        assert apm.startswith(b"CCSDS_APM_VERS = 2.0") and aem.startswith(b"CCSDS_AEM_VERS = 2.0")
    finally:
        _kill(server)  # no shutdown of any kind: the acknowledged writes must already be on disk

    server = _start(db, port, log)
    try:
        _wait_ready(base, server, log)
        again = httpx.get(f"{base}/api/attitudes/{confirmed['id']}", timeout=30).json()
        assert again == confirmed
        assert httpx.get(f"{base}/api/attitudes/{confirmed['id']}/apm", timeout=30).content == apm
        assert httpx.get(f"{base}/api/sequences/{sid}/aem", timeout=30).content == aem
        assert httpx.get(f"{base}/api/sequences/{sid}", timeout=30).json()["status"] == "confirmed"
        # The same upload is recognised as already stored.
        r = httpx.post(f"{base}/api/sequences", content=data, headers={"Content-Type": "application/json"},
                       timeout=60)
        assert r.status_code == 200 and r.json()["id"] == sid
    finally:
        _kill(server)
