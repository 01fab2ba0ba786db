"""Storage: round trips, append-only audit trail, threads, and durability across SIGKILL.

Every test that is not about one backend's own mechanics runs on both backends
(``archive_url``: a SQLite file, and a fresh database on the session's real
PostgreSQL server, tests/pg_server.py); the guards are checked through a
separate raw connection of each backend, since they live in the database.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest

from app.storage import (
    MIGRATIONS,
    StaleHotPixelMap,
    Storage,
    StorageError,
    UnknownSequence,
    VerdictExists,
    content_sha256,
)
from app.storage import postgres as pg_backend

ROOT = Path(__file__).resolve().parents[1]
T0 = datetime(2024, 5, 1, 10, 0, 0, tzinfo=timezone.utc)


@pytest.fixture
def db_path(archive_url):
    """The archive of the test: a SQLite file's path or a PostgreSQL database's URL (both backends)."""
    return archive_url


@pytest.fixture
def sqlite_path(tmp_path):
    return tmp_path / "archive.sqlite3"


@pytest.fixture
def store(db_path):
    with Storage.open(db_path) as storage:
        yield storage


class RawConnection:
    """A connection of the backend's own driver, beside the archive's: the guards live in the database.

    Takes SQL with ``?`` placeholders on both backends; ``errors`` is what the driver raises.
    """

    def __init__(self, target) -> None:
        self.postgres = str(target).startswith("postgresql://")
        if self.postgres:
            import psycopg

            self.errors = psycopg.Error
            self.conn = psycopg.connect(str(target), autocommit=True)
        else:
            self.errors = sqlite3.DatabaseError
            self.conn = sqlite3.connect(target)

    def execute(self, sql: str, params=()):
        return self.conn.execute(pg_backend.translate(sql) if self.postgres else sql, params)

    def commit(self) -> None:
        if not self.postgres:
            self.conn.commit()

    def close(self) -> None:
        self.conn.close()


def _upload(store, n, **overrides):
    kwargs = dict(raw_text=f'{{"sequence_id": "seq-{n}", "payload": {n}}}', filename=f"seq{n}.json",
                  sequence_id=f"seq-{n}", spacecraft="TUBSAT-N", camera={"name": "tubsat", "width": 752},
                  first_time=T0 + timedelta(minutes=n), n_snapshots=16,
                  extraction={"tracks": [[n, 1.5]], "pattern": {"included": [1, 2]}})
    kwargs.update(overrides)
    return store.add_sequence(**kwargs)


def _confirm(store, seq_id, search_id=None, rank=1, operator="alice", apm="APM text\n", **overrides):
    kwargs = dict(search_id=search_id, rank=rank, operator=operator, quaternion=[0.1, 0.2, 0.3, 0.927],
                  rotation_matrix=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                  ra_deg=83.6, dec_deg=22.0, roll_deg=37.0, deviation_arcsec=12.5,
                  false_match_probability=1e-9, pattern={"included": [1, 2, 3]},
                  candidate={"rank": rank, "matches": [{"hip": 26727}]}, apm_text=apm)
    kwargs.update(overrides)
    return store.add_confirmation(seq_id, **kwargs)


# -- round trips ----------------------------------------------------------------------

def test_sequence_round_trip_and_same_content_returns_existing_row(store, db_path):
    row, created = _upload(store, 1)
    assert created and row.status == "new"
    again, created_again = _upload(store, 1, filename="other-name.json")
    assert not created_again and again.id == row.id and again.filename == "seq1.json"
    assert row.content_sha256 == content_sha256(row.raw_text)
    store.close()
    with Storage.open(db_path) as reopened:
        got = reopened.get_sequence(row.id)
    assert got == row
    assert got.camera == {"name": "tubsat", "width": 752}
    assert got.first_time == T0 + timedelta(minutes=1) and got.first_time.tzinfo is not None
    assert got.extraction["tracks"] == [[1, 1.5]]


def test_unknown_ids_read_as_none_and_writes_to_them_fail(store):
    assert store.get_sequence(99) is None
    assert store.get_confirmation(99) is None
    assert store.get_search(99) is None
    assert store.current_pattern(99) is None
    assert store.latest_search(99) is None
    assert store.current_confirmation(99) is None
    with pytest.raises(UnknownSequence):
        store.add_pattern_version(99, {"included": []})
    with pytest.raises(UnknownSequence):
        store.add_search(99, pattern_version=1, method="m", options={}, result=[], status="no_match")
    with pytest.raises(UnknownSequence):
        _confirm(store, 99)
    with pytest.raises(UnknownSequence):
        store.set_status(99, "identified")


def test_list_sequences_pages_and_filters_like_a_brute_force_filter(store):
    statuses = ["new", "identified", "ambiguous", "no_match"]
    made = []
    for n in range(23):
        row, _ = _upload(store, n, spacecraft="TUBSAT-N" if n % 3 else "DLR-TUBSAT")
        store.set_status(row.id, statuses[n % 4])
        made.append((row.id, row.spacecraft, statuses[n % 4]))
    for spacecraft in (None, "TUBSAT-N", "DLR-TUBSAT", "NONE"):
        for status in (None, "identified", "confirmed"):
            expected = sorted((i for i, sc, s in made if spacecraft in (None, sc) and status in (None, s)),
                              reverse=True)
            got, total = [], None
            for offset in range(0, 30, 7):
                rows, total = store.list_sequences(offset, 7, spacecraft=spacecraft, status=status)
                got += [r.id for r in rows]
                assert all(r.raw_text is None and r.extraction is None for r in rows)
            assert got == expected and total == len(expected)


def test_bad_arguments_raise_value_error(store):
    row, _ = _upload(store, 1)
    for offset, limit in [(-1, 10), (0, 0), (0, 10_000), (0, 2.5)]:
        with pytest.raises(ValueError):
            store.list_sequences(offset, limit)
        with pytest.raises(ValueError):
            store.list_confirmations(offset, limit)
    with pytest.raises(ValueError):
        store.set_status(row.id, "done")
    with pytest.raises(ValueError):
        store.add_pattern_version(row.id, {}, kind="rewrite")
    with pytest.raises(ValueError):
        store.add_search(row.id, pattern_version=1, method="m", options={"x": float("nan")}, result=[],
                         status="new")
    assert store.latest_search(row.id) is None  # the failed write left nothing behind


# -- patterns and searches ---------------------------------------------------------------

def test_pattern_versions_are_appended_and_reset_is_a_new_version(store):
    row, _ = _upload(store, 1)
    automatic = {"excluded": [], "included": [1, 2, 3], "manual": []}
    edited = {"excluded": [2], "included": [1, 3], "manual": [{"snapshot": 0, "x": 10.5, "y": 20.25}]}
    v1 = store.add_pattern_version(row.id, automatic, kind="automatic")
    v2 = store.add_pattern_version(row.id, edited, operator="alice")
    assert store.current_pattern(row.id) == v2
    v3 = store.add_pattern_version(row.id, automatic, kind="reset", operator="bob")
    assert [v.version for v in (v1, v2, v3)] == [1, 2, 3]
    assert store.current_pattern(row.id).pattern == automatic
    assert store.current_pattern(row.id).kind == "reset"
    assert store.pattern_history(row.id) == [v1, v2, v3]  # the edit is still there, unchanged


def test_latest_search_is_the_newest(store):
    row, _ = _upload(store, 1)
    first = store.add_search(row.id, pattern_version=1, method="bright-pairs", options={"mag": 6},
                             result=[{"rank": 1}], status="identified", elapsed_s=0.12)
    second = store.add_search(row.id, pattern_version=2, method="bright-pairs", options={},
                              result=[], status="no_match", elapsed_s=0.05)
    assert store.latest_search(row.id) == second
    assert store.get_search(first.id) == first and first.result == [{"rank": 1}]


def test_a_search_and_the_status_it_gives_are_one_write(store):
    """A console read a sequence between the search's write and the status's, saw "new" beside identified
    candidates and, its polling seeing no newer search, never read it again.  The status now comes with the
    search; a verdict an operator gave stands."""
    row, _ = _upload(store, 1)
    assert row.status == "new"
    store.add_search(row.id, pattern_version=1, method="bright_pair", options={}, result=[], status="identified")
    assert store.get_sequence(row.id).status == "identified"
    store.set_status(row.id, "confirmed")
    store.add_search(row.id, pattern_version=1, method="tf", options={}, result=[], status="no_match")
    assert store.get_sequence(row.id).status == "confirmed"
    assert store.set_search_status(row.id, "ambiguous").status == "confirmed"


# -- confirmations: append-only audit trail ------------------------------------------------

def test_a_newer_confirmation_supersedes_the_older_which_is_kept_unchanged(store):
    row, _ = _upload(store, 1)
    other, _ = _upload(store, 2)
    search = store.add_search(row.id, pattern_version=1, method="m", options={}, result=[], status="ambiguous")
    first = _confirm(store, row.id, search.id, rank=2, apm="CCSDS_APM_VERS = 2.0\nfirst\n", comment="maybe")
    elsewhere = _confirm(store, other.id, operator="carol")
    second = _confirm(store, row.id, search.id, rank=1, operator="bob", apm="CCSDS_APM_VERS = 2.0\nsecond\n")
    assert store.get_sequence(row.id).status == "confirmed"
    assert store.current_confirmation(row.id) == second
    old = store.get_confirmation(first.id)
    assert old.superseded_by == second.id and not old.is_current
    # Apart from superseded_by, the old record is exactly what was stored.
    assert {**old.__dict__, "superseded_by": None} == first.__dict__
    assert old.apm_text == "CCSDS_APM_VERS = 2.0\nfirst\n"
    assert store.get_confirmation(elsewhere.id).is_current  # another sequence is untouched
    assert [c.id for c in store.confirmation_history(row.id)] == [first.id, second.id]
    rows, total = store.list_confirmations(0, 2)
    assert total == 3 and [c.id for c in rows] == [second.id, elsewhere.id]
    assert [c.id for c in store.list_confirmations(2, 2)[0]] == [first.id]


def test_the_schema_refuses_edits_and_deletes_of_the_audit_trail(store, db_path):
    row, _ = _upload(store, 1)
    store.add_pattern_version(row.id, {"included": [1]})
    store.add_search(row.id, pattern_version=1, method="m", options={}, result=[], status="no_match")
    first = _confirm(store, row.id)
    second = _confirm(store, row.id)
    raw = RawConnection(db_path)  # a separate connection: the guard lives in the database
    forbidden = [
        ("UPDATE confirmations SET apm_text = 'forged' WHERE id = ?", (first.id,)),
        ("UPDATE confirmations SET operator = 'mallory' WHERE id = ?", (second.id,)),
        ("UPDATE confirmations SET superseded_by = NULL WHERE id = ?", (first.id,)),
        ("UPDATE confirmations SET superseded_by = ? WHERE id = ?", (first.id, second.id)),
        # The one permitted change (superseded_by NULL -> newer id) cannot carry a content change.
        ("UPDATE confirmations SET superseded_by = 999, apm_text = 'forged' WHERE id = ?", (second.id,)),
        ("UPDATE confirmations SET superseded_by = 999, ra_deg = 1.0 WHERE id = ?", (second.id,)),
        ("DELETE FROM confirmations WHERE id = ?", (first.id,)),
        ("UPDATE pattern_versions SET pattern_json = '{}' WHERE seq_id = ?", (row.id,)),
        ("DELETE FROM searches WHERE seq_id = ?", (row.id,)),
        ("UPDATE sequences SET raw_text = 'changed' WHERE id = ?", (row.id,)),
        ("DELETE FROM sequences WHERE id = ?", (row.id,)),
    ]
    if raw.postgres:  # PostgreSQL's TRUNCATE skips row triggers: statement triggers refuse it
        forbidden += [(f"TRUNCATE {table} CASCADE", ()) for table in
                      ("confirmations", "searches", "pattern_versions", "sequences", "calibrations", "rejections")]
    for sql, params in forbidden:
        with pytest.raises(raw.errors, match="append-only|never"):
            raw.execute(sql, params)
    raw.execute("UPDATE sequences SET status = 'identified' WHERE id = ?", (row.id,))  # allowed
    raw.commit()
    raw.close()
    assert store.get_confirmation(first.id).apm_text == "APM text\n"
    assert store.get_sequence(row.id).status == "identified"


# -- opening, schema versions, health --------------------------------------------------------

def test_open_sets_wal_full_sync_foreign_keys_and_schema_version(sqlite_path):
    store = Storage.open(sqlite_path)
    db_path = sqlite_path
    health = store.health()
    assert health["ok"] and health["journal_mode"] == "wal"
    assert health["schema_version"] == len(MIGRATIONS)
    assert health["counts"] == {"sequences": 0, "pattern_versions": 0, "searches": 0, "confirmations": 0,
                                "calibrations": 0}
    conn = store._conn
    assert conn.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
    assert conn.execute("PRAGMA foreign_keys").fetchone()[0] == 1
    raw = sqlite3.connect(db_path)
    assert raw.execute("PRAGMA journal_mode").fetchone()[0] == "wal"  # persistent in the file
    assert raw.execute("SELECT version FROM schema_version").fetchall() == [(v,) for v in range(1, len(MIGRATIONS) + 1)]
    raw.close()
    store.close()


def test_reopening_does_not_migrate_twice_and_a_newer_schema_is_refused(db_path):
    with Storage.open(db_path if str(db_path).startswith("postgresql://") else f"sqlite:///{db_path}") as storage:
        _upload(storage, 1)
    with Storage.open(db_path) as storage:
        assert storage.health()["counts"]["sequences"] == 1
    raw = RawConnection(db_path)
    assert raw.execute("SELECT COUNT(*) FROM schema_version").fetchone()[0] == len(MIGRATIONS)
    raw.execute("INSERT INTO schema_version VALUES (?, '2099-01-01T00:00:00+00:00')", (len(MIGRATIONS) + 1,))
    raw.commit()
    raw.close()
    with pytest.raises(StorageError, match="newer"):
        Storage.open(db_path)


def test_database_url_from_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("DATABASE_URL", str(tmp_path / "env.sqlite3"))
    with Storage.open() as storage:
        assert storage.path == str(tmp_path / "env.sqlite3")
    assert (tmp_path / "env.sqlite3").exists()


def test_postgres_url_from_environment_selects_the_postgres_backend(postgres_url, monkeypatch):
    monkeypatch.setenv("DATABASE_URL", postgres_url)
    with Storage.open() as storage:
        assert storage.backend == "postgresql" and storage.path == postgres_url
        health = storage.health()
    assert health["ok"] and health["backend"] == "postgresql" and health["schema_version"] == len(MIGRATIONS)
    assert health["synchronous_commit"] == "on" and health["database"] == postgres_url.rsplit("/", 1)[1]
    assert len(pg_backend.MIGRATIONS) == len(MIGRATIONS)  # the same versions on both backends


# Port 1 on loopback: nothing listens there, the connection is refused at once.
@pytest.mark.parametrize("target", ["postgresql://user@127.0.0.1:1/db", "postgresql://user:secret@127.0.0.1:1/db",
                                    "mysql://x", ":memory:", ""])
def test_unsupported_targets_are_refused(target):
    with pytest.raises(StorageError) as refused:
        Storage.open(target)
    assert "secret" not in str(refused.value)  # a password never reaches a message or a log


def test_a_file_that_is_not_a_database_is_refused(tmp_path):
    path = tmp_path / "junk.sqlite3"
    path.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(StorageError, match="not a usable database"):
        Storage.open(path)


def test_closed_storage_refuses_work(db_path):
    storage = Storage.open(db_path)
    storage.close()
    storage.close()  # idempotent
    with pytest.raises(StorageError, match="closed"):
        storage.get_sequence(1)


# -- threads -----------------------------------------------------------------------------------

def test_concurrent_writers_keep_numbering_and_supersession_consistent(store):
    sequences = [_upload(store, n)[0].id for n in range(3)]
    n_threads, per_thread = 8, 6
    errors, created_flags = [], []
    start = threading.Barrier(n_threads)

    def work(worker):
        try:
            start.wait()
            # Everyone uploads the same content too: exactly one must create it.
            created_flags.append(_upload(store, 1000)[1])
            for k in range(per_thread):
                seq_id = sequences[(worker + k) % len(sequences)]
                store.add_pattern_version(seq_id, {"worker": worker, "k": k}, operator=f"w{worker}")
                search = store.add_search(seq_id, pattern_version=None, method="m",
                                          options={"worker": worker}, result=[{"rank": 1}], status="identified")
                _confirm(store, seq_id, search.id, operator=f"w{worker}")
                store.list_sequences(0, 10)
                store.current_confirmation(seq_id)
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(w,)) for w in range(n_threads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert sorted(created_flags) == [False] * (n_threads - 1) + [True]
    total_per_seq = {s: 0 for s in sequences}
    for w in range(n_threads):
        for k in range(per_thread):
            total_per_seq[sequences[(w + k) % len(sequences)]] += 1
    for seq_id, expected in total_per_seq.items():
        assert [v.version for v in store.pattern_history(seq_id)] == list(range(1, expected + 1))
        history = store.confirmation_history(seq_id)
        assert len(history) == expected
        # A single chain: each record superseded by the next one, only the last is current.
        assert [c.superseded_by for c in history] == [c.id for c in history[1:]] + [None]
    assert store.health()["counts"]["confirmations"] == n_threads * per_thread


# -- durability ----------------------------------------------------------------------------------

WRITER = r"""
import sys
from app.storage import Storage
store = Storage.open(sys.argv[1])
i = 0
while True:
    text = f"telemetry {i} " + "x" * (i % 97)
    row, _ = store.add_sequence(raw_text=text, sequence_id=f"s{i}", spacecraft="TUBSAT-N")
    conf = store.add_confirmation(row.id, search_id=None, rank=1, operator="op", quaternion=[0, 0, 0, 1],
                                  rotation_matrix=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], ra_deg=i, dec_deg=0,
                                  roll_deg=0, deviation_arcsec=None, false_match_probability=None,
                                  pattern={}, candidate={"i": i}, apm_text=f"APM {i}\n")
    print(i, row.id, conf.id, flush=True)  # acknowledged: both commits have returned
    i += 1
