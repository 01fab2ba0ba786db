"""The PostgreSQL backend: one archive shared by several servers on several machines.

Selected by ``DATABASE_URL=postgresql://user:password@host:port/database`` or
``--db postgresql://...``; the methods are those of :class:`app.storage.Storage`,
written once for both backends.  This module adds:

Connections
-----------
psycopg 3 with a :class:`psycopg_pool.ConnectionPool` (``STARID_DB_POOL_SIZE``
connections at most; one idle for a second is checked before use, so a
restarted database server costs no request and a dead connection no pool).  Every method is one
transaction on one pooled connection: writers run ``READ COMMITTED`` and take
the locks below; readers of several statements run ``REPEATABLE READ READ
ONLY``, one consistent snapshot per method (a page and its total agree), and
a reader of one statement runs it alone.  ``synchronous_commit`` is ``on``: a
method returns after PostgreSQL has flushed its commit to the WAL, as
SQLite's ``synchronous=FULL`` does.  An upload's text and extraction (tens of
kB, needed by most requests, and never changed: the schema refuses it) are
kept in a small per-process cache, so reading a sequence again costs one
light row (:meth:`PostgresStorage._read_sequence`); so are searches, which
are append-only (:meth:`PostgresStorage._read_search`).

Concurrency between servers
---------------------------
* Pattern versions, searches, confirmations and rejections of a sequence are
  written under ``SELECT ... FOR NO KEY UPDATE`` of the sequence's row, held
  until the commit: versions are numbered ``MAX + 1`` without gaps or
  duplicates, and "read the current verdict, append the new one, mark the old
  one superseded" is one step whichever server runs it (a second confirmation
  without ``supersede`` then sees the first and raises
  :class:`app.storage.VerdictExists`).  ``UNIQUE (seq_id, version)`` stays as the
  backstop.
* Calibrations (per spacecraft) and hot-pixel maps (per camera) are numbered
  under a transaction-scoped advisory lock on their name.
* The same upload sent to two servers at once is stored once:
  ``INSERT ... ON CONFLICT (content_sha256) DO NOTHING RETURNING id`` waits for
  the other transaction and then does nothing; both read the stored row.
* Migrations run in one transaction under an advisory lock, so servers that
  start together apply each version once (the others wait, then find it done).

Schema
------
:data:`MIGRATIONS` has the same versions as SQLite's
(:data:`app.storage.sqlite.MIGRATIONS`) with the same meaning in PostgreSQL's
dialect: ``BIGINT GENERATED ALWAYS AS IDENTITY`` keys, ``TIMESTAMPTZ`` times,
``JSONB`` documents, ``DOUBLE PRECISION`` reals, and the append-only guards as
PL/pgSQL trigger functions (refusing UPDATE, DELETE and TRUNCATE, with SQLSTATE
``restrict_violation``).  Where SQLite had to rebuild a table to change a CHECK
(version 4), PostgreSQL alters the constraint.  JSONB columns are read back as
text and parsed as SQLite's are, so rows are the same values from either
backend (JSONB keeps numbers exactly but not key order or spacing).

Errors: a database that cannot be reached, or a connection lost mid-method,
raises :class:`app.storage.StorageError` (the API answers 503); a value
PostgreSQL cannot store (a NUL character in a text) raises
:class:`app.storage.UnstorableValue` (a ValueError).
"""

from __future__ import annotations

import functools
import re
import threading
import time
import weakref
from collections import OrderedDict
from contextlib import contextmanager
from urllib.parse import urlsplit, urlunsplit

import psycopg
from psycopg.conninfo import conninfo_to_dict, make_conninfo
from psycopg.types.string import TextLoader
from psycopg_pool import ConnectionPool, PoolTimeout

from app.storage.base import Storage
from app.storage.records import (_SEQUENCE_LIGHT_COLUMNS, CONFIRMATION_COLUMNS, SearchRow, SequenceRow,
                                 StorageError, UnknownSequence, UnstorableValue, _search_row, _sequence_row)

