"""The SQLite backend: the embedded default archive (one file, no server).

SQLite in WAL mode (``journal_mode=WAL``, ``synchronous=FULL``,
``foreign_keys=ON``): with ``synchronous=FULL`` a commit returns only after
the WAL has been fsync'ed, so anything a method has returned survives a
SIGKILL or a power cut.

Threads: methods may be called from any thread (the FastAPI thread pool).
Writers share one connection guarded by a lock: SQLite serialises writers
anyway, and the lock makes each method one atomic transaction without
SQLITE_BUSY retries.  Writers take the write lock up front (``BEGIN
IMMEDIATE``), so the numbering of pattern versions and the supersession of
confirmations need no other lock.  Readers never take that lock: each reading
method borrows a read-only connection of its own (:class:`_Readers`, opened on
first need and kept for the next reader) and runs one deferred transaction on
it.  In WAL mode a reader sees the last commit before its first statement and
neither waits for a writer nor holds one up, so a search reading its sequence
does not queue behind a worst-case upload's large INSERT and its fsync (under
two clients sending such files, ordinary searches waited up to
hundreds of milliseconds on the one shared connection).  Several processes on
one file work (the busy time-out waits for the writer), but several machines
need :mod:`app.storage.postgres`.

Schema versions: ``schema_version`` holds the versions applied;
:data:`MIGRATIONS` lists the SQL of each version in order and
:meth:`SQLiteStorage.connect` applies the missing ones in one transaction.  A
database newer than this code is refused.  The PostgreSQL backend has the
same versions with the same meaning in its own dialect
(:data:`app.storage.postgres.MIGRATIONS`).
"""

from __future__ import annotations

import os
import sqlite3
import threading
from contextlib import contextmanager
from pathlib import Path

from app.storage.base import POSTGRES_SCHEMES, Storage
from app.storage.records import CONFIRMATION_COLUMNS, StorageError, _now, _time_text


# ---------------------------------------------------------------------------
# Schema
# ---------------------------------------------------------------------------

