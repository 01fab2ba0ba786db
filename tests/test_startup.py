"""Start-up: a server answers while its compute workers are still loading (on a first start, compiling) their
kernels; searches and uploads sent meanwhile wait for them and are then answered in full, not timed out.

The compilation is stood in for by a warm-up registered next to the product's (:func:`app.compiled.warm_up_with`)
that holds every worker until the test lets go of a lock file: the real workers, pool, routes and server
otherwise, and a state to wait on instead of a guess of how long a compilation takes.
"""

from __future__ import annotations

import fcntl
import json
import logging
import threading
from concurrent.futures import Future, ThreadPoolExecutor, TimeoutError as FutureTimeout

import httpx
import numpy as np
import pytest
import uvicorn

from app.api import create_app
from app.attitude import angle_between, rotation_from_radec_roll
from app.bench.server import free_port
from app.config import Settings
from app.storage import Storage
from app.workflow import AppContext
from app.workflow.archive import LARGE_UPLOAD_BYTES
from app.workflow.compute import KERNEL_MODULES, ComputePool

#: The search time-out of this test's server, seconds: short, so that waiting three times longer shows that a
#: request waiting for the kernels is not timed out.
TIMEOUT_S = 2.0

GATED_WARM_UP = '''
import fcntl, os

from app.compiled import warm_up_with


@warm_up_with
def _until_the_test_lets_go():
    with open(os.environ["STARTUP_TEST_GATE"]) as gate:
        fcntl.flock(gate, fcntl.LOCK_SH)  # waits while the test holds the file exclusively
'''


class _Server:
    """uvicorn in a thread of the test, on a free port of loopback."""

    def __init__(self, ctx: AppContext) -> None:
        self.port = free_port()
        self.server = uvicorn.Server(uvicorn.Config(create_app(ctx), host="127.0.0.1", port=self.port,
                                                    log_level="warning", log_config=None))
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> httpx.Client:
        self.thread.start()
        client = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=120)
        for _ in range(400):  # until uvicorn listens (each refused connection returns at once)
            try:
                client.get("/api/health")
                return client
            except httpx.ConnectError:
                self.thread.join(0.05)
        raise RuntimeError("the test server did not start")

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(30)


def test_the_server_answers_while_its_workers_load_their_kernels_and_searches_wait_for_them(
        tmp_path, monkeypatch, sample_dir, sky, caplog):
    (tmp_path / "gated_warm_up.py").write_text(GATED_WARM_UP)
    monkeypatch.syspath_prepend(str(tmp_path))  # the spawned workers get the test's sys.path
    gate = tmp_path / "gate"
    gate.touch()
    monkeypatch.setenv("STARTUP_TEST_GATE", str(gate))
    monkeypatch.setenv("STARID_SEARCH_TIMEOUT_S", str(TIMEOUT_S))
    caplog.set_level(logging.INFO, logger="app.workflow.compute")
    held = open(gate)
    fcntl.flock(held, fcntl.LOCK_EX)
    pool = ComputePool(1, bulk_processes=1, kernel_modules=(*KERNEL_MODULES, "gated_warm_up"))
    ctx = AppContext(storage=Storage.open(tmp_path / "db.sqlite3"), sky=sky, settings=Settings(), _compute=pool)
    waiting = ThreadPoolExecutor(2)
    try:
        with _Server(ctx) as api:
            # Health, the console, archive reads: answered at once, saying the compute is not ready.
            health = api.get("/api/health")
            assert health.status_code == 200 and health.json()["compute_ready"] is False
            assert health.json()["search_workers"] == "1 processes"
            assert api.get("/").status_code == 200 and "<html" in api.get("/").text.lower()
            assert api.get("/api/sequences").json()["total"] == 0

            # An upload followed by its search, sent now: both wait for the kernels, past their time-out.  Made
            # large with trailing blanks, the upload is parsed on the bulk lane before its extraction: two
            # computations of one request, the second as unhurried by the wait as the first.
            data = (sample_dir / "04-big-dipper.json").read_bytes() + b" " * LARGE_UPLOAD_BYTES

            def upload_and_search() -> tuple[httpx.Response, httpx.Response | None]:
                upload = api.post("/api/sequences?filename=04-big-dipper.json", content=data,
                                  headers={"Content-Type": "application/json"})
                if upload.status_code != 201:
                    return upload, None
                return upload, api.post(f"/api/sequences/{upload.json()['id']}/search", json={})

            sent: Future = waiting.submit(upload_and_search)
            with pytest.raises(FutureTimeout):
                sent.result(timeout=3 * TIMEOUT_S)  # not answered (503) within its time-out: it waits
            assert not pool.ready and api.get("/api/health").json()["compute_ready"] is False

            fcntl.flock(held, fcntl.LOCK_UN)  # the "compilation" ends
            upload, search = sent.result(timeout=120)
            assert upload.status_code == 201, upload.text
            assert search is not None and search.status_code == 200, search.text
            doc = search.json()
            truth = json.loads((sample_dir / "04-big-dipper.truth.json").read_text())
            ref = doc["reference_snapshot"]
            assert doc["status"] == "identified"
            boresight = rotation_from_radec_roll(*truth["radec_roll_deg"][ref])[2]
            assert np.degrees(angle_between(np.asarray(doc["candidates"][0]["rotation_matrix"])[2], boresight)) < 0.1
            assert pool.ready and api.get("/api/health").json()["compute_ready"] is True
    finally:
        held.close()
        waiting.shutdown(wait=False, cancel_futures=True)
        ctx.close()
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("compute ready")]
    assert len(said) == 1 and "(worker processes: 1 search, 1 bulk)" in said[0], said
