"""The real server process: what it acknowledged survives SIGKILL and a restart, byte for byte."""

from __future__ import annotations

import httpx

from app.bench.server import free_port, kill_server, start_server, wait_ready


def test_confirmation_and_apm_survive_sigkill(tmp_path, sample_dir):
    db = tmp_path / "durable.sqlite3"
    log = tmp_path / "server.log"
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(db, port, log)
    try:
        wait_ready(port, server, log)
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
        kill_server(server)  # no shutdown of any kind: the acknowledged writes must already be on disk

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
