"""Durable storage: every upload, pattern edit, search and confirmation.

All persistence of the ground station goes through :class:`Storage`, with two
backends behind the same methods (:meth:`Storage.open` picks one):

* **SQLite** (:mod:`app.storage.sqlite`), the embedded default: one file in
  WAL mode with ``synchronous=FULL``, the writers' connection behind a lock
  and a read-only connection per concurrent reader (reads never wait for a
  write);
* **PostgreSQL** (:mod:`app.storage.postgres`, ``DATABASE_URL=postgresql://...``
  or ``--db postgresql://...``): one archive shared by several servers on
  several machines, psycopg 3 with a connection pool, row and advisory locks
  where records are numbered or superseded.

The methods and their SQL are written once (:mod:`app.storage.base`); the
records they return are the same dataclasses whatever the backend
(:mod:`app.storage.records`).

Records
-------
* ``sequences`` - one row per distinct upload (``content_sha256`` is unique;
  the same bytes uploaded twice return the existing row, even from two servers
  at once).  The original telemetry text is kept verbatim so nothing is ever
  lost.  ``status`` is the only column that changes (``new`` ->
  ``identified``/``ambiguous``/``no_match`` -> ``confirmed``/``rejected``).
* ``pattern_versions`` - append-only, numbered 1, 2, ... per sequence without
  gaps or duplicates; the current pattern is the highest version.  ``kind``
  says where it came from: ``automatic`` (extraction), ``edit`` (operator) or
  ``reset`` (the automatic pattern again, as a new version: history is never
  rewritten).
* ``searches`` - append-only results of identification runs.
* ``calibrations`` - append-only, numbered 1, 2, ... per spacecraft: a camera
  fitted over many identified sequences (who, when, from which sequences);
  an upload without a camera block is given the current one
  (``sequences.camera_calibration`` says which).
* ``confirmations`` - append-only audit records of confirmed attitudes,
  including the APM, AEM and ACM texts rendered once at confirmation so that
  their export is byte-for-byte stable.  A newer confirmation of the same
  sequence sets ``superseded_by`` on the older ones, in the same transaction;
  that is the only UPDATE ever made to this table, and triggers in the schema
  refuse any other UPDATE or any DELETE on the append-only tables.
* ``rejections`` - append-only operator verdicts "no valid attitude" with
  their reason (status ``rejected``).  A sequence has at most one current
  verdict: a new confirmation or rejection names the rejection it replaces
  (``replaces_rejection``), a rejection names the confirmation it withdraws
  (``replaces_confirmation``), both at insert, so no rejection is ever updated.
* ``hot_pixel_maps``, ``frame_uploads`` - versioned hot-pixel maps of a camera
  and the frames each sequence came from, append-only.
* ``frame_previews`` - append-only, one row per snapshot of a sequence uploaded
  as frames (schema version 7): the frame stretched to 8 bits and averaged
  over ``scale`` x ``scale`` blocks so that it is at most 1024 pixels wide,
  as a PNG of at most 2 MiB (``MAX_PREVIEW_PNG_BYTES``; the schema refuses
  larger ones), with its overlay in full-resolution pixels (detections used
  as sources, rejected blobs and why, the hot pixels of the map applied).
  The frames themselves are not kept; sequences uploaded before version 7, or
  as spot lists, have no preview.

Schema versions
---------------
``schema_version`` holds the versions applied; each backend lists the SQL of
each version in order (:data:`MIGRATIONS` is SQLite's,
:data:`app.storage.postgres.MIGRATIONS` PostgreSQL's, the same versions with
the same meaning) and applies the missing ones in one transaction when the
archive is opened.  A database newer than this code is refused.
"""

from app.storage.base import Storage, backend_of
from app.storage.records import (
    DATABASE_URL_ENV,
    MAX_PAGE,
    MAX_PREVIEW_PNG_BYTES,
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
    StorageError,
    UnknownSequence,
    UnstorableValue,
    VerdictExists,
    content_sha256,
    verdict_key,
    default_database_path,
)
from app.storage.sqlite import MIGRATIONS, SQLiteStorage

__all__ = [
    "DATABASE_URL_ENV", "MAX_PAGE", "MAX_PREVIEW_PNG_BYTES", "MIGRATIONS", "PATTERN_KINDS", "SEQUENCE_ORDERS",
    "STATUSES", "CalibrationRow", "ConfirmationRow", "FramePreviewRow", "HotPixelMapRow", "PatternVersion",
    "RejectionRow", "SQLiteStorage", "SearchRow", "SequenceRow", "StaleHotPixelMap", "Storage", "StorageError",
    "UnknownSequence", "UnstorableValue", "VerdictExists", "backend_of", "content_sha256", "default_database_path", "verdict_key",
]
