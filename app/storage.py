"""Durable storage: every upload, pattern edit, search and confirmation.

All persistence of the ground station goes through :class:`Storage`.  The
backend is SQLite in WAL mode (``journal_mode=WAL``, ``synchronous=FULL``,
``foreign_keys=ON``): with ``synchronous=FULL`` a commit returns only after
the WAL has been fsync'ed, so anything a method has returned survives a
SIGKILL or a power cut.

Records
-------
* ``sequences`` - one row per distinct upload (``content_sha256`` is unique;
  the same bytes uploaded twice return the existing row).  The original
  telemetry text is kept verbatim so nothing is ever lost.  ``status`` is the
  only column that changes (``new`` -> ``identified``/``ambiguous``/
  ``no_match`` -> ``confirmed``).
* ``pattern_versions`` - append-only, numbered 1, 2, ... per sequence; the
  current pattern is the highest version.  ``kind`` says where it came from:
  ``automatic`` (extraction), ``edit`` (operator) or ``reset`` (the automatic
  pattern again, as a new version: history is never rewritten).
* ``searches`` - append-only results of identification runs.
* ``calibrations`` - append-only, numbered 1, 2, ... per spacecraft: a camera
  fitted over many identified sequences (who, when, from which sequences);
  an upload without a camera block is given the current one
  (``sequences.camera_calibration`` says which).
* ``confirmations`` - append-only audit records of confirmed attitudes,
  including the APM text rendered once at confirmation so that its export is
  byte-for-byte stable.  A newer confirmation of the same sequence sets
  ``superseded_by`` on the older ones, in the same transaction; that is the
  only UPDATE ever made to this table, and triggers in the schema refuse any
  other UPDATE or any DELETE on the append-only tables.

Threads
-------
One connection guarded by a lock: methods may be called from any thread (the
FastAPI thread pool).  SQLite serialises writers anyway; the lock also makes
each method one atomic transaction without SQLITE_BUSY retries.

Schema versions
---------------
``schema_version`` holds the versions applied; :data:`MIGRATIONS` lists the
SQL of each version in order and :meth:`Storage.open` applies the missing ones
in one transaction.  A database newer than this code is refused.

PostgreSQL
----------
The interface takes and returns plain Python values and the SQL is plain
(``INSERT ... ON CONFLICT DO NOTHING``, ``COUNT``, ``ORDER BY``/``LIMIT``/
``OFFSET``), so a PostgreSQL backend selected by ``DATABASE_URL=postgresql://``
could serve the same methods.  It would change: ``?`` placeholders to ``%s``;
``INTEGER PRIMARY KEY`` to ``BIGINT GENERATED ALWAYS AS IDENTITY`` and
``lastrowid`` to ``RETURNING id``; TEXT timestamps to ``TIMESTAMPTZ`` and TEXT
JSON to ``JSONB``; the guard triggers to PL/pgSQL functions; the process lock
to a connection pool, with ``SELECT ... FOR UPDATE`` on the sequence row when
numbering pattern versions and superseding confirmations (several servers
then share one archive); no PRAGMAs.  :meth:`Storage.open` raises
:class:`StorageError` for such URLs today.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import sqlite3
import threading
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

#: Allowed values of ``sequences.status``.
STATUSES = ("new", "identified", "ambiguous", "no_match", "confirmed")
#: Allowed values of ``pattern_versions.kind``.
PATTERN_KINDS = ("automatic", "edit", "reset")
#: Largest page :meth:`Storage.list_sequences` and :meth:`Storage.list_confirmations` return.
MAX_PAGE = 1000
#: Environment variable naming the database (a path, ``sqlite:///path`` or, later, ``postgresql://``).
DATABASE_URL_ENV = "DATABASE_URL"


class StorageError(RuntimeError):
    """The database cannot be opened or used as asked (bad URL, newer schema, ...)."""


class UnknownSequence(StorageError, LookupError):
    """A write refers to a sequence id that does not exist."""


# ---------------------------------------------------------------------------
# Schema
# ---------------------------------------------------------------------------

def _confirmations_only_supersede(extra_columns: tuple[str, ...] = ()) -> str:
    """The guard that lets only ``superseded_by`` change, once, from NULL to a newer record of the same
    sequence; every other column (``extra_columns``: those added by later migrations) is frozen."""
    columns = ("id", "seq_id", "search_id", "rank", "operator", "confirmed_at", "comment", "quaternion_json",
               "rotation_matrix_json", "ra_deg", "dec_deg", "roll_deg", "deviation_arcsec",
               "false_match_probability", "pattern_json", "candidate_json", "apm_text", "aem_text", *extra_columns)
    frozen = " OR ".join(f"NEW.{c} IS NOT OLD.{c}" for c in columns)
    return f"""CREATE TRIGGER confirmations_only_supersede BEFORE UPDATE ON confirmations
        WHEN OLD.superseded_by IS NOT NULL OR NEW.superseded_by IS NULL OR NEW.superseded_by <= OLD.id
          OR {frozen}
        BEGIN SELECT RAISE(ABORT, 'confirmations are append-only'); END"""


_APPEND_ONLY_GUARDS = [
    f"""CREATE TRIGGER {table}_no_delete BEFORE DELETE ON {table}
        BEGIN SELECT RAISE(ABORT, '{table} is append-only'); END"""
    for table in ("pattern_versions", "searches", "confirmations")
] + [
    f"""CREATE TRIGGER {table}_no_update BEFORE UPDATE ON {table}
        BEGIN SELECT RAISE(ABORT, '{table} is append-only'); END"""
    for table in ("pattern_versions", "searches")
] + [
    _confirmations_only_supersede(),
    """CREATE TRIGGER sequences_keep_content BEFORE UPDATE ON sequences
        WHEN NEW.id IS NOT OLD.id OR NEW.content_sha256 IS NOT OLD.content_sha256
          OR NEW.raw_text IS NOT OLD.raw_text OR NEW.uploaded_at IS NOT OLD.uploaded_at
        BEGIN SELECT RAISE(ABORT, 'an upload is never changed'); END""",
    """CREATE TRIGGER sequences_no_delete BEFORE DELETE ON sequences
        BEGIN SELECT RAISE(ABORT, 'uploads are never deleted'); END""",
]

#: Version n of the schema is reached by running ``MIGRATIONS[n - 1]`` on version n - 1.
MIGRATIONS: list[list[str]] = [
    [
        """CREATE TABLE sequences (
            id INTEGER PRIMARY KEY,
            content_sha256 TEXT NOT NULL UNIQUE,
            filename TEXT,
            sequence_id TEXT,
            spacecraft TEXT,
            camera_json TEXT,
            first_time TEXT,
            n_snapshots INTEGER,
            raw_text TEXT NOT NULL,
            uploaded_at TEXT NOT NULL,
            extraction_json TEXT,
            status TEXT NOT NULL DEFAULT 'new'
                CHECK (status IN ('new', 'identified', 'ambiguous', 'no_match', 'confirmed'))
        )""",
        "CREATE INDEX sequences_spacecraft ON sequences (spacecraft)",
        "CREATE INDEX sequences_status ON sequences (status)",
        """CREATE TABLE pattern_versions (
            id INTEGER PRIMARY KEY,
            seq_id INTEGER NOT NULL REFERENCES sequences (id),
            version INTEGER NOT NULL,
            kind TEXT NOT NULL CHECK (kind IN ('automatic', 'edit', 'reset')),
            pattern_json TEXT NOT NULL,
            operator TEXT,
            created_at TEXT NOT NULL,
            UNIQUE (seq_id, version)
        )""",
        """CREATE TABLE searches (
            id INTEGER PRIMARY KEY,
            seq_id INTEGER NOT NULL REFERENCES sequences (id),
            pattern_version INTEGER,
            method TEXT NOT NULL,
            options_json TEXT NOT NULL,
            result_json TEXT NOT NULL,
            status TEXT NOT NULL,
            created_at TEXT NOT NULL,
            elapsed_s REAL
        )""",
        "CREATE INDEX searches_seq ON searches (seq_id, id)",
        """CREATE TABLE confirmations (
            id INTEGER PRIMARY KEY,
            seq_id INTEGER NOT NULL REFERENCES sequences (id),
            search_id INTEGER REFERENCES searches (id),
            rank INTEGER NOT NULL,
            operator TEXT NOT NULL,
            confirmed_at TEXT NOT NULL,
            comment TEXT,
            quaternion_json TEXT NOT NULL,
            rotation_matrix_json TEXT NOT NULL,
            ra_deg REAL NOT NULL,
            dec_deg REAL NOT NULL,
            roll_deg REAL NOT NULL,
            deviation_arcsec REAL,
            false_match_probability REAL,
            pattern_json TEXT NOT NULL,
            candidate_json TEXT NOT NULL,
            apm_text TEXT NOT NULL,
            aem_text TEXT,
            superseded_by INTEGER REFERENCES confirmations (id)
        )""",
        "CREATE INDEX confirmations_seq ON confirmations (seq_id, id)",
        *_APPEND_ONLY_GUARDS,
    ],
    # 2: a confirmation's epoch and fitted body rate as columns (they were only inside the APM text and
    # the candidate); the stored extraction of an upload becomes immutable (it is authoritative: pattern
    # versions refer to its track ids).
    [
        "ALTER TABLE confirmations ADD COLUMN epoch TEXT",
        "ALTER TABLE confirmations ADD COLUMN rate_deg_s_json TEXT",
        "DROP TRIGGER confirmations_only_supersede",
        # The APM's "EPOCH = 2024-01-01T00:00:00.000000" line, as the archive's fixed-width UTC text.
        """UPDATE confirmations SET
             epoch = substr(apm_text, instr(apm_text, char(10) || 'EPOCH = ') + 9, 26) || '+00:00',
             rate_deg_s_json = json_extract(candidate_json, '$.sequence_fit.rate_deg_s')""",
        _confirmations_only_supersede(("epoch", "rate_deg_s_json")),
        "CREATE INDEX confirmations_current ON confirmations (seq_id) WHERE superseded_by IS NULL",
        "DROP TRIGGER sequences_keep_content",
        """CREATE TRIGGER sequences_keep_content BEFORE UPDATE ON sequences
            WHEN NEW.id IS NOT OLD.id OR NEW.content_sha256 IS NOT OLD.content_sha256
              OR NEW.raw_text IS NOT OLD.raw_text OR NEW.uploaded_at IS NOT OLD.uploaded_at
              OR NEW.extraction_json IS NOT OLD.extraction_json
            BEGIN SELECT RAISE(ABORT, 'an upload is never changed'); END""",
    ],
    # 3: camera calibrations of a spacecraft, versioned and append-only; an upload records the
    # calibration whose camera it was given (its file had no camera block).
    [
        """CREATE TABLE calibrations (
            id INTEGER PRIMARY KEY,
            spacecraft TEXT NOT NULL,
            version INTEGER NOT NULL,
            camera_json TEXT NOT NULL,
            result_json TEXT NOT NULL,
            sequences_json TEXT NOT NULL,
            operator TEXT,
            created_at TEXT NOT NULL,
            UNIQUE (spacecraft, version)
        )""",
        """CREATE TRIGGER calibrations_no_update BEFORE UPDATE ON calibrations
            BEGIN SELECT RAISE(ABORT, 'calibrations are append-only'); END""",
        """CREATE TRIGGER calibrations_no_delete BEFORE DELETE ON calibrations
            BEGIN SELECT RAISE(ABORT, 'calibrations are append-only'); END""",
        "ALTER TABLE sequences ADD COLUMN camera_calibration INTEGER",
        "DROP TRIGGER sequences_keep_content",
        """CREATE TRIGGER sequences_keep_content BEFORE UPDATE ON sequences
            WHEN NEW.id IS NOT OLD.id OR NEW.content_sha256 IS NOT OLD.content_sha256
              OR NEW.raw_text IS NOT OLD.raw_text OR NEW.uploaded_at IS NOT OLD.uploaded_at
              OR NEW.extraction_json IS NOT OLD.extraction_json OR NEW.camera_json IS NOT OLD.camera_json
              OR NEW.camera_calibration IS NOT OLD.camera_calibration
            BEGIN SELECT RAISE(ABORT, 'an upload is never changed'); END""",
    ],
]


# ---------------------------------------------------------------------------
# Records
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class SequenceRow:
    """One upload.  In :meth:`Storage.list_sequences` rows, ``raw_text`` and
    ``extraction`` are None (they can be megabytes); :meth:`Storage.get_sequence`
    fills them."""

    id: int
    content_sha256: str
    filename: str | None
    sequence_id: str | None
    spacecraft: str | None
    camera: dict | None
    first_time: datetime | None
    n_snapshots: int | None
    uploaded_at: datetime
    status: str
    raw_text: str | None = None
    extraction_json: str | None = field(default=None, repr=False)
    #: Version of the spacecraft's calibration whose camera the upload was given (None: its own or the default).
    camera_calibration: int | None = None

    @functools.cached_property
    def extraction(self) -> dict | None:
        """The stored extraction document, parsed on first use (tens of kB of JSON)."""
        return _loads(self.extraction_json)


@dataclass(frozen=True)
class PatternVersion:
    id: int
    seq_id: int
    version: int
    kind: str  # 'automatic' | 'edit' | 'reset'
    pattern: dict  # excluded tracks, included tracks, manual points, as the API defines them
    operator: str | None
    created_at: datetime


@dataclass(frozen=True)
class SearchRow:
    id: int
    seq_id: int
    pattern_version: int | None
    method: str
    options: dict
    result_json: str = field(repr=False)  # the candidates as the API serialises them: see ``result``
    status: str
    created_at: datetime
    elapsed_s: float | None

    @functools.cached_property
    def result(self) -> Any:
        """The stored result document, parsed on first use."""
        return _loads(self.result_json)


@dataclass(frozen=True)
class ConfirmationRow:
    id: int
    seq_id: int
    search_id: int | None
    rank: int
    operator: str
    confirmed_at: datetime
    comment: str | None
    quaternion: list[float]  # project convention: scalar-last [x, y, z, w] of R
    rotation_matrix: list[list[float]]  # ICRS -> camera
    ra_deg: float
    dec_deg: float
    roll_deg: float
    deviation_arcsec: float | None
    false_match_probability: float | None
    pattern: dict
    candidate: dict
    apm_text: str
    aem_text: str | None
    superseded_by: int | None
    epoch: datetime | None = None  # the reference snapshot's time, the APM's EPOCH
    rate_deg_s: list[float] | None = None  # fitted body rate, camera axes (None: no sequence fit)

    @property
    def is_current(self) -> bool:
        return self.superseded_by is None


@dataclass(frozen=True)
class CalibrationRow:
    """One calibration of a spacecraft's camera: version 1, 2, ... per spacecraft, never changed."""

    id: int
    spacecraft: str
    version: int
    camera: dict  # the telemetry camera object of the fitted camera
    result: dict  # sigmas, covariance, stars and sequences used, RMS before and after
    sequences: list[int]  # archive ids of the sequences it was fitted on
    operator: str | None
    created_at: datetime