def _confirmations_only_supersede(extra_columns: tuple[str, ...] = ()) -> str:
    """The guard that lets only ``superseded_by`` change, once, from NULL to a newer record of the same
    sequence; every other column (``extra_columns``: those added by later migrations) is frozen."""
    columns = (*CONFIRMATION_COLUMNS, *extra_columns)
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
    # 4: operator verdicts.  "No valid attitude" (a rejection with its reason) is a verdict
    # and a status; a confirmation records the reason an operator gave for overriding a guard rail
    # and the guard rail's own reasons.  The status CHECK can only change by rebuilding the table
    # (foreign keys are off during migrations and checked before the commit); its indexes and
    # guards are created again exactly as migration 3 left them.
    [
        """CREATE TABLE sequences_v4 (
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
                CHECK (status IN ('new', 'identified', 'ambiguous', 'no_match', 'confirmed', 'rejected')),
            camera_calibration INTEGER
        )""",
        """INSERT INTO sequences_v4 (id, content_sha256, filename, sequence_id, spacecraft, camera_json, first_time,
                                     n_snapshots, raw_text, uploaded_at, extraction_json, status, camera_calibration)
           SELECT id, content_sha256, filename, sequence_id, spacecraft, camera_json, first_time, n_snapshots,
                  raw_text, uploaded_at, extraction_json, status, camera_calibration FROM sequences""",
        "DROP TABLE sequences",
        "ALTER TABLE sequences_v4 RENAME TO sequences",
        "CREATE INDEX sequences_spacecraft ON sequences (spacecraft)",
        "CREATE INDEX sequences_status ON sequences (status)",
        "CREATE INDEX sequences_first_time ON sequences (first_time)",
        """CREATE TRIGGER sequences_keep_content BEFORE UPDATE ON sequences
            WHEN NEW.id IS NOT OLD.id OR NEW.content_sha256 IS NOT OLD.content_sha256
              OR NEW.raw_text IS NOT OLD.raw_text OR NEW.uploaded_at IS NOT OLD.uploaded_at
              OR NEW.extraction_json IS NOT OLD.extraction_json OR NEW.camera_json IS NOT OLD.camera_json
              OR NEW.camera_calibration IS NOT OLD.camera_calibration
            BEGIN SELECT RAISE(ABORT, 'an upload is never changed'); END""",
        """CREATE TRIGGER sequences_no_delete BEFORE DELETE ON sequences
            BEGIN SELECT RAISE(ABORT, 'uploads are never deleted'); END""",
        """CREATE TABLE rejections (
            id INTEGER PRIMARY KEY,
            seq_id INTEGER NOT NULL REFERENCES sequences (id),
            search_id INTEGER REFERENCES searches (id),
            operator TEXT NOT NULL CHECK (length(trim(operator)) > 0),
            rejected_at TEXT NOT NULL,
            reason TEXT NOT NULL CHECK (length(trim(reason)) > 0),
            replaces_confirmation INTEGER REFERENCES confirmations (id),
            replaces_rejection INTEGER REFERENCES rejections (id)
        )""",
        "CREATE INDEX rejections_seq ON rejections (seq_id, id)",
        "CREATE INDEX rejections_replaces_confirmation ON rejections (replaces_confirmation)",
        "CREATE INDEX rejections_replaces_rejection ON rejections (replaces_rejection)",
        """CREATE TRIGGER rejections_no_update BEFORE UPDATE ON rejections
            BEGIN SELECT RAISE(ABORT, 'rejections are append-only'); END""",
        """CREATE TRIGGER rejections_no_delete BEFORE DELETE ON rejections
            BEGIN SELECT RAISE(ABORT, 'rejections are append-only'); END""",
        "ALTER TABLE confirmations ADD COLUMN override_reason TEXT",
        "ALTER TABLE confirmations ADD COLUMN overridden_json TEXT",
        "ALTER TABLE confirmations ADD COLUMN replaces_rejection INTEGER REFERENCES rejections (id)",
        "CREATE INDEX confirmations_replaces_rejection ON confirmations (replaces_rejection)",
        "DROP TRIGGER confirmations_only_supersede",
        _confirmations_only_supersede(("epoch", "rate_deg_s_json", "override_reason", "overridden_json",
                                       "replaces_rejection")),
    ],
    # hot-pixel maps of a spacecraft's camera (one per sensor size), versioned and
    # append-only like calibrations; uploads of frames by the hash of their content and parameters,
    # so the same frames sent again give the stored sequence even after the map has grown.
    [
        """CREATE TABLE hot_pixel_maps (
            id INTEGER PRIMARY KEY,
            spacecraft TEXT NOT NULL,
            sensor TEXT NOT NULL,
            version INTEGER NOT NULL,
            map_json TEXT NOT NULL,
            frames INTEGER NOT NULL,
            hot_pixels INTEGER NOT NULL,
            seq_id INTEGER REFERENCES sequences (id),
            created_at TEXT NOT NULL,
            UNIQUE (spacecraft, sensor, version)
        )""",
        """CREATE TRIGGER hot_pixel_maps_no_update BEFORE UPDATE ON hot_pixel_maps
            BEGIN SELECT RAISE(ABORT, 'hot-pixel maps are append-only'); END""",
        """CREATE TRIGGER hot_pixel_maps_no_delete BEFORE DELETE ON hot_pixel_maps
            BEGIN SELECT RAISE(ABORT, 'hot-pixel maps are append-only'); END""",
        """CREATE TABLE frame_uploads (
            upload_sha256 TEXT PRIMARY KEY,
            seq_id INTEGER NOT NULL REFERENCES sequences (id),
            created_at TEXT NOT NULL
        )""",
        """CREATE TRIGGER frame_uploads_no_update BEFORE UPDATE ON frame_uploads
            BEGIN SELECT RAISE(ABORT, 'frame uploads are append-only'); END""",
        """CREATE TRIGGER frame_uploads_no_delete BEFORE DELETE ON frame_uploads
            BEGIN SELECT RAISE(ABORT, 'frame uploads are append-only'); END""",
    ],
    # 6: the CCSDS ACM of a confirmation, rendered once at confirmation like its APM and
    # AEM (NULL for confirmations made before), frozen like every other column.
    [
        "ALTER TABLE confirmations ADD COLUMN acm_text TEXT",
        "DROP TRIGGER confirmations_only_supersede",
        _confirmations_only_supersede(("epoch", "rate_deg_s_json", "override_reason", "overridden_json",
                                       "replaces_rejection", "acm_text")),
    ],
    # 7: a preview of each frame of a sequence uploaded as frames (the frame
    # stretched to 8 bits, averaged over scale x scale blocks, as PNG; at most 2 MiB) with its overlay
    # (detections, rejected blobs, hot pixels), one per snapshot, append-only.
    [
        """CREATE TABLE frame_previews (
            id INTEGER PRIMARY KEY,
            seq_id INTEGER NOT NULL REFERENCES sequences (id),
            snapshot INTEGER NOT NULL CHECK (snapshot >= 0),
            width INTEGER NOT NULL CHECK (width >= 1),
            height INTEGER NOT NULL CHECK (height >= 1),
            scale INTEGER NOT NULL CHECK (scale >= 1),
            image_width INTEGER NOT NULL CHECK (image_width >= 1),
            image_height INTEGER NOT NULL CHECK (image_height >= 1),
            png BLOB NOT NULL CHECK (length(png) <= 2097152),
            overlay_json TEXT NOT NULL,
            created_at TEXT NOT NULL,
            UNIQUE (seq_id, snapshot)
        )""",
        """CREATE TRIGGER frame_previews_no_update BEFORE UPDATE ON frame_previews
            BEGIN SELECT RAISE(ABORT, 'frame previews are append-only'); END""",
        """CREATE TRIGGER frame_previews_no_delete BEFORE DELETE ON frame_previews
            BEGIN SELECT RAISE(ABORT, 'frame previews are append-only'); END""",
    ],
]