#: Seconds to wait for a connection: to the server when opening, from the pool in a method.
CONNECT_TIMEOUT_S = 10
POOL_TIMEOUT_S = 30.0
#: Advisory lock of the schema migrations (any constant: the key of "starid:schema").
MIGRATION_LOCK_KEY = "starid:schema"
#: Uploads whose text and extraction (tens of kB, read on most requests) a process keeps in memory.
CONTENT_CACHE_SIZE = 256


# ---------------------------------------------------------------------------
# Schema: the same versions as SQLite's, in PostgreSQL's dialect
# ---------------------------------------------------------------------------

def _refuse(table: str, message: str, events: str = "UPDATE OR DELETE") -> list[str]:
    """Triggers that refuse ``events`` (row level) and TRUNCATE on ``table`` with ``message``."""
    return [f"CREATE TRIGGER {table}_append_only BEFORE {events} ON {table} "
            f"FOR EACH ROW EXECUTE FUNCTION starid_refuse('{message}')",
            f"CREATE TRIGGER {table}_no_truncate BEFORE TRUNCATE ON {table} "
            f"FOR EACH STATEMENT EXECUTE FUNCTION starid_refuse('{message}')"]


def _confirmations_only_supersede(extra_columns: tuple[str, ...] = ()) -> str:
    """The guard that lets only ``superseded_by`` change, once, from NULL to a newer record of the same
    sequence; every other column (``extra_columns``: those added by later migrations) is frozen.
    (SQLite's trigger of the same name, as a PL/pgSQL function.)"""
    frozen = "\n             OR ".join(f"NEW.{c} IS DISTINCT FROM OLD.{c}" for c in (*CONFIRMATION_COLUMNS, *extra_columns))
    return f"""CREATE OR REPLACE FUNCTION starid_confirmations_only_supersede() RETURNS trigger
        LANGUAGE plpgsql AS $$
        BEGIN
          IF OLD.superseded_by IS NOT NULL OR NEW.superseded_by IS NULL OR NEW.superseded_by <= OLD.id
             OR {frozen} THEN
            RAISE EXCEPTION 'confirmations are append-only' USING ERRCODE = 'restrict_violation';
          END IF;
          RETURN NEW;
        END $$"""


def _sequences_keep_content(columns: tuple[str, ...]) -> str:
    """The guard that freezes an upload's ``columns`` (``status`` is the only column that changes)."""
    changed = "\n             OR ".join(f"NEW.{c} IS DISTINCT FROM OLD.{c}" for c in columns)
    return f"""CREATE OR REPLACE FUNCTION starid_sequences_keep_content() RETURNS trigger
        LANGUAGE plpgsql AS $$
        BEGIN
          IF {changed} THEN
            RAISE EXCEPTION 'an upload is never changed' USING ERRCODE = 'restrict_violation';
          END IF;
          RETURN NEW;
        END $$"""


_UPLOAD_COLUMNS_V1 = ("id", "content_sha256", "raw_text", "uploaded_at")

