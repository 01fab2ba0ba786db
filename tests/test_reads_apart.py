"""Reads that do not queue behind writes (issue 29).

* SQLite: a reading method runs on a read connection of its own, so it answers while a writer's transaction
  is open (it sees the last commit, not the writer's rows) and an open read snapshot does not hold a writer up;
  closing the archive closes the read connections.
* A large upload is validated in a bulk worker, not in the server: the worker's answer is the telemetry the
  server would have parsed, an invalid file's located problems cross the process boundary whole, and the API
  answers such files exactly as before (201 with the stored file, 422 with the located problem).
"""

from __future__ import annotations

import json
import pickle
import threading

import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.bench.load import worst_case_telemetry
from app.storage import Storage, StorageError, content_sha256
from app.telemetry import TelemetryError, parse_telemetry
from app.workflow import AppContext, archive
from app.workflow.compute import BULK, ComputePool

#: Generous bound for a thread that should finish at once (it only fails a test that would hang).
PROMPT_S = 20.0


def _upload(store: Storage, k: int):
    row, created = store.add_sequence(raw_text=f"upload {k}", sequence_id=f"s{k}")
    assert created
    return row


def _in_thread(fn):
    """Run ``fn`` in a thread; (thread, result box) so the caller can join with a bound."""
    box: dict = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, box


def test_sqlite_reads_answer_while_a_write_transaction_is_open(tmp_path):
    store = Storage.open(tmp_path / "reads.sqlite3")
    first = _upload(store, 1)
    inserted, release = threading.Event(), threading.Event()

    def slow_writer():
        with store._transaction() as conn:  # the writers' lock and SQLite's write lock, held until release
            conn.execute("INSERT INTO sequences (content_sha256, raw_text, uploaded_at) VALUES (?, ?, ?)",
                         (content_sha256("uncommitted"), "uncommitted", "2026-01-01T00:00:00.000000+00:00"))
            inserted.set()
            assert release.wait(PROMPT_S)

    writer, writer_box = _in_thread(slow_writer)
    assert inserted.wait(PROMPT_S)
    # With one shared connection these reads waited for the writer's commit (here: forever).
    reader, box = _in_thread(lambda: (store.get_sequence(first.id), store.find_sequence(content_sha256("uncommitted")),
                                      store.list_sequences()[1]))
    reader.join(PROMPT_S)
    assert not reader.is_alive(), "a read waited for an open write transaction"
    assert "error" not in box
    committed, uncommitted, total = box["value"]
    assert committed.raw_text == "upload 1" and uncommitted is None and total == 1  # the last commit only
    release.set()
    writer.join(PROMPT_S)
    assert not writer.is_alive() and "error" not in writer_box
    assert store.find_sequence(content_sha256("uncommitted")) is not None  # seen once committed
    assert store.list_sequences()[1] == 2
    store.close()


def test_sqlite_a_read_snapshot_neither_blocks_a_writer_nor_sees_its_commit(tmp_path):
    store = Storage.open(tmp_path / "snapshot.sqlite3")
    _upload(store, 1)
    with store._transaction(write=False, snapshot=True) as conn:
        assert conn.execute("SELECT COUNT(*) FROM sequences").fetchone()[0] == 1
        writer, box = _in_thread(lambda: _upload(store, 2))
        writer.join(PROMPT_S)
        assert not writer.is_alive() and "error" not in box  # committed while the snapshot is open
        assert conn.execute("SELECT COUNT(*) FROM sequences").fetchone()[0] == 1  # one state of the archive
    assert store.list_sequences()[1] == 2
    with pytest.raises(Exception, match="readonly|read-only|query_only"):
        with store._transaction(write=False) as conn:  # a reader cannot write past the writers' lock
            conn.execute("UPDATE sequences SET status = 'identified'")
    assert {r.status for r in store.list_sequences()[0]} == {"new"}
    store.close()


def test_sqlite_close_closes_the_read_connections(tmp_path):
    store = Storage.open(tmp_path / "close.sqlite3")
    row = _upload(store, 1)
    with store._transaction(write=False) as held:  # in use while the archive closes
        assert store.get_sequence(row.id).id == row.id  # a second reader: a second connection
        idle = list(store._readers._idle)
        assert len(idle) == 1
        store.close()
        assert held.execute("SELECT COUNT(*) FROM sequences").fetchone()[0] == 1  # its reader finishes
    for conn in (*idle, held):
        with pytest.raises(Exception, match="closed"):
            conn.execute("SELECT 1")
    with pytest.raises(StorageError, match="closed"):
        store.get_sequence(row.id)


def test_a_large_upload_is_parsed_in_a_bulk_worker_as_the_server_would(tmp_path):
    data = worst_case_telemetry(3, "cluster")
    no_camera = json.loads(data)
    del no_camera["camera"]
    no_camera = json.dumps(no_camera).encode()
    broken = data.replace(b'"x": ', b'"x": -9', 1)
    assert all(archive.parse_lane(d) == BULK for d in (data, no_camera, broken))
    assert archive.parse_lane(b"x" * archive.LARGE_UPLOAD_BYTES) is None
    pool = ComputePool(1, load_sky=False, bulk_processes=1)
    try:
        for body, defaulted in ((data, False), (no_camera, True)):
            sequence, given = pool.submit_within(archive.telemetry_job, body, "w.json", "tubsat-752x582-20deg",
                                                 1 << 20, lane=BULK).result(timeout=60)
            here = parse_telemetry(body, filename="w.json", max_bytes=1 << 20)
            assert given is defaulted
            assert sequence.camera == here.camera and len(sequence.snapshots) == 64
            assert all((a.xy == b.xy).all() and a.time == b.time for a, b in zip(sequence.snapshots, here.snapshots))
        with pytest.raises(TelemetryError) as raised:
            pool.submit_within(archive.telemetry_job, broken, "w.json", "tubsat-752x582-20deg", 1 << 20,
                               lane=BULK).result(timeout=60)
    finally:
        pool.shutdown()
    with pytest.raises(TelemetryError) as here:
        parse_telemetry(broken, filename="w.json", max_bytes=1 << 20)
    assert raised.value.to_dict() == here.value.to_dict()  # the located problems, whole, from the worker
    assert raised.value.problems[0].location.startswith("snapshots[0].sources[0].x")
    copy = pickle.loads(pickle.dumps(here.value))
    assert copy.to_dict() == here.value.to_dict() and copy.filename == "w.json"


def test_the_api_answers_large_uploads_as_before(tmp_path, sky):
    ctx = AppContext(storage=Storage.open(tmp_path / "api.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    data = worst_case_telemetry(4, "random")
    answer = client.post("/api/sequences?filename=worst.json", content=data,
                         headers={"content-type": "application/json"})
    assert answer.status_code == 201, answer.text
    doc = answer.json()
    row = ctx.storage.get_sequence(doc["id"])
    assert row.raw_text == data.decode() and row.filename == "worst.json" and row.n_snapshots == 64
    assert doc["sequence"]["sequence_id"] == "worst-random-4"
    again = client.post("/api/sequences", content=data, headers={"content-type": "application/json"})
    assert again.status_code == 200 and again.json()["id"] == doc["id"]
    broken = data.replace(b'"y": ', b'"y": "a', 1)
    refused = client.post("/api/sequences", content=broken, headers={"content-type": "application/json"})
    assert refused.status_code == 422
    with pytest.raises(TelemetryError) as here:
        parse_telemetry(broken, max_bytes=ctx.settings.max_upload_bytes)
    assert refused.json()["problems"] == [p.to_dict() for p in here.value.problems]
    ctx.close()
