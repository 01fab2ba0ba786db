"""The PostgreSQL archive shared by several processes (issue 14): what several servers on several machines
writing at once must get right, checked with real processes on the session's PostgreSQL server.

* pattern versions numbered without gaps or duplicates, one supersession chain of confirmations, the same
  upload stored once, every acknowledged write there exactly once (4 writer processes at once);
* two verdicts without ``supersede`` at once: exactly one wins, the other sees it;
* servers starting together apply each migration once (the advisory lock);
* a writer really waits for the sequence's row lock (seen in ``pg_stat_activity``, not guessed by time).

The processes start together on a line on their standard input, after each has opened the archive.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import psycopg
import pytest

from app.storage import MIGRATIONS, Storage
from app.storage import postgres as pg_backend

ROOT = Path(__file__).resolve().parents[1]
PROCESS_TIMEOUT_S = 120

WRITER = r"""
import json, sys
from app.storage import Storage, VerdictExists
url, worker, rounds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
sequences = json.loads(sys.argv[4])
store = Storage.open(url)
print("ready", flush=True)
sys.stdin.readline()
def ack(**kw):
    print(json.dumps(kw), flush=True)
for k in range(rounds):
    row, created = store.add_sequence(raw_text=f"shared upload {k}", sequence_id=f"shared-{k}")
    ack(op="upload", round=k, id=row.id, created=created)
    seq = sequences[(worker + k) % len(sequences)]
    v = store.add_pattern_version(seq, {"worker": worker, "k": k}, operator=f"w{worker}")
    ack(op="pattern", seq=seq, id=v.id, version=v.version)
    s = store.add_search(seq, pattern_version=v.version, method="m", options={"w": worker}, result=[], status="identified")
    ack(op="search", seq=seq, id=s.id)
    c = store.add_confirmation(seq, search_id=s.id, rank=1, operator=f"w{worker}", quaternion=[0, 0, 0, 1],
                               rotation_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], ra_deg=k, dec_deg=0, roll_deg=0,
                               deviation_arcsec=None, false_match_probability=None, pattern={}, candidate={"k": k},
                               apm_text=f"APM {worker} {k}\n", supersede=True)
    ack(op="confirm", seq=seq, id=c.id)
store.close()
"""

VERDICT = r"""
import json, sys
from app.storage import Storage, VerdictExists
url, worker = sys.argv[1], int(sys.argv[2])
sequences = json.loads(sys.argv[3])
store = Storage.open(url)
print("ready", flush=True)
sys.stdin.readline()
for seq in sequences:
    try:
        if worker % 2:
            c = store.add_rejection(seq, operator=f"w{worker}", reason="every candidate is wrong", supersede=False)
            kind = "rejection"
        else:
            c = store.add_confirmation(seq, search_id=None, rank=1, operator=f"w{worker}", quaternion=[0, 0, 0, 1],
                                       rotation_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], ra_deg=1, dec_deg=0,
                                       roll_deg=0, deviation_arcsec=None, false_match_probability=None, pattern={},
                                       candidate={}, apm_text="APM\n", supersede=False)
            kind = "confirmation"
        print(json.dumps({"seq": seq, "won": kind, "id": c.id}), flush=True)
    except VerdictExists as exc:
        print(json.dumps({"seq": seq, "lost_to": exc.current.id}), flush=True)
store.close()
"""

OPENER = r"""
import sys
from app.storage import Storage
url = sys.argv[1]
print("ready", flush=True)
sys.stdin.readline()
with Storage.open(url) as store:
    print(store.health()["schema_version"], flush=True)
"""


def _run_together(script: str, argv_per_process: list[list[str]]) -> list[list[str]]:
    """Start one process per argv, let them all go at once (after each said "ready"), return their output lines."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    processes = [subprocess.Popen([sys.executable, "-c", script, *argv], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT) for argv in argv_per_process]
    try:
        for p in processes:
            assert p.stdout.readline().strip() == "ready", p.stderr.read()[-3000:]
        for p in processes:
            p.stdin.write("go\n")
            p.stdin.flush()
        outputs = []
        for p in processes:
            out, err = p.communicate(timeout=PROCESS_TIMEOUT_S)
            assert p.returncode == 0, err[-3000:]
            outputs.append(out.splitlines())
        return outputs
    finally:
        for p in processes:
            if p.poll() is None:
                p.kill()
                p.wait()