"""


def test_acknowledged_rows_survive_sigkill(db_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    child = subprocess.Popen([sys.executable, "-c", WRITER, str(db_path)], stdout=subprocess.PIPE,
                             text=True, env=env, cwd=ROOT)
    acknowledged = []
    deadline = time.monotonic() + 30
    try:
        while len(acknowledged) < 40 and time.monotonic() < deadline:
            line = child.stdout.readline()
            if not line:
                break
            acknowledged.append(tuple(int(v) for v in line.split()))
    finally:
        child.send_signal(signal.SIGKILL)  # mid-write, most likely
        child.wait(timeout=10)
    assert child.returncode == -signal.SIGKILL
    assert len(acknowledged) >= 40, "writer did not acknowledge rows in time"
    with Storage.open(db_path) as reopened:
        for i, seq_id, conf_id in acknowledged:
            row = reopened.get_sequence(seq_id)
            assert row is not None and row.raw_text == f"telemetry {i} " + "x" * (i % 97)
            conf = reopened.get_confirmation(conf_id)
            assert conf is not None and conf.apm_text == f"APM {i}\n" and conf.candidate == {"i": i}
        assert reopened.health()["ok"]
    if not str(db_path).startswith("postgresql://"):
        raw = sqlite3.connect(db_path)
        assert raw.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        raw.close()


def test_calibrations_are_versioned_per_spacecraft_append_only_and_survive_a_reopen(db_path):
    with Storage.open(db_path) as store:
        first = store.add_calibration("SAT-A", camera={"focal_length_px": 2100.0}, result={"stars_used": 10},
                                      sequences=[1, 2], operator="ana")
        store.add_calibration("SAT-B", camera={"focal_length_px": 1000.0}, result={}, sequences=[3])
        second = store.add_calibration("SAT-A", camera={"focal_length_px": 2101.5}, result={}, sequences=[4])
        assert (first.version, second.version) == (1, 2)
    with Storage.open(db_path) as store:
        assert store.current_calibration("SAT-A").camera == {"focal_length_px": 2101.5}
        assert [c.version for c in store.calibration_history("SAT-A")] == [1, 2]
        assert store.calibration_history("SAT-A")[0].operator == "ana"
        assert store.current_calibration("SAT-C") is None and store.current_calibration(None) is None
    raw = RawConnection(db_path)
    for statement in ("UPDATE calibrations SET camera_json = '{}'", "DELETE FROM calibrations"):
        with pytest.raises(raw.errors, match="append-only"):
            raw.execute(statement)
    raw.close()


# -- the rest of the interface, on both backends ---------------------------------------------------

def test_verdicts_rejections_and_confirmations_replace_each_other_in_one_chain(store):
    row, _ = _upload(store, 1)
    first = _confirm(store, row.id, acm_text="CCSDS_ACM_VERS = 2.0\n")
    assert first.acm_text == "CCSDS_ACM_VERS = 2.0\n" and store.current_verdict(row.id) == first
    with pytest.raises(VerdictExists) as exists:
        store.add_rejection(row.id, operator="bob", reason="ghosts")
    assert exists.value.current == first
    rejection = store.add_rejection(row.id, operator="bob", reason="ghosts", supersede=True)
    assert rejection.replaces_confirmation == first.id and store.get_sequence(row.id).status == "rejected"
    assert store.current_confirmation(row.id) is None and store.get_confirmation(first.id).withdrawn_by == rejection.id
    second = _confirm(store, row.id, operator="carol", supersede=True)
    assert second.replaces_rejection == rejection.id and store.current_verdict(row.id) == second
    assert store.get_rejection(rejection.id).replaced_by_confirmation == second.id
    # The withdrawn confirmation is not superseded by the new one: it stays as the rejection left it.
    assert store.get_confirmation(first.id).superseded_by is None
    assert [r.id for r in store.rejection_history(row.id)] == [rejection.id]
    for operator, reason in (("", "why"), ("ann", " ")):
        with pytest.raises(ValueError):
            store.add_rejection(row.id, operator=operator, reason=reason, supersede=True)


def test_search_orders_spacecraft_and_time_ranges(store):
    made = []
    for n, (spacecraft, sequence_id) in enumerate([("SAT-B", "Alpha-1"), (None, "beta_2"), ("SAT-A", "ALPHA-3"),
                                                   ("SAT-B", "gamma%4")]):
        made.append(_upload(store, n, spacecraft=spacecraft, sequence_id=sequence_id)[0])
    found = lambda text: [r.id for r in store.list_sequences(0, 10, search=text)[0]]  # noqa: E731
    assert found("alpha") == [made[2].id, made[0].id]  # case-insensitive, newest first
    assert found("%") == [made[3].id] and found("_") == [made[1].id]  # LIKE wildcards are literal
    assert found(f"#{made[1].id}") == [made[1].id]
    oldest = [r.id for r in store.list_sequences(0, 10, order="oldest")[0]]
    assert oldest == [r.id for r in made]
    assert [r.id for r in store.list_sequences(0, 10, order="time_asc")[0]] == oldest  # first_time grows with n
    assert store.spacecraft_names() == [("SAT-A", 1), ("SAT-B", 2), (None, 1)]
    for row in made:
        _confirm(store, row.id, epoch=T0 + timedelta(hours=row.id), rate_deg_s=[0.1, 0.2, 0.3])
    assert store.latest_confirmation_of_spacecraft(None).seq_id == made[1].id  # the unnamed spacecraft's
    assert store.latest_confirmation_of_spacecraft("SAT-B").seq_id == made[3].id
    in_range = store.current_confirmations("SAT-B", T0 + timedelta(hours=made[0].id),
                                           T0 + timedelta(hours=made[3].id))
    assert [c.seq_id for c in in_range] == [made[0].id]  # [start, end)
    assert [c.seq_id for c in store.current_confirmations("SAT-B")] == [made[0].id, made[3].id]
    assert store.get_confirmation(in_range[0].id).rate_deg_s == [0.1, 0.2, 0.3]


def test_hot_pixel_maps_and_frame_uploads(store):
    row, _ = _upload(store, 1)
    first = store.add_hot_pixel_map("SAT", "752x582", map_doc={"pixels": [[1, 2]]}, frames=4, hot_pixels=1,
                                    based_on=None, seq_id=row.id)
    with pytest.raises(StaleHotPixelMap):  # computed from nothing, but version 1 exists meanwhile
        store.add_hot_pixel_map("SAT", "752x582", map_doc={}, frames=1, hot_pixels=0, based_on=None)
    second = store.add_hot_pixel_map("SAT", "752x582", map_doc={"pixels": []}, frames=8, hot_pixels=0, based_on=1)
    assert (first.version, second.version) == (1, 2) and store.current_hot_pixel_map("SAT", "752x582") == second
    assert store.hot_pixel_map_history("SAT", "752x582") == [first, second]
    assert store.current_hot_pixel_map(None, "752x582") is None
    assert store.add_frame_upload("abc", row.id) == row.id
    other, _ = _upload(store, 2)
    assert store.add_frame_upload("abc", other.id) == row.id  # the first recorded stays
    assert store.find_frame_upload("abc") == row.id and store.find_frame_upload("nope") is None