# ---------------------------------------------------------------------------
# The backend
# ---------------------------------------------------------------------------

def sqlite_path(path_or_url: str | os.PathLike) -> str:
    """The file of a path or ``sqlite:///path``; StorageError for other URLs and for ``:memory:``."""
    text = os.fspath(path_or_url)
    if text.startswith(POSTGRES_SCHEMES):
        raise StorageError("a PostgreSQL URL is opened by Storage.open, not by the SQLite backend")
    if text.startswith("sqlite:///"):
        # As in SQLAlchemy: sqlite:///relative.db, sqlite:////absolute/path.db
        text = text[len("sqlite:///"):]
    elif "://" in text:
        raise StorageError(f"unsupported database URL scheme: {text.split('://')[0]} "
                           "(a file path, sqlite:///path or postgresql://...)")
    if not text or text == ":memory:":
        # WAL and durability make no sense in memory; refuse rather than pretend.
        raise StorageError("a database file path is required")
    return text


class SQLiteStorage(Storage):
    """The archive in one SQLite file (see the module docstring)."""

    backend = "sqlite"

    def __init__(self, connection: sqlite3.Connection, path: str) -> None:
        self._conn = connection  # the writers' connection (and the migrations')
        self._path = path
        self._mutex = threading.RLock()
        self._readers = _Readers(path)
        self._closed = False

    @classmethod
    def connect(cls, path_or_url: str | os.PathLike) -> "SQLiteStorage":
        path = sqlite_path(path_or_url)
        try:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StorageError(f"cannot open database {path}: {exc}") from None
        conn = _connect(path)
        try:
            mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StorageError(f"cannot switch {path} to WAL mode (got {mode})")
            conn.execute("PRAGMA synchronous=FULL")
            storage = cls(conn, path)
            # Foreign keys are off while migrating: a migration may rebuild a table to change a
            # constraint (SQLite's documented way, see migration 4); _migrate checks every key
            # before it commits.  The pragma is a no-op inside a transaction, so it is set here.
            conn.execute("PRAGMA foreign_keys=OFF")
            storage._migrate()
            conn.execute("PRAGMA foreign_keys=ON")
        except sqlite3.DatabaseError as exc:
            conn.close()
            raise StorageError(f"{path} is not a usable database: {exc}") from None
        except StorageError:
            conn.close()
            raise
        return storage

    def close(self) -> None:
        with self._mutex:
            if not self._closed:
                self._closed = True
                self._readers.close()
                self._conn.close()

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
            broken = conn.execute("PRAGMA foreign_key_check").fetchall()
            if broken:  # raised inside the transaction: nothing of the migration is kept
                raise StorageError(f"the schema migration would leave {len(broken)} broken references "
                                   f"(first in table {broken[0][0]})")

    class _Transaction:
        """A writer's transaction on the writers' connection, under their lock."""

        def __init__(self, storage: "SQLiteStorage") -> None:
            self._storage = storage

        def __enter__(self) -> sqlite3.Connection:
            self._storage._mutex.acquire()
            if self._storage._closed:
                self._storage._mutex.release()
                raise StorageError("storage is closed")
            # Writers take the write lock up front (no lock upgrade deadlocks between processes).
            try:
                self._storage._conn.execute("BEGIN IMMEDIATE")
            except BaseException:
                self._storage._mutex.release()
                raise
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
                self._storage._mutex.release()

    def _transaction(self, write: bool = True, snapshot: bool = False):
        # Every transaction is one snapshot here, a reader's included.
        return SQLiteStorage._Transaction(self) if write else self._readers.transaction()

    def _insert(self, conn: sqlite3.Connection, sql: str, params) -> int | None:
        cursor = conn.execute(sql, params)
        return cursor.lastrowid if cursor.rowcount == 1 else None

    def _backend_facts(self, conn: sqlite3.Connection) -> dict:
        return {"journal_mode": conn.execute("PRAGMA journal_mode").fetchone()[0]}