# ---------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------

def content_sha256(raw_text: str) -> str:
    """Hex SHA-256 of the UTF-8 bytes of an upload: the identity of its content."""
    return hashlib.sha256(raw_text.encode("utf-8")).hexdigest()


def default_database_path() -> Path:
    """``$XDG_DATA_HOME/starid/starid.sqlite3`` (``~/.local/share`` when unset)."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.expanduser("~/.local/share")
    return Path(base) / "starid" / "starid.sqlite3"


def _now() -> datetime:
    return datetime.now(timezone.utc)


def _time_text(t: datetime | None) -> str | None:
    """Aware datetimes as fixed-width UTC ISO text, so text order is time order."""
    if t is None:
        return None
    if t.tzinfo is None or t.utcoffset() is None:
        raise ValueError("times must be timezone-aware")
    return t.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f+00:00")


def _time(text: str | None) -> datetime | None:
    return None if text is None else datetime.fromisoformat(text)


def _dumps(value: Any) -> str:
    # allow_nan=False: NaN/Infinity are not JSON and would not survive other readers.
    return json.dumps(value, separators=(",", ":"), allow_nan=False)


def _loads(text: str | None) -> Any:
    return None if text is None else json.loads(text)


def _check_page(offset: int, limit: int) -> None:
    if not isinstance(offset, int) or offset < 0:
        raise ValueError("offset must be a non-negative integer")
    if not isinstance(limit, int) or not 1 <= limit <= MAX_PAGE:
        raise ValueError(f"limit must be an integer from 1 to {MAX_PAGE}")


def _sqlite_path(path_or_url: str | os.PathLike) -> str:
    text = os.fspath(path_or_url)
    if text.startswith(("postgres://", "postgresql://")):
        raise StorageError("the PostgreSQL backend is not implemented yet; use a SQLite path")
    if text.startswith("sqlite:///"):
        # As in SQLAlchemy: sqlite:///relative.db, sqlite:////absolute/path.db
        text = text[len("sqlite:///"):]
    elif "://" in text:
        raise StorageError(f"unsupported database URL scheme: {text.split('://')[0]}")
    if not text or text == ":memory:":
        # WAL and durability make no sense in memory; refuse rather than pretend.
        raise StorageError("a database file path is required")
    return text


_SEQUENCE_LIGHT_COLUMNS = ("id, content_sha256, filename, sequence_id, spacecraft, camera_json, "
                           "first_time, n_snapshots, uploaded_at, status, camera_calibration")


def _sequence_row(row: sqlite3.Row, full: bool) -> SequenceRow:
    return SequenceRow(
        id=row["id"], content_sha256=row["content_sha256"], filename=row["filename"],
        sequence_id=row["sequence_id"], spacecraft=row["spacecraft"],
        camera=_loads(row["camera_json"]), first_time=_time(row["first_time"]),
        n_snapshots=row["n_snapshots"], uploaded_at=_time(row["uploaded_at"]),
        status=row["status"],
        raw_text=row["raw_text"] if full else None,
        extraction_json=row["extraction_json"] if full else None,
        camera_calibration=row["camera_calibration"],
    )


def _pattern_row(row: sqlite3.Row) -> PatternVersion:
    return PatternVersion(id=row["id"], seq_id=row["seq_id"], version=row["version"],
                          kind=row["kind"], pattern=_loads(row["pattern_json"]),
                          operator=row["operator"], created_at=_time(row["created_at"]))


def _search_row(row: sqlite3.Row) -> SearchRow:
    return SearchRow(id=row["id"], seq_id=row["seq_id"], pattern_version=row["pattern_version"],
                     method=row["method"], options=_loads(row["options_json"]),
                     result_json=row["result_json"], status=row["status"],
                     created_at=_time(row["created_at"]), elapsed_s=row["elapsed_s"])


def _calibration_row(row: sqlite3.Row) -> CalibrationRow:
    return CalibrationRow(id=row["id"], spacecraft=row["spacecraft"], version=row["version"],
                          camera=_loads(row["camera_json"]), result=_loads(row["result_json"]),
                          sequences=_loads(row["sequences_json"]), operator=row["operator"],
                          created_at=_time(row["created_at"]))


def _confirmation_row(row: sqlite3.Row) -> ConfirmationRow:
    return ConfirmationRow(
        id=row["id"], seq_id=row["seq_id"], search_id=row["search_id"], rank=row["rank"],
        operator=row["operator"], confirmed_at=_time(row["confirmed_at"]), comment=row["comment"],
        quaternion=_loads(row["quaternion_json"]),
        rotation_matrix=_loads(row["rotation_matrix_json"]),
        ra_deg=row["ra_deg"], dec_deg=row["dec_deg"], roll_deg=row["roll_deg"],
        deviation_arcsec=row["deviation_arcsec"],
        false_match_probability=row["false_match_probability"],
        pattern=_loads(row["pattern_json"]), candidate=_loads(row["candidate_json"]),
        apm_text=row["apm_text"], aem_text=row["aem_text"], superseded_by=row["superseded_by"],
        epoch=_time(row["epoch"]), rate_deg_s=_loads(row["rate_deg_s_json"]),
    )


# ---------------------------------------------------------------------------
# Storage
# ---------------------------------------------------------------------------

class Storage:
    """The archive.  Open with :meth:`open`; every method is one transaction.

    Reads of unknown ids return None; writes that name an unknown sequence
    raise :class:`UnknownSequence`; bad argument values raise ValueError.
    """

    def __init__(self, connection: sqlite3.Connection, path: str) -> None:
        self._conn = connection
        self._path = path
        self._lock = threading.RLock()
        self._closed = False

    # -- life cycle ---------------------------------------------------------

    @classmethod
    def open(cls, path_or_url: str | os.PathLike | None = None) -> "Storage":
        """Open (creating if needed) the database and bring its schema up to date.

        ``path_or_url``: a file path or ``sqlite:///path``; None means
        ``$DATABASE_URL`` or :func:`default_database_path`.
        """
        if path_or_url is None:
            path_or_url = os.environ.get(DATABASE_URL_ENV) or default_database_path()
        path = _sqlite_path(path_or_url)
        try:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            # isolation_level=None: we issue BEGIN/COMMIT ourselves, so the
            # transaction boundaries are exactly the methods' boundaries.
            conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=30.0)
        except (OSError, sqlite3.Error) as exc:
            raise StorageError(f"cannot open database {path}: {exc}") from None
        conn.row_factory = sqlite3.Row
        try:
            mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StorageError(f"cannot switch {path} to WAL mode (got {mode})")
            conn.execute("PRAGMA synchronous=FULL")
            conn.execute("PRAGMA foreign_keys=ON")
            conn.execute("PRAGMA busy_timeout=30000")
            storage = cls(conn, path)
            storage._migrate()
        except sqlite3.DatabaseError as exc:
            conn.close()
            raise StorageError(f"{path} is not a usable database: {exc}") from None
        except StorageError:
            conn.close()
            raise
        return storage

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._conn.close()

    def __enter__(self) -> "Storage":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    @property
    def path(self) -> str:
        return self._path

    def _migrate(self) -> None:
        with self._transaction() as conn:
            conn.execute("CREATE TABLE IF NOT EXISTS schema_version ("
                         "version INTEGER PRIMARY KEY, applied_at TEXT NOT NULL)")
            current = conn.execute("SELECT COALESCE(MAX(version), 0) FROM schema_version").fetchone()[0]
            if current > len(MIGRATIONS):
                raise StorageError(f"database schema version {current} is newer than this "
                                   f"program's ({len(MIGRATIONS)}); upgrade the program")
            for version in range(current + 1, len(MIGRATIONS) + 1):
                for statement in MIGRATIONS[version - 1]:
                    conn.execute(statement)
                conn.execute("INSERT INTO schema_version (version, applied_at) VALUES (?, ?)",
                             (version, _time_text(_now())))

    class _Transaction:
        def __init__(self, storage: "Storage", write: bool) -> None:
            self._storage = storage
            self._write = write

        def __enter__(self) -> sqlite3.Connection:
            self._storage._lock.acquire()
            if self._storage._closed:
                self._storage._lock.release()
                raise StorageError("storage is closed")
            # Writers take the write lock up front (no lock upgrade deadlocks between
            # processes); readers use a deferred transaction: one consistent snapshot.
            self._storage._conn.execute("BEGIN IMMEDIATE" if self._write else "BEGIN")
            return self._storage._conn

        def __exit__(self, exc_type, exc, tb) -> None:
            conn = self._storage._conn
            try:
                if exc_type is None:
                    try:
                        conn.execute("COMMIT")
                    except sqlite3.Error:
                        # e.g. disk full: leave no half-open transaction behind.
                        if conn.in_transaction:
                            conn.execute("ROLLBACK")
                        raise
                else:
                    conn.execute("ROLLBACK")
            finally:
                self._storage._lock.release()

    def _transaction(self, write: bool = True) -> "_Transaction":
        return Storage._Transaction(self, write)

    @staticmethod
    def _require_sequence(conn: sqlite3.Connection, seq_id: int) -> None:
        if conn.execute("SELECT 1 FROM sequences WHERE id = ?", (seq_id,)).fetchone() is None:
            raise UnknownSequence(f"no sequence with id {seq_id}")

    # -- sequences ----------------------------------------------------------

    def add_sequence(self, *, raw_text: str, filename: str | None = None,
                     sequence_id: str | None = None, spacecraft: str | None = None,
                     camera: dict | None = None, first_time: datetime | None = None,
                     n_snapshots: int | None = None, extraction: dict | None = None,
                     status: str = "new", uploaded_at: datetime | None = None,
                     camera_calibration: int | None = None,
                     ) -> tuple[SequenceRow, bool]:
        """Store an upload; ``(row, True)`` if new, ``(existing row, False)`` if
        the same content (SHA-256 of ``raw_text``) was stored before."""
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}")
        digest = content_sha256(raw_text)
        with self._transaction() as conn:
            cursor = conn.execute(
                "INSERT INTO sequences (content_sha256, filename, sequence_id, spacecraft, camera_json, "
                "first_time, n_snapshots, raw_text, uploaded_at, extraction_json, status, camera_calibration) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (content_sha256) DO NOTHING",
                (digest, filename, sequence_id, spacecraft,
                 None if camera is None else _dumps(camera), _time_text(first_time), n_snapshots,
                 raw_text, _time_text(uploaded_at or _now()),
                 None if extraction is None else _dumps(extraction), status, camera_calibration))
            created = cursor.rowcount == 1
            row = conn.execute("SELECT * FROM sequences WHERE content_sha256 = ?", (digest,)).fetchone()
        return _sequence_row(row, full=True), created

    def find_sequence(self, content_sha256: str) -> SequenceRow | None:
        """The stored sequence with this content digest (:func:`content_sha256`), if any."""
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM sequences WHERE content_sha256 = ?", (content_sha256,)).fetchone()
        return None if row is None else _sequence_row(row, full=True)

    def get_sequence(self, seq_id: int) -> SequenceRow | None:
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM sequences WHERE id = ?", (seq_id,)).fetchone()
        return None if row is None else _sequence_row(row, full=True)

    def list_sequences(self, offset: int = 0, limit: int = 50, *, spacecraft: str | None = None,
                       status: str | None = None) -> tuple[list[SequenceRow], int]:
        """A page of uploads, newest first, and the total number matching the filters."""
        _check_page(offset, limit)
        where, params = [], []
        if spacecraft is not None:
            where.append("spacecraft = ?")
            params.append(spacecraft)
        if status is not None:
            where.append("status = ?")
            params.append(status)
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        with self._transaction(write=False) as conn:
            total = conn.execute(f"SELECT COUNT(*) FROM sequences{clause}", params).fetchone()[0]
            rows = conn.execute(f"SELECT {_SEQUENCE_LIGHT_COLUMNS} FROM sequences{clause} "
                                "ORDER BY id DESC LIMIT ? OFFSET ?", [*params, limit, offset]).fetchall()
        return [_sequence_row(r, full=False) for r in rows], total

    def set_status(self, seq_id: int, status: str) -> SequenceRow:
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}")
        with self._transaction() as conn:
            self._require_sequence(conn, seq_id)
            conn.execute("UPDATE sequences SET status = ? WHERE id = ?", (status, seq_id))
            row = conn.execute("SELECT * FROM sequences WHERE id = ?", (seq_id,)).fetchone()
        return _sequence_row(row, full=True)

    # -- patterns -----------------------------------------------------------

    def add_pattern_version(self, seq_id: int, pattern: dict, *, kind: str = "edit",
                            operator: str | None = None) -> PatternVersion:
        """Append the next version of a sequence's pattern (1 for the first)."""
        if kind not in PATTERN_KINDS:
            raise ValueError(f"kind must be one of {PATTERN_KINDS}")
        with self._transaction() as conn:
            self._require_sequence(conn, seq_id)
            version = conn.execute("SELECT COALESCE(MAX(version), 0) + 1 FROM pattern_versions "
                                   "WHERE seq_id = ?", (seq_id,)).fetchone()[0]
            cursor = conn.execute(
                "INSERT INTO pattern_versions (seq_id, version, kind, pattern_json, operator, created_at) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (seq_id, version, kind, _dumps(pattern), operator, _time_text(_now())))
            row = conn.execute("SELECT * FROM pattern_versions WHERE id = ?",
                               (cursor.lastrowid,)).fetchone()
        return _pattern_row(row)

    def current_pattern(self, seq_id: int) -> PatternVersion | None:
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM pattern_versions WHERE seq_id = ? "
                               "ORDER BY version DESC LIMIT 1", (seq_id,)).fetchone()
        return None if row is None else _pattern_row(row)

    def pattern_history(self, seq_id: int) -> list[PatternVersion]:
        """All versions of a sequence's pattern, oldest first."""
        with self._transaction(write=False) as conn:
            rows = conn.execute("SELECT * FROM pattern_versions WHERE seq_id = ? ORDER BY version",
                                (seq_id,)).fetchall()
        return [_pattern_row(r) for r in rows]

    # -- searches -----------------------------------------------------------

    def add_search(self, seq_id: int, *, pattern_version: int | None, method: str, options: dict,
                   result: Any, status: str, elapsed_s: float | None = None) -> SearchRow:
        with self._transaction() as conn:
            self._require_sequence(conn, seq_id)
            cursor = conn.execute(
                "INSERT INTO searches (seq_id, pattern_version, method, options_json, result_json, "
                "status, created_at, elapsed_s) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (seq_id, pattern_version, method, _dumps(options), _dumps(result), status,
                 _time_text(_now()), elapsed_s))
            row = conn.execute("SELECT * FROM searches WHERE id = ?", (cursor.lastrowid,)).fetchone()
        return _search_row(row)

    def get_search(self, search_id: int) -> SearchRow | None:
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM searches WHERE id = ?", (search_id,)).fetchone()
        return None if row is None else _search_row(row)

    def latest_search(self, seq_id: int) -> SearchRow | None:
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM searches WHERE seq_id = ? ORDER BY id DESC LIMIT 1",
                               (seq_id,)).fetchone()
        return None if row is None else _search_row(row)

    # -- confirmations ------------------------------------------------------

    def add_confirmation(self, seq_id: int, *, search_id: int | None, rank: int, operator: str,
                         quaternion: list[float], rotation_matrix: list[list[float]],
                         ra_deg: float, dec_deg: float, roll_deg: float,
                         deviation_arcsec: float | None, false_match_probability: float | None,
                         pattern: dict, candidate: dict, apm_text: str, aem_text: str | None = None,
                         comment: str | None = None, confirmed_at: datetime | None = None,
                         epoch: datetime | None = None, rate_deg_s: list[float] | None = None,
                         ) -> ConfirmationRow:
        """Append a confirmation; in the same transaction mark the sequence's
        earlier current confirmation as superseded by it and set the sequence's
        status to ``confirmed``."""
        if not operator:
            raise ValueError("a confirmation needs an operator")
        if not apm_text:
            raise ValueError("a confirmation needs its APM text")
        with self._transaction() as conn:
            self._require_sequence(conn, seq_id)
            cursor = conn.execute(
                "INSERT INTO confirmations (seq_id, search_id, rank, operator, confirmed_at, comment, "
                "quaternion_json, rotation_matrix_json, ra_deg, dec_deg, roll_deg, deviation_arcsec, "
                "false_match_probability, pattern_json, candidate_json, apm_text, aem_text, epoch, "
                "rate_deg_s_json) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (seq_id, search_id, int(rank), operator, _time_text(confirmed_at or _now()), comment,
                 _dumps([float(v) for v in quaternion]),
                 _dumps([[float(v) for v in row] for row in rotation_matrix]),
                 float(ra_deg), float(dec_deg), float(roll_deg),
                 None if deviation_arcsec is None else float(deviation_arcsec),
                 None if false_match_probability is None else float(false_match_probability),
                 _dumps(pattern), _dumps(candidate), apm_text, aem_text, _time_text(epoch),
                 None if rate_deg_s is None else _dumps([float(w) for w in rate_deg_s])))
            new_id = cursor.lastrowid
            conn.execute("UPDATE confirmations SET superseded_by = ? "
                         "WHERE seq_id = ? AND superseded_by IS NULL AND id < ?",
                         (new_id, seq_id, new_id))
            conn.execute("UPDATE sequences SET status = 'confirmed' WHERE id = ?", (seq_id,))
            row = conn.execute("SELECT * FROM confirmations WHERE id = ?", (new_id,)).fetchone()
        return _confirmation_row(row)

    def get_confirmation(self, confirmation_id: int) -> ConfirmationRow | None:
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM confirmations WHERE id = ?",
                               (confirmation_id,)).fetchone()
        return None if row is None else _confirmation_row(row)

    def list_confirmations(self, offset: int = 0, limit: int = 50,
                           ) -> tuple[list[ConfirmationRow], int]:
        """A page of all confirmations (superseded ones included), newest first, and the total."""
        _check_page(offset, limit)
        with self._transaction(write=False) as conn:
            total = conn.execute("SELECT COUNT(*) FROM confirmations").fetchone()[0]
            rows = conn.execute("SELECT * FROM confirmations ORDER BY id DESC LIMIT ? OFFSET ?",
                                (limit, offset)).fetchall()
        return [_confirmation_row(r) for r in rows], total

    def current_confirmation(self, seq_id: int) -> ConfirmationRow | None:
        """The sequence's newest confirmation (the one not superseded), if any."""
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM confirmations WHERE seq_id = ? AND superseded_by IS NULL "
                               "ORDER BY id DESC LIMIT 1", (seq_id,)).fetchone()
        return None if row is None else _confirmation_row(row)

    def latest_confirmation_of_spacecraft(self, spacecraft: str | None) -> ConfirmationRow | None:
        """The newest current confirmation of any sequence of ``spacecraft`` (None: of unnamed spacecraft)."""
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT c.* FROM confirmations c JOIN sequences s ON s.id = c.seq_id "
                               "WHERE c.superseded_by IS NULL AND s.spacecraft IS ? ORDER BY c.id DESC LIMIT 1",
                               (spacecraft,)).fetchone()
        return None if row is None else _confirmation_row(row)

    def confirmation_history(self, seq_id: int) -> list[ConfirmationRow]:
        """Every confirmation of a sequence, oldest first (the audit trail)."""
        with self._transaction(write=False) as conn:
            rows = conn.execute("SELECT * FROM confirmations WHERE seq_id = ? ORDER BY id",
                                (seq_id,)).fetchall()
        return [_confirmation_row(r) for r in rows]

    # -- calibrations -------------------------------------------------------

    def add_calibration(self, spacecraft: str, *, camera: dict, result: dict, sequences: list[int],
                        operator: str | None = None) -> CalibrationRow:
        """Append the next calibration version of ``spacecraft``'s camera (1 for the first)."""
        if not spacecraft:
            raise ValueError("a calibration needs a spacecraft")
        with self._transaction() as conn:
            version = conn.execute("SELECT COALESCE(MAX(version), 0) + 1 FROM calibrations WHERE spacecraft = ?",
                                   (spacecraft,)).fetchone()[0]
            cursor = conn.execute(
                "INSERT INTO calibrations (spacecraft, version, camera_json, result_json, sequences_json, operator, "
                "created_at) VALUES (?, ?, ?, ?, ?, ?, ?)",
                (spacecraft, version, _dumps(camera), _dumps(result), _dumps([int(s) for s in sequences]),
                 operator, _time_text(_now())))
            row = conn.execute("SELECT * FROM calibrations WHERE id = ?", (cursor.lastrowid,)).fetchone()
        return _calibration_row(row)

    def current_calibration(self, spacecraft: str | None) -> CalibrationRow | None:
        """The newest calibration of ``spacecraft``'s camera, if any."""
        if spacecraft is None:
            return None
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM calibrations WHERE spacecraft = ? ORDER BY version DESC LIMIT 1",
                               (spacecraft,)).fetchone()
        return None if row is None else _calibration_row(row)

    def calibration_history(self, spacecraft: str) -> list[CalibrationRow]:
        """Every calibration of ``spacecraft``'s camera, oldest first."""
        with self._transaction(write=False) as conn:
            rows = conn.execute("SELECT * FROM calibrations WHERE spacecraft = ? ORDER BY version",
                                (spacecraft,)).fetchall()
        return [_calibration_row(r) for r in rows]

    # -- health -------------------------------------------------------------

    def health(self) -> dict:
        """Backend, schema version, journal mode, row counts; ``ok`` False if the database fails."""
        try:
            with self._transaction(write=False) as conn:
                version = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()[0]
                mode = conn.execute("PRAGMA journal_mode").fetchone()[0]
                counts = {table: conn.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
                          for table in ("sequences", "pattern_versions", "searches", "confirmations",
                                        "calibrations")}
        except (sqlite3.Error, StorageError) as exc:
            return {"ok": False, "backend": "sqlite", "path": self._path, "error": str(exc)}
        return {"ok": True, "backend": "sqlite", "path": self._path, "schema_version": version,
                "journal_mode": mode, "counts": counts}
