"""The archive's interface, written once for both backends (:class:`Storage`).

Every method is one transaction and its SQL is the plain subset SQLite and
PostgreSQL share, with ``?`` placeholders (the PostgreSQL backend turns them
into ``%s``, and ``IS ?`` into ``IS NOT DISTINCT FROM %s``).  What differs
between the backends is behind five hooks:

* :meth:`Storage._transaction` - a connection inside one transaction
  (SQLite: the writers' connection under a lock with ``BEGIN IMMEDIATE``, a
  reader's own read-only connection in WAL mode;
  PostgreSQL: a pooled connection, ``READ COMMITTED`` for writers and a
  ``REPEATABLE READ READ ONLY`` snapshot for readers);
* :meth:`Storage._lock_sequence` - the sequence's row lock that numbers pattern
  versions and makes "read the current verdict, append the new one, supersede
  the old" one step (SQLite: its single writer already is one; PostgreSQL:
  ``SELECT ... FOR NO KEY UPDATE`` on the sequence's row, held to the commit,
  which serialises every server sharing the archive);
* :meth:`Storage._lock` - the same for records numbered per name
  (calibrations per spacecraft, hot-pixel maps per camera): PostgreSQL takes a
  transaction-scoped advisory lock;
* :meth:`Storage._insert` - an INSERT that gives the new row's id (None when
  ``ON CONFLICT DO NOTHING`` did nothing);
* :meth:`Storage._backend_facts` - what :meth:`Storage.health` adds.

:meth:`Storage.open` picks the backend from the target: a path or
``sqlite:///path`` (:mod:`app.storage.sqlite`) or ``postgresql://...``
(:mod:`app.storage.postgres`, imported only then).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
from datetime import datetime
from typing import Any

from app.storage.records import (
    _CONFIRMATIONS,
    _CURRENT_CONFIRMATION,
    _FRAME_PREVIEW_LIGHT_COLUMNS,
    _REJECTIONS,
    _SEQUENCE_LIGHT_COLUMNS,
    DATABASE_URL_ENV,
    PATTERN_KINDS,
    SEQUENCE_ORDERS,
    STATUSES,
    CalibrationRow,
    ConfirmationRow,
    FramePreviewRow,
    HotPixelMapRow,
    PatternVersion,
    RejectionRow,
    SearchRow,
    SequenceRow,
    StaleHotPixelMap,
    UnknownSequence,
    VerdictExists,
    verdict_key,
    _calibration_row,
    _check_frame_preview,
    _check_page,
    _confirmation_row,
    _dumps,
    _frame_preview_row,
    _hot_pixel_map_row,
    _now,
    _pattern_row,
    _rejection_row,
    _search_row,
    _sequence_row,
    _time_text,
    content_sha256,
    default_database_path,
)

#: URL schemes of PostgreSQL (libpq accepts both).
POSTGRES_SCHEMES = ("postgresql://", "postgres://")


#: A search's status for its sequence; a verdict an operator gave stands until an operator supersedes it.
_SEARCH_STATUS = "UPDATE sequences SET status = ? WHERE id = ? AND status NOT IN ('confirmed', 'rejected')"


def _check_replaced(current: ConfirmationRow | RejectionRow | None, supersede: bool,
                    replaces: tuple[str, int] | None) -> None:
    """Raise :class:`VerdictExists` unless a new verdict may follow ``current`` (in the caller's transaction):
    with no current verdict, or with ``supersede`` and, when ``replaces`` names the verdict the operator saw,
    that one still current."""
    if current is None:
        if replaces is not None:
            raise ValueError(f"{replaces[0]} {replaces[1]} is no verdict of this sequence")
        return
    if not supersede or (replaces is not None and verdict_key(current) != tuple(replaces)):
        raise VerdictExists(current)


def backend_of(target: str) -> str:
    """``"postgresql"`` for a PostgreSQL URL, ``"sqlite"`` for anything else (a path or ``sqlite:///``)."""
    return "postgresql" if target.startswith(POSTGRES_SCHEMES) else "sqlite"


class Storage:
    """The archive.  Open with :meth:`open`; every method is one transaction.

    Reads of unknown ids return None; writes that name an unknown sequence
    raise :class:`UnknownSequence`; bad argument values raise ValueError.
    """

    #: "sqlite" or "postgresql" (set by each backend).
    backend = "?"

    # -- life cycle ---------------------------------------------------------

    @classmethod
    def open(cls, path_or_url: str | os.PathLike | None = None) -> "Storage":
        """Open (creating if needed) the database and bring its schema up to date.

        ``path_or_url``: a file path or ``sqlite:///path`` (SQLite), or
        ``postgresql://user:password@host:port/database`` (PostgreSQL); None
        means ``$DATABASE_URL`` or :func:`default_database_path`.
        """
        if path_or_url is None:
            path_or_url = os.environ.get(DATABASE_URL_ENV) or default_database_path()
        target = os.fspath(path_or_url)
        if backend_of(target) == "postgresql":
            # Imported only for a PostgreSQL URL: the embedded default never loads psycopg.
            return importlib.import_module("app.storage.postgres").PostgresStorage.connect(target)
        return importlib.import_module("app.storage.sqlite").SQLiteStorage.connect(target)

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> "Storage":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    @property
    def path(self) -> str:
        """The database: a file path, or a PostgreSQL URL without its password."""
        raise NotImplementedError

    # -- the backend's hooks (see the module docstring) -----------------------

    def _transaction(self, write: bool = True, snapshot: bool = False):
        """A connection in one transaction: a writer's, or a reader's (``snapshot``: its statements see one
        state of the archive; a reader of one statement needs none)."""
        raise NotImplementedError

    def _insert(self, conn, sql: str, params) -> int | None:
        raise NotImplementedError

    def _lock_sequence(self, conn, seq_id: int) -> None:
        """Serialise writers of this sequence until the commit; UnknownSequence if it does not exist."""
        self._require_sequence(conn, seq_id)

    def _lock(self, conn, key: str) -> None:
        """Serialise writers of the records named ``key`` until the commit."""

    def _backend_facts(self, conn) -> dict:
        return {}

    def _read_search(self, conn, where: str, params) -> SearchRow | None:
        """The search ``SELECT ... FROM searches WHERE <where>`` finds (searches never change)."""
        row = conn.execute(f"SELECT * FROM searches WHERE {where}", params).fetchone()
        return None if row is None else _search_row(row)

    def _read_sequence(self, conn, column: str, value) -> SequenceRow | None:
        """The whole stored upload whose ``column`` ("id" or "content_sha256") is ``value``."""
        row = conn.execute(f"SELECT * FROM sequences WHERE {column} = ?", (value,)).fetchone()
        return None if row is None else _sequence_row(row, full=True)

    @staticmethod
    def _require_sequence(conn, seq_id: int) -> None:
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
            # The same content from two servers at once: one insert wins, the other does nothing
            # (PostgreSQL waits for the winner's commit) and both read the stored row.
            new_id = self._insert(
                conn,
                "INSERT INTO sequences (content_sha256, filename, sequence_id, spacecraft, camera_json, "
                "first_time, n_snapshots, raw_text, uploaded_at, extraction_json, status, camera_calibration) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (content_sha256) DO NOTHING",
                (digest, filename, sequence_id, spacecraft,
                 None if camera is None else _dumps(camera), _time_text(first_time), n_snapshots,
                 raw_text, _time_text(uploaded_at or _now()),
                 None if extraction is None else _dumps(extraction), status, camera_calibration))
            created = new_id is not None
            row = self._read_sequence(conn, "content_sha256", digest)
        return row, created

    def find_sequence(self, content_sha256: str) -> SequenceRow | None:
        """The stored sequence with this content digest (:func:`content_sha256`), if any."""
        with self._transaction(write=False) as conn:
            return self._read_sequence(conn, "content_sha256", content_sha256)

    def get_sequence(self, seq_id: int) -> SequenceRow | None:
        with self._transaction(write=False) as conn:
            return self._read_sequence(conn, "id", seq_id)

    def list_sequences(self, offset: int = 0, limit: int = 50, *, spacecraft: str | None = None,
                       status: str | None = None, search: str | None = None,
                       order: str = "newest") -> tuple[list[SequenceRow], int]:
        """A page of uploads in ``order`` (:data:`SEQUENCE_ORDERS`; newest first by default) and the
        total number matching the filters; ``search`` matches part of the sequence id or file name
        (case-insensitive) or the archive id."""
        _check_page(offset, limit)
        if order not in SEQUENCE_ORDERS:
            raise ValueError(f"order must be one of {tuple(SEQUENCE_ORDERS)}")
        where, params = [], []
        if spacecraft is not None:
            where.append("spacecraft = ?")
            params.append(spacecraft)
        if status is not None:
            where.append("status = ?")
            params.append(status)
        if search:
            pattern = "%" + search.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_") + "%"
            where.append("(lower(sequence_id) LIKE lower(?) ESCAPE '\\' OR lower(filename) LIKE lower(?) ESCAPE '\\' "
                         "OR CAST(id AS TEXT) = ?)")
            params += [pattern, pattern, search.strip().lstrip("#")]
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        with self._transaction(write=False, snapshot=True) as conn:
            total = conn.execute(f"SELECT COUNT(*) FROM sequences{clause}", params).fetchone()[0]
            rows = conn.execute(f"SELECT {_SEQUENCE_LIGHT_COLUMNS} FROM sequences{clause} "
                                f"ORDER BY {SEQUENCE_ORDERS[order]} LIMIT ? OFFSET ?",
                                [*params, limit, offset]).fetchall()
        return [_sequence_row(r, full=False) for r in rows], total

    def same_sequence_uploads(self, spacecraft: str | None, sequence_id: str | None, *,
                              other_than: int | None = None) -> list[tuple[int, str | None]]:
        """(id, file name) of the stored uploads of this spacecraft and sequence id, oldest first (None
        matches None), leaving out ``other_than``.

        Uploads are told apart by their exact content (:func:`content_sha256`), so the same telemetry
        sent again with other line endings or a byte-order mark is a second sequence; this says which
        sequences it shares its names with.  ``= ?`` rather than a null-safe ``IS ?``: an index serves
        the equality on both backends, ``IS NOT DISTINCT FROM`` none on PostgreSQL.
        """
        where, params = [], []
        for column, value in (("spacecraft", spacecraft), ("sequence_id", sequence_id)):
            if value is None:
                where.append(f"{column} IS NULL")
            else:
                where.append(f"{column} = ?")
                params.append(value)
        if other_than is not None:
            where.append("id <> ?")
            params.append(other_than)
        with self._transaction(write=False) as conn:
            rows = conn.execute(f"SELECT id, filename FROM sequences WHERE {' AND '.join(where)} ORDER BY id",
                                params).fetchall()
        return [(r[0], r[1]) for r in rows]

    def spacecraft_names(self) -> list[tuple[str | None, int]]:
        """Every spacecraft name in the archive (None: files without one) with its number of sequences."""
        with self._transaction(write=False) as conn:
            rows = conn.execute("SELECT spacecraft, COUNT(*) FROM sequences GROUP BY spacecraft "
                                "ORDER BY spacecraft IS NULL, spacecraft").fetchall()
        return [(r[0], r[1]) for r in rows]

    def timeline_rows(self, spacecraft: str, start: datetime | None, end: datetime | None, limit: int,
                      ) -> tuple[list[tuple[SequenceRow, SearchRow | None, ConfirmationRow | RejectionRow | None]], int]:
        """The newest ``limit`` uploads of ``spacecraft`` whose first snapshot's time lies in [start, end) (None:
        open), oldest first, each with its raw text (its snapshots' times; ``extraction`` left out), newest
        search and current verdict (as :meth:`current_verdict`); and how many uploads the range holds.

        One snapshot of the archive and five statements whatever ``limit`` (at most :data:`MAX_PAGE`): what a
        spacecraft's attitude timeline reads (:mod:`app.workflow.timeline`).  Uploads without a time
        (``first_time`` null: frames that carried none) lie in no range.
        """
        _check_page(0, limit)
        where, params = ["spacecraft = ?", "first_time IS NOT NULL"], [spacecraft]
        for bound, op in ((start, ">="), (end, "<")):
            if bound is not None:
                where.append(f"first_time {op} ?")
                params.append(_time_text(bound))
        clause = " AND ".join(where)
        with self._transaction(write=False, snapshot=True) as conn:
            total = conn.execute(f"SELECT COUNT(*) FROM sequences WHERE {clause}", params).fetchone()[0]
            found = conn.execute(f"SELECT {_SEQUENCE_LIGHT_COLUMNS}, raw_text FROM sequences WHERE {clause} "
                                 "ORDER BY first_time DESC, id DESC LIMIT ?", [*params, limit]).fetchall()
            ids = [r["id"] for r in found]
            marks = ", ".join("?" * len(ids)) or "NULL"
            searches = {s.seq_id: s for s in map(_search_row, conn.execute(
                f"SELECT * FROM searches WHERE id IN (SELECT MAX(id) FROM searches WHERE seq_id IN ({marks}) "
                "GROUP BY seq_id)", ids).fetchall())}
            # Oldest first, so that the newest current one of a sequence is the one kept.
            verdicts: dict[int, ConfirmationRow | RejectionRow] = {
                r.seq_id: r for r in map(_rejection_row, conn.execute(
                    f"SELECT * FROM ({_REJECTIONS}) AS rj WHERE seq_id IN ({marks}) AND replaced_by_confirmation "
                    "IS NULL AND replaced_by_rejection IS NULL ORDER BY id", ids).fetchall())}
            # A current confirmation is the verdict before any rejection (as _current_verdict reads them).
            verdicts.update({c.seq_id: c for c in map(_confirmation_row, conn.execute(
                f"{_CONFIRMATIONS} WHERE c.seq_id IN ({marks}) AND {_CURRENT_CONFIRMATION} ORDER BY c.id",
                ids).fetchall())})
        rows = [dataclasses.replace(_sequence_row(r, full=False), raw_text=r["raw_text"]) for r in reversed(found)]
        return [(row, searches.get(row.id), verdicts.get(row.id)) for row in rows], total

    def set_status(self, seq_id: int, status: str) -> SequenceRow:
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}")
        with self._transaction() as conn:
            self._lock_sequence(conn, seq_id)
            conn.execute("UPDATE sequences SET status = ? WHERE id = ?", (status, seq_id))
            return self._read_sequence(conn, "id", seq_id)

    # -- patterns -----------------------------------------------------------

    def add_pattern_version(self, seq_id: int, pattern: dict, *, kind: str = "edit",
                            operator: str | None = None) -> PatternVersion:
        """Append the next version of a sequence's pattern (1 for the first)."""
        if kind not in PATTERN_KINDS:
            raise ValueError(f"kind must be one of {PATTERN_KINDS}")
        with self._transaction() as conn:
            # Numbered under the sequence's lock: no gap, no duplicate, whichever server writes.
            self._lock_sequence(conn, seq_id)
            version = conn.execute("SELECT COALESCE(MAX(version), 0) + 1 FROM pattern_versions "
                                   "WHERE seq_id = ?", (seq_id,)).fetchone()[0]
            new_id = self._insert(
                conn,
                "INSERT INTO pattern_versions (seq_id, version, kind, pattern_json, operator, created_at) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (seq_id, version, kind, _dumps(pattern), operator, _time_text(_now())))
            row = conn.execute("SELECT * FROM pattern_versions WHERE id = ?", (new_id,)).fetchone()
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
        """Append a search and, in the same transaction, give the sequence its status (unless an operator's
        verdict stands: :meth:`set_search_status`).  One write: a reader never sees the new search beside
        the status of none (a console showed "new" beside identified candidates, and its polling, seeing no
        new search, never read it again), and a confirmation landing in between is never overwritten."""
        with self._transaction() as conn:
            # Under the sequence's lock too, so that the newest search is also the last one committed.
            self._lock_sequence(conn, seq_id)
            new_id = self._insert(
                conn, "INSERT INTO searches (seq_id, pattern_version, method, options_json, result_json, "
                "status, created_at, elapsed_s) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (seq_id, pattern_version, method, _dumps(options), _dumps(result), status,
                 _time_text(_now()), elapsed_s))
            if status in STATUSES:
                conn.execute(_SEARCH_STATUS, (status, seq_id))
            row = conn.execute("SELECT * FROM searches WHERE id = ?", (new_id,)).fetchone()
        return _search_row(row)

    def set_search_status(self, seq_id: int, status: str) -> SequenceRow:
        """The status a search gives the sequence, unless an operator's verdict (confirmed, rejected) stands."""
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}")
        with self._transaction() as conn:
            self._lock_sequence(conn, seq_id)
            conn.execute(_SEARCH_STATUS, (status, seq_id))
            return self._read_sequence(conn, "id", seq_id)

    def get_search(self, search_id: int) -> SearchRow | None:
        with self._transaction(write=False) as conn:
            return self._read_search(conn, "id = ?", (search_id,))

    def latest_search(self, seq_id: int) -> SearchRow | None:
        with self._transaction(write=False) as conn:
            return self._read_search(conn, "seq_id = ? ORDER BY id DESC LIMIT 1", (seq_id,))

    # -- confirmations ------------------------------------------------------

    def add_confirmation(self, seq_id: int, *, search_id: int | None, rank: int, operator: str,
                         quaternion: list[float], rotation_matrix: list[list[float]],
                         ra_deg: float, dec_deg: float, roll_deg: float,
                         deviation_arcsec: float | None, false_match_probability: float | None,
                         pattern: dict, candidate: dict, apm_text: str, aem_text: str | None = None,
                         comment: str | None = None, confirmed_at: datetime | None = None,
                         epoch: datetime | None = None, rate_deg_s: list[float] | None = None,
                         override_reason: str | None = None, overridden: list[str] | None = None,
                         supersede: bool = True, acm_text: str | None = None,
                         replaces: tuple[str, int] | None = None) -> ConfirmationRow:
        """Append a confirmation; in the same transaction make it the sequence's
        verdict (the earlier current confirmation is marked superseded by it, a
        current rejection is named as replaced) and set the status ``confirmed``.

        With ``supersede`` False, a sequence that already has a current verdict
        raises :class:`VerdictExists` (carrying it) and nothing is written: the
        check and the write are one transaction, so two operators confirming at
        once cannot both succeed.  With ``replaces`` (:func:`verdict_key` of the
        verdict the operator saw), it is replaced only if it is still the
        current one: another operator's verdict in between raises too.
        """
        if not operator:
            raise ValueError("a confirmation needs an operator")
        if not apm_text:
            raise ValueError("a confirmation needs its APM text")
        with self._transaction() as conn:
            # The sequence's lock makes "read the current verdict, append the new one, supersede the
            # old" one step for every server sharing the archive.
            self._lock_sequence(conn, seq_id)
            current = self._current_verdict(conn, seq_id)
            _check_replaced(current, supersede, replaces)
            replaced_rejection = current.id if isinstance(current, RejectionRow) else None
            new_id = self._insert(
                conn, "INSERT INTO confirmations (seq_id, search_id, rank, operator, confirmed_at, comment, "
                "quaternion_json, rotation_matrix_json, ra_deg, dec_deg, roll_deg, deviation_arcsec, "
                "false_match_probability, pattern_json, candidate_json, apm_text, aem_text, epoch, "
                "rate_deg_s_json, override_reason, overridden_json, replaces_rejection, acm_text) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (seq_id, search_id, int(rank), operator, _time_text(confirmed_at or _now()), comment,
                 _dumps([float(v) for v in quaternion]),
                 _dumps([[float(v) for v in row] for row in rotation_matrix]),
                 float(ra_deg), float(dec_deg), float(roll_deg),
                 None if deviation_arcsec is None else float(deviation_arcsec),
                 None if false_match_probability is None else float(false_match_probability),
                 _dumps(pattern), _dumps(candidate), apm_text, aem_text, _time_text(epoch),
                 None if rate_deg_s is None else _dumps([float(w) for w in rate_deg_s]),
                 override_reason, None if overridden is None else _dumps(list(overridden)), replaced_rejection,
                 acm_text))
            # Only the current confirmation is superseded: one withdrawn by a rejection stays as it was.
            conn.execute(f"UPDATE confirmations AS c SET superseded_by = ? "
                         f"WHERE c.seq_id = ? AND c.id < ? AND {_CURRENT_CONFIRMATION}",
                         (new_id, seq_id, new_id))
            conn.execute("UPDATE sequences SET status = 'confirmed' WHERE id = ?", (seq_id,))
            row = conn.execute(f"{_CONFIRMATIONS} WHERE c.id = ?", (new_id,)).fetchone()
        return _confirmation_row(row)

    def get_confirmation(self, confirmation_id: int) -> ConfirmationRow | None:
        with self._transaction(write=False) as conn:
            row = conn.execute(f"{_CONFIRMATIONS} WHERE c.id = ?", (confirmation_id,)).fetchone()
        return None if row is None else _confirmation_row(row)

    def list_confirmations(self, offset: int = 0, limit: int = 50,
                           ) -> tuple[list[ConfirmationRow], int]:
        """A page of all confirmations (superseded ones included), newest first, and the total."""
        _check_page(offset, limit)
        with self._transaction(write=False, snapshot=True) as conn:
            total = conn.execute("SELECT COUNT(*) FROM confirmations").fetchone()[0]
            rows = conn.execute(f"{_CONFIRMATIONS} ORDER BY c.id DESC LIMIT ? OFFSET ?",
                                (limit, offset)).fetchall()
        return [_confirmation_row(r) for r in rows], total

    def current_confirmation(self, seq_id: int) -> ConfirmationRow | None:
        """The sequence's current confirmation (neither superseded nor withdrawn by a rejection), if any."""
        with self._transaction(write=False) as conn:
            row = conn.execute(f"{_CONFIRMATIONS} WHERE c.seq_id = ? AND {_CURRENT_CONFIRMATION} "
                               "ORDER BY c.id DESC LIMIT 1", (seq_id,)).fetchone()
        return None if row is None else _confirmation_row(row)

    def latest_confirmation_of_spacecraft(self, spacecraft: str | None) -> ConfirmationRow | None:
        """The newest current confirmation of any sequence of ``spacecraft`` (None: of unnamed spacecraft)."""
        with self._transaction(write=False) as conn:
            row = conn.execute(f"{_CONFIRMATIONS} JOIN sequences s ON s.id = c.seq_id "
                               f"WHERE {_CURRENT_CONFIRMATION} AND s.spacecraft IS ? ORDER BY c.id DESC LIMIT 1",
                               (spacecraft,)).fetchone()
        return None if row is None else _confirmation_row(row)

    def confirmation_history(self, seq_id: int) -> list[ConfirmationRow]:
        """Every confirmation of a sequence, oldest first (the audit trail)."""
        with self._transaction(write=False) as conn:
            rows = conn.execute(f"{_CONFIRMATIONS} WHERE c.seq_id = ? ORDER BY c.id",
                                (seq_id,)).fetchall()
        return [_confirmation_row(r) for r in rows]

    def current_confirmations(self, spacecraft: str | None, start: datetime | None = None,
                              end: datetime | None = None) -> list[ConfirmationRow]:
        """The current confirmations of ``spacecraft``'s sequences whose epoch lies in [start, end)
        (an open end when None), oldest epoch first: what a bulk AEM export holds."""
        where, params = [_CURRENT_CONFIRMATION, "s.spacecraft IS ?"], [spacecraft]
        if start is not None:
            where.append("c.epoch >= ?")
            params.append(_time_text(start))
        if end is not None:
            where.append("c.epoch < ?")
            params.append(_time_text(end))
        with self._transaction(write=False) as conn:
            rows = conn.execute(f"{_CONFIRMATIONS} JOIN sequences s ON s.id = c.seq_id WHERE "
                                f"{' AND '.join(where)} ORDER BY c.epoch, c.id", params).fetchall()
        return [_confirmation_row(r) for r in rows]

    # -- rejections (operator verdict "no valid attitude") ---------------------

    @staticmethod
    def _current_verdict(conn, seq_id: int) -> "ConfirmationRow | RejectionRow | None":
        row = conn.execute(f"{_CONFIRMATIONS} WHERE c.seq_id = ? AND {_CURRENT_CONFIRMATION} "
                           "ORDER BY c.id DESC LIMIT 1", (seq_id,)).fetchone()
        if row is not None:
            return _confirmation_row(row)
        row = conn.execute(f"SELECT * FROM ({_REJECTIONS}) AS rj WHERE seq_id = ? AND replaced_by_confirmation IS NULL "
                           "AND replaced_by_rejection IS NULL ORDER BY id DESC LIMIT 1", (seq_id,)).fetchone()
        return None if row is None else _rejection_row(row)

    def current_verdict(self, seq_id: int) -> ConfirmationRow | RejectionRow | None:
        """The sequence's current verdict: its current confirmation or rejection, or None."""
        with self._transaction(write=False, snapshot=True) as conn:
            return self._current_verdict(conn, seq_id)

    def add_rejection(self, seq_id: int, *, operator: str, reason: str, search_id: int | None = None,
                      supersede: bool = False, rejected_at: datetime | None = None,
                      replaces: tuple[str, int] | None = None) -> RejectionRow:
        """Append the verdict "no valid attitude" and set the status ``rejected``; the current verdict,
        if any, is named as replaced (with ``supersede`` False, or ``replaces`` naming another verdict, it
        raises :class:`VerdictExists`: see :meth:`add_confirmation`)."""
        if not operator or not operator.strip():
            raise ValueError("a rejection needs an operator")
        if not reason or not reason.strip():
            raise ValueError("a rejection needs a reason")
        with self._transaction() as conn:
            self._lock_sequence(conn, seq_id)
            current = self._current_verdict(conn, seq_id)
            _check_replaced(current, supersede, replaces)
            new_id = self._insert(
                conn,
                "INSERT INTO rejections (seq_id, search_id, operator, rejected_at, reason, replaces_confirmation, "
                "replaces_rejection) VALUES (?, ?, ?, ?, ?, ?, ?)",
                (seq_id, search_id, operator, _time_text(rejected_at or _now()), reason,
                 current.id if isinstance(current, ConfirmationRow) else None,
                 current.id if isinstance(current, RejectionRow) else None))
            conn.execute("UPDATE sequences SET status = 'rejected' WHERE id = ?", (seq_id,))
            row = conn.execute(f"SELECT * FROM ({_REJECTIONS}) AS rj WHERE id = ?", (new_id,)).fetchone()
        return _rejection_row(row)

    def get_rejection(self, rejection_id: int) -> RejectionRow | None:
        with self._transaction(write=False) as conn:
            row = conn.execute(f"SELECT * FROM ({_REJECTIONS}) AS rj WHERE id = ?", (rejection_id,)).fetchone()
        return None if row is None else _rejection_row(row)

    def rejection_history(self, seq_id: int) -> list[RejectionRow]:
        """Every rejection of a sequence, oldest first (with :meth:`confirmation_history`: the audit trail)."""
        with self._transaction(write=False) as conn:
            rows = conn.execute(f"SELECT * FROM ({_REJECTIONS}) AS rj WHERE seq_id = ? ORDER BY id", (seq_id,)).fetchall()
        return [_rejection_row(r) for r in rows]

    # -- calibrations -------------------------------------------------------

    def add_calibration(self, spacecraft: str, *, camera: dict, result: dict, sequences: list[int],
                        operator: str | None = None) -> CalibrationRow:
        """Append the next calibration version of ``spacecraft``'s camera (1 for the first)."""
        if not spacecraft:
            raise ValueError("a calibration needs a spacecraft")
        with self._transaction() as conn:
            self._lock(conn, f"calibrations:{spacecraft}")  # versions without gaps or duplicates
            version = conn.execute("SELECT COALESCE(MAX(version), 0) + 1 FROM calibrations WHERE spacecraft = ?",
                                   (spacecraft,)).fetchone()[0]
            new_id = self._insert(
                conn,
                "INSERT INTO calibrations (spacecraft, version, camera_json, result_json, sequences_json, operator, "
                "created_at) VALUES (?, ?, ?, ?, ?, ?, ?)",
                (spacecraft, version, _dumps(camera), _dumps(result), _dumps([int(s) for s in sequences]),
                 operator, _time_text(_now())))
            row = conn.execute("SELECT * FROM calibrations WHERE id = ?", (new_id,)).fetchone()
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
        """Backend, schema version, row counts and the backend's own facts; ``ok`` False if the database fails."""
        try:
            with self._transaction(write=False, snapshot=True) as conn:
                version = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()[0]
                counts = {table: conn.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
                          for table in ("sequences", "pattern_versions", "searches", "confirmations",
                                        "calibrations")}
                facts = self._backend_facts(conn)
        except Exception as exc:  # noqa: BLE001 - any failure of the database is reported, not raised
            return {"ok": False, "backend": self.backend, "path": self.path, "error": str(exc)}
        return {"ok": True, "backend": self.backend, "path": self.path, "schema_version": version,
                **facts, "counts": counts}

    # -- hot-pixel maps and frame uploads -------------------------

    def add_hot_pixel_map(self, spacecraft: str, sensor: str, *, map_doc: dict, frames: int, hot_pixels: int,
                          based_on: int | None, seq_id: int | None = None) -> "HotPixelMapRow":
        """Append the next version of ``spacecraft``'s hot-pixel map for a ``sensor`` ("WIDTHxHEIGHT").

        ``based_on`` is the version the new map was computed from (None: none existed); when another
        version was stored meanwhile :class:`StaleHotPixelMap` is raised and nothing is written, so
        the caller merges again (two uploads at once never lose each other's frames).
        """
        if not spacecraft:
            raise ValueError("a hot-pixel map needs a spacecraft")
        with self._transaction() as conn:
            self._lock(conn, f"hot_pixel_maps:{spacecraft}:{sensor}")
            latest = conn.execute("SELECT MAX(version) FROM hot_pixel_maps WHERE spacecraft = ? AND sensor = ?",
                                  (spacecraft, sensor)).fetchone()[0]
            if latest != based_on:
                raise StaleHotPixelMap(f"hot-pixel map of {spacecraft} {sensor} is at version {latest}, "
                                       f"not {based_on}")
            new_id = self._insert(
                conn, "INSERT INTO hot_pixel_maps (spacecraft, sensor, version, map_json, frames, hot_pixels, seq_id, "
                "created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (spacecraft, sensor, (latest or 0) + 1, _dumps(map_doc), int(frames), int(hot_pixels), seq_id,
                 _time_text(_now())))
            row = conn.execute("SELECT * FROM hot_pixel_maps WHERE id = ?", (new_id,)).fetchone()
        return _hot_pixel_map_row(row)

    def current_hot_pixel_map(self, spacecraft: str | None, sensor: str) -> "HotPixelMapRow | None":
        """The newest hot-pixel map of ``spacecraft``'s camera of this sensor size, if any."""
        if spacecraft is None:
            return None
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT * FROM hot_pixel_maps WHERE spacecraft = ? AND sensor = ? "
                               "ORDER BY version DESC LIMIT 1", (spacecraft, sensor)).fetchone()
        return None if row is None else _hot_pixel_map_row(row)

    def hot_pixel_map_history(self, spacecraft: str, sensor: str) -> "list[HotPixelMapRow]":
        """Every version of the map, oldest first."""
        with self._transaction(write=False) as conn:
            rows = conn.execute("SELECT * FROM hot_pixel_maps WHERE spacecraft = ? AND sensor = ? ORDER BY version",
                                (spacecraft, sensor)).fetchall()
        return [_hot_pixel_map_row(r) for r in rows]

    def add_frame_upload(self, upload_sha256: str, seq_id: int) -> int:
        """Record that frames with this upload hash became sequence ``seq_id``; returns the recorded
        sequence (the first one recorded, when the same frames were stored twice at once)."""
        with self._transaction() as conn:
            self._require_sequence(conn, seq_id)
            conn.execute("INSERT INTO frame_uploads (upload_sha256, seq_id, created_at) VALUES (?, ?, ?) "
                         "ON CONFLICT (upload_sha256) DO NOTHING", (upload_sha256, seq_id, _time_text(_now())))
            return conn.execute("SELECT seq_id FROM frame_uploads WHERE upload_sha256 = ?",
                                (upload_sha256,)).fetchone()[0]

    def find_frame_upload(self, upload_sha256: str) -> int | None:
        """The sequence that frames with this upload hash became, if they were uploaded before."""
        with self._transaction(write=False) as conn:
            row = conn.execute("SELECT seq_id FROM frame_uploads WHERE upload_sha256 = ?",
                               (upload_sha256,)).fetchone()
        return None if row is None else int(row[0])

    # -- frame previews -------------------------------------

    def add_frame_previews(self, seq_id: int, previews: list[dict]) -> int:
        """Store the previews of a sequence's frames (each a dict: ``snapshot``, ``width``, ``height``,
        ``scale``, ``image_width``, ``image_height``, ``png`` bytes, ``overlay``), all in one transaction.

        Append-only: a snapshot that has a preview keeps it (the first stored wins, so the same frames
        uploaded twice at once store one set).  Returns how many were stored now.  ValueError (nothing
        stored) for a preview that is not one (:func:`app.storage.records._check_frame_preview`: PNG
        bytes of at most :data:`app.storage.records.MAX_PREVIEW_PNG_BYTES`, sizes that agree).
        """
        rows = [_check_frame_preview(p) for p in previews]
        if len({r[0] for r in rows}) != len(rows):
            raise ValueError("two previews of the same snapshot")
        stored = 0
        with self._transaction() as conn:
            self._require_sequence(conn, seq_id)
            now = _time_text(_now())
            for snapshot, width, height, scale, image_width, image_height, png, overlay in rows:
                new_id = self._insert(
                    conn, "INSERT INTO frame_previews (seq_id, snapshot, width, height, scale, image_width, "
                    "image_height, png, overlay_json, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) "
                    "ON CONFLICT (seq_id, snapshot) DO NOTHING",
                    (seq_id, snapshot, width, height, scale, image_width, image_height, png, overlay, now))
                stored += new_id is not None
        return stored

    def frame_previews(self, seq_id: int) -> "list[FramePreviewRow]":
        """The previews of a sequence's frames without their PNGs, by snapshot (empty: none kept)."""
        with self._transaction(write=False) as conn:
            rows = conn.execute(f"SELECT {_FRAME_PREVIEW_LIGHT_COLUMNS} FROM frame_previews WHERE seq_id = ? "
                                "ORDER BY snapshot", (seq_id,)).fetchall()
        return [_frame_preview_row(r) for r in rows]

    def frame_preview(self, seq_id: int, snapshot: int) -> "FramePreviewRow | None":
        """One snapshot's preview with its PNG, if kept."""
        with self._transaction(write=False) as conn:
            row = conn.execute(f"SELECT {_FRAME_PREVIEW_LIGHT_COLUMNS}, png FROM frame_previews "
                               "WHERE seq_id = ? AND snapshot = ?", (seq_id, snapshot)).fetchone()
        return None if row is None else _frame_preview_row(row, png=True)