def _seed_sequences(url: str, n: int) -> list[int]:
    with Storage.open(url) as store:
        return [store.add_sequence(raw_text=f"sequence {i}", sequence_id=f"s{i}")[0].id for i in range(n)]


def test_writers_in_several_processes_keep_numbering_supersession_and_uploads_exact(postgres_url):
    sequences = _seed_sequences(postgres_url, 3)
    workers, rounds = 4, 12
    outputs = _run_together(WRITER, [[postgres_url, str(w), str(rounds), json.dumps(sequences)] for w in range(workers)])
    acks = [json.loads(line) for lines in outputs for line in lines]
    assert len(acks) == workers * rounds * 4

    with Storage.open(postgres_url) as store:
        # The same upload from every process at once: stored once, every process got its row.
        for k in range(rounds):
            mine = [a for a in acks if a["op"] == "upload" and a["round"] == k]
            assert sorted(a["created"] for a in mine) == [False] * (workers - 1) + [True]
            assert len({a["id"] for a in mine}) == 1
            assert store.get_sequence(mine[0]["id"]).raw_text == f"shared upload {k}"
        assert store.health()["counts"]["sequences"] == len(sequences) + rounds

        for seq in sequences:
            history = store.pattern_history(seq)
            acked = sorted((a["version"], a["id"]) for a in acks if a["op"] == "pattern" and a["seq"] == seq)
            # Numbered 1..n without gap or duplicate, and every acknowledged version is exactly there.
            assert [v.version for v in history] == list(range(1, len(acked) + 1))
            assert [(v.version, v.id) for v in history] == acked
            confirmations = store.confirmation_history(seq)
            acked_ids = sorted(a["id"] for a in acks if a["op"] == "confirm" and a["seq"] == seq)
            assert [c.id for c in confirmations] == acked_ids
            # One chain: each superseded by the next, only the newest current.
            assert [c.superseded_by for c in confirmations] == [c.id for c in confirmations[1:]] + [None]
            assert store.current_confirmation(seq).id == acked_ids[-1]
            searches = sorted(a["id"] for a in acks if a["op"] == "search" and a["seq"] == seq)
            assert all(store.get_search(i) is not None for i in searches)
            assert store.latest_search(seq).id == searches[-1]
        assert store.health()["counts"]["confirmations"] == workers * rounds


def test_two_verdicts_without_supersede_at_once_one_wins_the_other_sees_it(postgres_url):
    sequences = _seed_sequences(postgres_url, 25)
    outputs = _run_together(VERDICT, [[postgres_url, str(w), json.dumps(sequences)] for w in range(4)])
    results = [json.loads(line) for lines in outputs for line in lines]
    with Storage.open(postgres_url) as store:
        for seq in sequences:
            mine = [r for r in results if r["seq"] == seq]
            winners = [r for r in mine if "won" in r]
            assert len(mine) == 4 and len(winners) == 1, mine
            winner = winners[0]
            # Every loser was told of the winner's record, which is the sequence's verdict.
            assert all(r["lost_to"] == winner["id"] for r in mine if r is not winner)
            verdict = store.current_verdict(seq)
            assert verdict.id == winner["id"] and type(verdict).__name__.lower().startswith(winner["won"])
            assert store.get_sequence(seq).status == ("confirmed" if winner["won"] == "confirmation" else "rejected")
            assert len(store.confirmation_history(seq)) + len(store.rejection_history(seq)) == 1


def test_servers_starting_together_apply_each_migration_once(postgres_url):
    outputs = _run_together(OPENER, [[postgres_url] for _ in range(5)])
    assert [lines for lines in outputs] == [[str(len(MIGRATIONS))]] * 5
    with psycopg.connect(postgres_url) as conn:
        versions = [v for (v,) in conn.execute("SELECT version FROM schema_version ORDER BY version")]
    assert versions == list(range(1, len(pg_backend.MIGRATIONS) + 1))