#: Version n of the schema is reached by running ``MIGRATIONS[n - 1]`` on version n - 1 (as SQLite's).
MIGRATIONS: list[list[str]] = [
    [
        # One function refuses for every append-only table; its argument is the message.
        """CREATE OR REPLACE FUNCTION starid_refuse() RETURNS trigger LANGUAGE plpgsql AS $$
        BEGIN
          RAISE EXCEPTION '%', TG_ARGV[0] USING ERRCODE = 'restrict_violation';
        END $$""",
        """CREATE TABLE sequences (
            id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
            content_sha256 TEXT NOT NULL UNIQUE,
            filename TEXT,
            sequence_id TEXT,
            spacecraft TEXT,
            camera_json JSONB,
            first_time TIMESTAMPTZ,
            n_snapshots INTEGER,
            raw_text TEXT NOT NULL,
            uploaded_at TIMESTAMPTZ NOT NULL,
            extraction_json JSONB,
            status TEXT NOT NULL DEFAULT 'new'
                CONSTRAINT sequences_status_check
                CHECK (status IN ('new', 'identified', 'ambiguous', 'no_match', 'confirmed'))
        )""",
        "CREATE INDEX sequences_spacecraft ON sequences (spacecraft)",
        "CREATE INDEX sequences_status ON sequences (status)",
        """CREATE TABLE pattern_versions (
            id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
            seq_id BIGINT NOT NULL REFERENCES sequences (id),
            version INTEGER NOT NULL,
            kind TEXT NOT NULL CHECK (kind IN ('automatic', 'edit', 'reset')),
            pattern_json JSONB NOT NULL,
            operator TEXT,
            created_at TIMESTAMPTZ NOT NULL,
            UNIQUE (seq_id, version)
        )""",
        """CREATE TABLE searches (
            id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
            seq_id BIGINT NOT NULL REFERENCES sequences (id),
            pattern_version INTEGER,
            method TEXT NOT NULL,
            options_json JSONB NOT NULL,
            result_json JSONB NOT NULL,
            status TEXT NOT NULL,
            created_at TIMESTAMPTZ NOT NULL,
            elapsed_s DOUBLE PRECISION
        )""",
        "CREATE INDEX searches_seq ON searches (seq_id, id)",
        """CREATE TABLE confirmations (
            id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
            seq_id BIGINT NOT NULL REFERENCES sequences (id),
            search_id BIGINT REFERENCES searches (id),
            rank INTEGER NOT NULL,
            operator TEXT NOT NULL,
            confirmed_at TIMESTAMPTZ NOT NULL,
            comment TEXT,
            quaternion_json JSONB NOT NULL,
            rotation_matrix_json JSONB NOT NULL,
            ra_deg DOUBLE PRECISION NOT NULL,
            dec_deg DOUBLE PRECISION NOT NULL,
            roll_deg DOUBLE PRECISION NOT NULL,
            deviation_arcsec DOUBLE PRECISION,
            false_match_probability DOUBLE PRECISION,
            pattern_json JSONB NOT NULL,
            candidate_json JSONB NOT NULL,
            apm_text TEXT NOT NULL,
            aem_text TEXT,
            superseded_by BIGINT REFERENCES confirmations (id)
        )""",
        "CREATE INDEX confirmations_seq ON confirmations (seq_id, id)",
        *_refuse("pattern_versions", "pattern_versions is append-only"),
        *_refuse("searches", "searches is append-only"),
        _confirmations_only_supersede(),
        """CREATE TRIGGER confirmations_only_supersede BEFORE UPDATE ON confirmations
            FOR EACH ROW EXECUTE FUNCTION starid_confirmations_only_supersede()""",
        *_refuse("confirmations", "confirmations is append-only", "DELETE"),
        _sequences_keep_content(_UPLOAD_COLUMNS_V1),
        """CREATE TRIGGER sequences_keep_content BEFORE UPDATE ON sequences
            FOR EACH ROW EXECUTE FUNCTION starid_sequences_keep_content()""",
        *_refuse("sequences", "uploads are never deleted", "DELETE"),
    ],
    # 2: a confirmation's epoch and fitted body rate as columns, filled from the APM text and the
    # candidate (the guard is off while they are filled); the stored extraction becomes immutable.
    [
        "ALTER TABLE confirmations ADD COLUMN epoch TIMESTAMPTZ",
        "ALTER TABLE confirmations ADD COLUMN rate_deg_s_json JSONB",
        "ALTER TABLE confirmations DISABLE TRIGGER confirmations_only_supersede",
        # The APM's "EPOCH = 2024-01-01T00:00:00.000000" line (26 characters of UTC).
        r"""UPDATE confirmations SET
             epoch = (substring(apm_text from E'\nEPOCH = (.{26})') || '+00:00')::timestamptz,
             rate_deg_s_json = NULLIF(candidate_json #> '{sequence_fit,rate_deg_s}', 'null'::jsonb)""",
        "ALTER TABLE confirmations ENABLE TRIGGER confirmations_only_supersede",
        _confirmations_only_supersede(("epoch", "rate_deg_s_json")),
        "CREATE INDEX confirmations_current ON confirmations (seq_id) WHERE superseded_by IS NULL",
        _sequences_keep_content((*_UPLOAD_COLUMNS_V1, "extraction_json")),
    ],
    # 3: camera calibrations of a spacecraft, versioned and append-only; an upload records the
    # calibration whose camera it was given.
    [
        """CREATE TABLE calibrations (
            id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
            spacecraft TEXT NOT NULL,
            version INTEGER NOT NULL,
            camera_json JSONB NOT NULL,
            result_json JSONB NOT NULL,
            sequences_json JSONB NOT NULL,
            operator TEXT,
            created_at TIMESTAMPTZ NOT NULL,
            UNIQUE (spacecraft, version)
        )""",
        *_refuse("calibrations", "calibrations are append-only"),
        "ALTER TABLE sequences ADD COLUMN camera_calibration INTEGER",
        _sequences_keep_content((*_UPLOAD_COLUMNS_V1, "extraction_json", "camera_json", "camera_calibration")),
    ],
    # 4: operator verdicts: "no valid attitude" (a rejection with its reason) as a verdict
    # and a status; a confirmation records an override's reason and the guard rail's reasons.  The
    # status CHECK is altered in place (SQLite rebuilds the table for the same change).
    [
        "ALTER TABLE sequences DROP CONSTRAINT sequences_status_check",
        """ALTER TABLE sequences ADD CONSTRAINT sequences_status_check
            CHECK (status IN ('new', 'identified', 'ambiguous', 'no_match', 'confirmed', 'rejected'))""",
        "CREATE INDEX sequences_first_time ON sequences (first_time)",
        """CREATE TABLE rejections (
            id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
            seq_id BIGINT NOT NULL REFERENCES sequences (id),
            search_id BIGINT REFERENCES searches (id),
            operator TEXT NOT NULL CHECK (length(trim(operator)) > 0),
            rejected_at TIMESTAMPTZ NOT NULL,
            reason TEXT NOT NULL CHECK (length(trim(reason)) > 0),
            replaces_confirmation BIGINT REFERENCES confirmations (id),
            replaces_rejection BIGINT REFERENCES rejections (id)
        )""",
        "CREATE INDEX rejections_seq ON rejections (seq_id, id)",
        "CREATE INDEX rejections_replaces_confirmation ON rejections (replaces_confirmation)",
        "CREATE INDEX rejections_replaces_rejection ON rejections (replaces_rejection)",
        *_refuse("rejections", "rejections are append-only"),
        "ALTER TABLE confirmations ADD COLUMN override_reason TEXT",
        "ALTER TABLE confirmations ADD COLUMN overridden_json JSONB",
        "ALTER TABLE confirmations ADD COLUMN replaces_rejection BIGINT REFERENCES rejections (id)",
        "CREATE INDEX confirmations_replaces_rejection ON confirmations (replaces_rejection)",
        _confirmations_only_supersede(("epoch", "rate_deg_s_json", "override_reason", "overridden_json",
                                       "replaces_rejection")),
    ],
    # 5: hot-pixel maps of a spacecraft's camera (one per sensor size), versioned and
    # append-only; uploads of frames by the hash of their content and parameters.
    [
        """CREATE TABLE hot_pixel_maps (
            id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
            spacecraft TEXT NOT NULL,
            sensor TEXT NOT NULL,
            version INTEGER NOT NULL,
            map_json JSONB NOT NULL,
            frames INTEGER NOT NULL,
            hot_pixels INTEGER NOT NULL,
            seq_id BIGINT REFERENCES sequences (id),
            created_at TIMESTAMPTZ NOT NULL,
            UNIQUE (spacecraft, sensor, version)
        )""",
        *_refuse("hot_pixel_maps", "hot-pixel maps are append-only"),
        """CREATE TABLE frame_uploads (
            upload_sha256 TEXT PRIMARY KEY,
            seq_id BIGINT NOT NULL REFERENCES sequences (id),
            created_at TIMESTAMPTZ NOT NULL
        )""",
        *_refuse("frame_uploads", "frame uploads are append-only"),
    ],
    # 6: the CCSDS ACM of a confirmation, rendered once at confirmation, frozen.
    [
        "ALTER TABLE confirmations ADD COLUMN acm_text TEXT",
        _confirmations_only_supersede(("epoch", "rate_deg_s_json", "override_reason", "overridden_json",
                                       "replaces_rejection", "acm_text")),
    ],
    # 7: a preview of each frame of a sequence uploaded as frames (PNG of at most
    # 2 MiB, with its overlay), one per snapshot, append-only.
    [
        """CREATE TABLE frame_previews (
            id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
            seq_id BIGINT NOT NULL REFERENCES sequences (id),
            snapshot INTEGER NOT NULL CHECK (snapshot >= 0),
            width INTEGER NOT NULL CHECK (width >= 1),
            height INTEGER NOT NULL CHECK (height >= 1),
            scale INTEGER NOT NULL CHECK (scale >= 1),
            image_width INTEGER NOT NULL CHECK (image_width >= 1),
            image_height INTEGER NOT NULL CHECK (image_height >= 1),
            png BYTEA NOT NULL CHECK (octet_length(png) <= 2097152),
            overlay_json JSONB NOT NULL,
            created_at TIMESTAMPTZ NOT NULL,
            UNIQUE (seq_id, snapshot)
        )""",
        *_refuse("frame_previews", "frame previews are append-only"),
    ],
]


