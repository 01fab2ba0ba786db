"""The real server process: what it acknowledged survives SIGKILL and a restart, byte for byte."""

from __future__ import annotations

import uuid
from pathlib import Path

import httpx

from app.bench.server import free_port, kill_server, start_server, wait_ready
from test_hardening_workers import MARKER, marked_processes, wait_until_gone  # tests/ is on sys.path


def test_confirmation_and_apm_survive_sigkill(tmp_path, sample_dir):
    db = tmp_path / "durable.sqlite3"
    log = tmp_path / "server.log"
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    marker = uuid.uuid4().hex  # inherited by every process the server starts (see test_hardening_workers)
    server = start_server(db, port, log, env={MARKER: marker})
    try:
        wait_ready(port, server, log)
        assert httpx.get(f"{base}/api/health", timeout=30).json()["search_workers"].endswith("processes")
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
        workers = _children(server.pid)
        kill_server(server)  # no shutdown of any kind: the acknowledged writes must already be on disk
    # The worker processes and multiprocessing's resource tracker go too (nobody else would ever stop them).
    assert len(workers) >= 3, "the server runs its work in worker processes (2 interactive, 1 bulk)"
    assert not wait_until_gone(marker)

    server = start_server(db, port, log)
    try:
        wait_ready(port, server, log)
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
        kill_server(server)


def _children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid`` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found