def test_a_writer_waits_for_the_sequence_lock_of_another_server(postgres_url):
    (seq,) = _seed_sequences(postgres_url, 1)
    first, second = Storage.open(postgres_url), Storage.open(postgres_url)
    done = threading.Event()
    errors = []
    try:
        with first._transaction() as conn:
            first._lock_sequence(conn, seq)  # "another server" in the middle of numbering a version
            conn.execute("INSERT INTO pattern_versions (seq_id, version, kind, pattern_json, created_at) "
                         "VALUES (?, 1, 'edit', '{}', now())", (seq,))

            def write():
                try:
                    second.add_pattern_version(seq, {"second": True})
                except Exception as exc:  # noqa: BLE001 - reported below
                    errors.append(exc)
                done.set()

            thread = threading.Thread(target=write)
            thread.start()
            # Wait until PostgreSQL shows the second writer blocked on a lock (a state, polled).
            with psycopg.connect(postgres_url, autocommit=True) as watcher:
                deadline = time.monotonic() + 30
                while not watcher.execute(
                        "SELECT count(*) FROM pg_stat_activity WHERE datname = current_database() "
                        "AND wait_event_type = 'Lock' AND query LIKE '%FOR NO KEY UPDATE%'").fetchone()[0]:
                    assert time.monotonic() < deadline, "the second writer never waited for the lock"
                    assert not done.is_set(), "the second writer did not wait for the first"
                    time.sleep(0.01)
            assert not done.is_set()
        thread.join(timeout=30)
        assert done.is_set() and errors == []
        # It numbered after the first writer's version, not beside it.
        assert [(v.version, v.pattern) for v in first.pattern_history(seq)] == [(1, {}), (2, {"second": True})]
    finally:
        first.close()
        second.close()


def test_health_and_errors_of_an_unreachable_archive(postgres, postgres_url):
    store = Storage.open(postgres_url)
    try:
        health = store.health()
        assert health["ok"] and health["backend"] == "postgresql" and health["pool"]["max"] >= 1
        # A database dropped under a running server: methods raise StorageError (the API's 503), health says why.
        store.close()
        with pytest.raises(Exception, match="closed"):
            store.get_sequence(1)
    finally:
        store.close()
    with pytest.raises(Exception, match="does not exist"):
        Storage.open(postgres.url("no_such_database"))


def test_values_postgres_cannot_store_are_refused_as_value_errors(postgres_url):
    with Storage.open(postgres_url) as store:
        row, _ = store.add_sequence(raw_text="telemetry")
        with pytest.raises(ValueError, match="cannot store"):
            store.add_pattern_version(row.id, {"note": "a\u0000b"}, operator="ann")
        with pytest.raises(ValueError, match="cannot store"):
            store.add_sequence(raw_text="nul \x00 inside")
        assert [v.version for v in store.pattern_history(row.id)] == []  # nothing half-written
        assert store.add_pattern_version(row.id, {"note": "fine"}).version == 1


def test_a_restarted_database_server_costs_no_request_after_an_idle_pause(postgres, postgres_url, monkeypatch):
    """Pooled connections cut by a restart: one idle for CHECK_AFTER_IDLE_S is checked (and replaced) before
    use; without the check (a busy server's connection), the request gets StorageError once and the next
    one a fresh connection."""
    with Storage.open(postgres_url) as store:
        row, _ = store.add_sequence(raw_text="before the restart")
        monkeypatch.setattr(pg_backend, "CHECK_AFTER_IDLE_S", 0.0)  # every connection counts as idle
        postgres.restart()
        assert store.get_sequence(row.id).raw_text == "before the restart"
        assert store.add_pattern_version(row.id, {"after": 1}).version == 1
        monkeypatch.setattr(pg_backend, "CHECK_AFTER_IDLE_S", 1e9)  # never checked
        postgres.restart()
        outcomes = []
        for _ in range(store._pool.max_size + 1):
            try:
                outcomes.append(store.current_pattern(row.id).version)
            except Exception as exc:  # noqa: BLE001 - the point of the test
                assert type(exc).__name__ == "StorageError", exc
                outcomes.append("unavailable")
        assert outcomes[-1] == 1 and "unavailable" in outcomes
        assert store.health()["ok"]