# ---------------------------------------------------------------------------
# SQL and rows
# ---------------------------------------------------------------------------

@functools.lru_cache(maxsize=512)
def translate(sql: str) -> str:
    """The shared SQL (``?`` placeholders, ``IS ?`` for a null-safe comparison) in psycopg's form."""
    sql = sql.replace("%", "%%")
    sql = re.sub(r"\bIS \?", "IS NOT DISTINCT FROM ?", sql)
    return sql.replace("?", "%s")


class Row(tuple):
    """A result row readable by position and by column name, as :class:`sqlite3.Row` is."""

    __slots__ = ()
    _index: dict[str, int] = {}

    def __getitem__(self, key):
        if isinstance(key, str):
            key = self._index[key]
        return tuple.__getitem__(self, key)


@functools.lru_cache(maxsize=256)
def _row_class(names: tuple[str, ...]) -> type[Row]:
    return type("Row", (Row,), {"__slots__": (), "_index": {name: i for i, name in enumerate(names)}})


def row_factory(cursor: psycopg.Cursor):
    """psycopg's row factory making :class:`Row` objects (one class per list of column names)."""
    return _row_class(tuple(column.name for column in cursor.description or ()))


class Connection:
    """A pooled connection inside a transaction, taking the shared SQL."""

    __slots__ = ("raw",)

    def __init__(self, raw: psycopg.Connection) -> None:
        self.raw = raw

    def execute(self, sql: str, params=()) -> psycopg.Cursor:
        return self.raw.execute(translate(sql), params)