def _connect(path: str) -> sqlite3.Connection:
    """A connection to ``path`` as every connection here is made: rows by name, a 30 s busy time-out, and
    isolation_level=None: we issue BEGIN/COMMIT ourselves, so the transaction boundaries are exactly the
    methods' boundaries."""
    try:
        conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=30.0)
        conn.row_factory = sqlite3.Row
        conn.execute("PRAGMA busy_timeout=30000")
    except sqlite3.Error as exc:
        raise StorageError(f"cannot open database {path}: {exc}") from None
    return conn


class _Readers:
    """Read-only connections to one SQLite file, one per reader at a time (see the module docstring).

    A connection is opened when every open one is in use and kept for the next reader, so there are
    at most as many as readers ever ran at once (the server's thread pool bounds them).  Each is
    ``query_only``: a reading method that tried to write would fail rather than bypass the writers'
    lock.
    """

    def __init__(self, path: str) -> None:
        self._path = path
        self._idle: list[sqlite3.Connection] = []
        self._lock = threading.Lock()
        self._closed = False

    def _open(self) -> sqlite3.Connection:
        conn = _connect(self._path)
        conn.execute("PRAGMA query_only=ON")
        return conn

    @contextmanager
    def transaction(self):
        """A connection of its own in one deferred transaction: one snapshot of the archive."""
        with self._lock:
            if self._closed:
                raise StorageError("storage is closed")
            conn = self._idle.pop() if self._idle else None
        if conn is None:
            conn = self._open()
        reusable = False
        try:
            conn.execute("BEGIN")
            yield conn
        finally:
            try:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")  # a reader's: nothing to keep, it ends the snapshot
                reusable = True
            except sqlite3.Error:
                pass  # a connection in an unknown state is not handed to the next reader
            with self._lock:
                if reusable and not self._closed:
                    self._idle.append(conn)
                    conn = None
            if conn is not None:
                conn.close()

    def close(self) -> None:
        """Close the idle connections now; one in use is closed when its reader is done."""
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()