def redacted(url: str) -> str:
    """The URL without its password (for logs and :meth:`PostgresStorage.path`)."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    netloc = f"{parts.username}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


def _configure(conn: psycopg.Connection) -> None:
    """Every pooled connection: rows like sqlite3.Row, JSONB as text, times in UTC, durable commits."""
    conn.row_factory = row_factory
    conn.adapters.register_loader("jsonb", TextLoader)
    conn.adapters.register_loader("json", TextLoader)
    conn.execute("SET TIME ZONE 'UTC'")
    conn.execute("SET synchronous_commit = on")


#: When each pooled connection was last handed out; one idle longer than CHECK_AFTER_IDLE_S is checked
#: (a round trip) before use, so a restarted database server costs no request, while a busy server's
#: connections, reused within milliseconds, are not checked each time.
_LAST_USED: "weakref.WeakKeyDictionary[psycopg.Connection, float]" = weakref.WeakKeyDictionary()
CHECK_AFTER_IDLE_S = 1.0


def _check_if_idle(conn: psycopg.Connection) -> None:
    if time.monotonic() - _LAST_USED.get(conn, 0.0) > CHECK_AFTER_IDLE_S:
        ConnectionPool.check_connection(conn)


class _ContentCache:
    """Thread-safe LRU by id of what never changes: uploads' text and extraction, searches."""

    def __init__(self, size: int) -> None:
        self._size = size
        self._items: OrderedDict[int, tuple] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: int) -> tuple | None:
        with self._lock:
            item = self._items.get(key)
            if item is not None:
                self._items.move_to_end(key)
            return item

    def put(self, key: int, item: tuple) -> None:
        with self._lock:
            self._items[key] = item
            while len(self._items) > self._size:
                self._items.popitem(last=False)


# ---------------------------------------------------------------------------
# The backend
# ---------------------------------------------------------------------------

class PostgresStorage(Storage):
    """The archive in a PostgreSQL database (see the module docstring)."""

    backend = "postgresql"

    def __init__(self, pool: ConnectionPool, url: str) -> None:
        self._pool = pool
        self._url = url
        self._closed = False
        self._contents = _ContentCache(CONTENT_CACHE_SIZE)
        self._searches = _ContentCache(CONTENT_CACHE_SIZE)

    @classmethod
    def connect(cls, url: str, pool_size: int | None = None) -> "PostgresStorage":
        """Bring the schema up to date (under the migration lock) and open the pool."""
        if pool_size is None:
            from app.config import settings

            pool_size = settings().database_pool_size
        try:
            params = conninfo_to_dict(url)
        except psycopg.ProgrammingError as exc:
            raise StorageError(f"not a usable PostgreSQL URL {redacted(url)}: {exc}") from None
        params.setdefault("connect_timeout", CONNECT_TIMEOUT_S)
        params.setdefault("application_name", "starid")
        conninfo = make_conninfo(**params)
        try:
            with psycopg.connect(conninfo, autocommit=True) as conn:
                _configure(conn)
                _migrate(Connection(conn))
        except psycopg.Error as exc:
            raise StorageError(f"cannot use the PostgreSQL database {redacted(url)}: "
                               f"{str(exc).strip() or type(exc).__name__}") from None
        pool = ConnectionPool(conninfo, min_size=1, max_size=max(1, pool_size), open=False,
                              kwargs={"autocommit": True}, configure=_configure, check=_check_if_idle,
                              timeout=POOL_TIMEOUT_S, name="starid-archive")
        try:
            pool.open(wait=True, timeout=CONNECT_TIMEOUT_S + 5)
        except PoolTimeout as exc:
            pool.close()
            raise StorageError(f"cannot connect to the PostgreSQL database {redacted(url)}: {exc}") from None
        return cls(pool, url)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._pool.close()

    @property
    def path(self) -> str:
        return redacted(self._url)

    @contextmanager
    def _transaction(self, write: bool = True, snapshot: bool = False):
        if self._closed:
            raise StorageError("storage is closed")
        try:
            with self._pool.connection() as raw:
                # Writers: READ COMMITTED, each statement sees what committed before it, which the
                # row and advisory locks taken first make exactly what they need.  Readers of several
                # statements: one snapshot.  A reader of one statement needs no transaction of its own.
                _LAST_USED[raw] = time.monotonic()
                if not write and not snapshot:
                    yield Connection(raw)
                    return
                raw.execute("BEGIN" if write else "BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY")
                try:
                    yield Connection(raw)
                except BaseException:
                    if not raw.closed and not raw.broken:
                        raw.execute("ROLLBACK")
                    raise
                raw.execute("COMMIT")
        except psycopg.DataError as exc:  # e.g. a NUL character: PostgreSQL text cannot hold it
            raise UnstorableValue(f"the archive cannot store this value: {str(exc).strip()}") from None
        except (psycopg.OperationalError, psycopg.InterfaceError, PoolTimeout) as exc:
            raise StorageError(f"PostgreSQL: {str(exc).strip() or type(exc).__name__}") from None

    def _insert(self, conn: Connection, sql: str, params) -> int | None:
        row = conn.execute(f"{sql} RETURNING id", params).fetchone()
        return None if row is None else row[0]

    def _read_sequence(self, conn: Connection, column: str, value) -> SequenceRow | None:
        """The stored upload: its light columns read now, its text and extraction from this process's cache
        when there (they never change: the schema refuses it), else read once and kept."""
        row = conn.execute(f"SELECT {_SEQUENCE_LIGHT_COLUMNS} FROM sequences WHERE {column} = ?", (value,)).fetchone()
        if row is None:
            return None
        contents = self._contents.get(row["id"])
        if contents is None:
            contents = tuple(conn.execute("SELECT raw_text, extraction_json FROM sequences WHERE id = ?",
                                          (row["id"],)).fetchone())
            self._contents.put(row["id"], contents)
        full = {name: row[name] for name in row._index}
        full["raw_text"], full["extraction_json"] = contents
        return _sequence_row(full, full=True)

    def _read_search(self, conn: Connection, where: str, params) -> SearchRow | None:
        """Searches never change (append-only): their id is read now, the row from the cache when there."""
        found = conn.execute(f"SELECT id FROM searches WHERE {where}", params).fetchone()
        if found is None:
            return None
        row = self._searches.get(found[0])  # the row, so that every caller gets a record of its own
        if row is None:
            row = conn.execute("SELECT * FROM searches WHERE id = ?", (found[0],)).fetchone()
            self._searches.put(found[0], row)
        return _search_row(row)

    def _lock_sequence(self, conn: Connection, seq_id: int) -> None:
        # NO KEY UPDATE conflicts with itself (our writers queue up) but not with the KEY SHARE
        # locks that inserts of other tables' rows referencing the sequence take.
        if conn.execute("SELECT id FROM sequences WHERE id = ? FOR NO KEY UPDATE", (seq_id,)).fetchone() is None:
            raise UnknownSequence(f"no sequence with id {seq_id}")

    def _lock(self, conn: Connection, key: str) -> None:
        conn.execute("SELECT pg_advisory_xact_lock(hashtext(?))", (f"starid:{key}",))

    def _backend_facts(self, conn: Connection) -> dict:
        version, database, synchronous = conn.execute(
            "SELECT current_setting('server_version'), current_database(), current_setting('synchronous_commit')"
        ).fetchone()
        stats = self._pool.get_stats()
        return {"server_version": version, "database": database, "synchronous_commit": synchronous,
                "pool": {"size": stats.get("pool_size"), "available": stats.get("pool_available"),
                         "max": self._pool.max_size, "waiting": stats.get("requests_waiting", 0)}}


def _migrate(conn: Connection) -> None:
    """Apply the missing versions in one transaction, under the migration lock (see the module docstring)."""
    raw = conn.raw
    with raw.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(hashtext(?))", (MIGRATION_LOCK_KEY,))
        raw.execute("CREATE TABLE IF NOT EXISTS schema_version ("
                    "version INTEGER PRIMARY KEY, applied_at TIMESTAMPTZ NOT NULL)")
        current = raw.execute("SELECT COALESCE(MAX(version), 0) FROM schema_version").fetchone()[0]
        if current > len(MIGRATIONS):
            raise StorageError(f"database schema version {current} is newer than this "
                               f"program's ({len(MIGRATIONS)}); upgrade the program")
        for version in range(current + 1, len(MIGRATIONS) + 1):
            for statement in MIGRATIONS[version - 1]:
                raw.execute(statement)
            raw.execute("INSERT INTO schema_version (version, applied_at) VALUES (%s, now())", (version,))
