"""The archive's records, errors and the helpers both backends share (:mod:`app.storage`).

Rows are plain frozen dataclasses: what :class:`app.storage.Storage` returns
whatever the backend.  Times are aware UTC datetimes; JSON columns are
parsed here (SQLite keeps them as TEXT, PostgreSQL as JSONB read back as
text), so a row read from either backend is the same value.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

#: Allowed values of ``sequences.status``.
STATUSES = ("new", "identified", "ambiguous", "no_match", "confirmed", "rejected")
#: Allowed values of ``pattern_versions.kind``.
PATTERN_KINDS = ("automatic", "edit", "reset")
#: Orders of :meth:`Storage.list_sequences`: SQL of each.  ``queue`` puts what needs an operator
#: first (ambiguous, then no match, then identified but not confirmed), then what is still being
#: searched, then the sequences with a verdict; newest first within each status.
SEQUENCE_ORDERS = {
    "newest": "id DESC",
    "oldest": "id ASC",
    "queue": "CASE status WHEN 'ambiguous' THEN 0 WHEN 'no_match' THEN 1 WHEN 'identified' THEN 2 "
             "WHEN 'new' THEN 3 WHEN 'rejected' THEN 4 ELSE 5 END, id DESC",
    "time": "first_time IS NULL, first_time DESC, id DESC",
    "time_asc": "first_time IS NULL, first_time ASC, id ASC",
    "spacecraft": "spacecraft IS NULL, spacecraft, first_time DESC, id DESC",
}
#: Largest page :meth:`Storage.list_sequences` and :meth:`Storage.list_confirmations` return.
MAX_PAGE = 1000
#: Environment variable naming the database (a path, ``sqlite:///path`` or ``postgresql://...``).
DATABASE_URL_ENV = "DATABASE_URL"


#: The columns of ``confirmations`` in schema version 1 (later versions add columns).
CONFIRMATION_COLUMNS = ("id", "seq_id", "search_id", "rank", "operator", "confirmed_at", "comment", "quaternion_json",
                        "rotation_matrix_json", "ra_deg", "dec_deg", "roll_deg", "deviation_arcsec",
                        "false_match_probability", "pattern_json", "candidate_json", "apm_text", "aem_text")


class StorageError(RuntimeError):
    """The database cannot be opened or used as asked (bad URL, newer schema, ...)."""


class UnknownSequence(StorageError, LookupError):
    """A write refers to a sequence id that does not exist."""


class UnstorableValue(ValueError):
    """A value the backend cannot store (PostgreSQL text and JSONB cannot hold NUL characters)."""


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
    override_reason: str | None = None  # why the operator confirmed past a guard rail
    overridden: list[str] | None = None  # the guard rail's reasons the operator overrode
    replaces_rejection: int | None = None  # the rejection this confirmation replaced as the verdict
    withdrawn_by: int | None = None  # the rejection that withdrew this confirmation (read, never stored here)
    acm_text: str | None = None  # the CCSDS ACM rendered at confirmation (None: confirmed before ACMs)

    @property
    def is_current(self) -> bool:
        return self.superseded_by is None and self.withdrawn_by is None


@dataclass(frozen=True)
class RejectionRow:
    """An operator's verdict "no valid attitude" for a sequence, with the reason (append-only)."""

    id: int
    seq_id: int
    search_id: int | None  # the latest search when the verdict was given (None: never searched)
    operator: str
    rejected_at: datetime
    reason: str
    replaces_confirmation: int | None  # the confirmation it withdrew
    replaces_rejection: int | None  # the earlier rejection it replaced
    replaced_by_confirmation: int | None = None  # read: a later confirmation that replaced it
    replaced_by_rejection: int | None = None  # read: a later rejection that replaced it

    @property
    def is_current(self) -> bool:
        return self.replaced_by_confirmation is None and self.replaced_by_rejection is None


def verdict_key(verdict: "ConfirmationRow | RejectionRow | None") -> tuple[str, int] | None:
    """``("attitude", id)`` or ``("rejection", id)``: which verdict a caller saw, to replace that one only."""
    if verdict is None:
        return None
    return ("attitude" if isinstance(verdict, ConfirmationRow) else "rejection", verdict.id)


class VerdictExists(ValueError):
    """A confirmation or rejection without ``supersede`` on a sequence that already has a current verdict, or
    with ``replaces`` naming another verdict than the current one (another operator's came in between)."""

    def __init__(self, current: "ConfirmationRow | RejectionRow") -> None:
        super().__init__(f"sequence {current.seq_id} already has a current verdict")
        self.current = current


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


def _time(value: str | datetime | None) -> datetime | None:
    """A stored time (SQLite: the text of :func:`_time_text`; PostgreSQL: a TIMESTAMPTZ) in UTC."""
    if value is None:
        return None
    if isinstance(value, datetime):
        return value.astimezone(timezone.utc)
    return datetime.fromisoformat(value)


def _dumps(value: Any) -> str:
    # allow_nan=False: NaN/Infinity are not JSON and would not survive other readers.
    return json.dumps(value, separators=(",", ":"), allow_nan=False)


def _loads(text: str | None) -> Any:
    """A stored JSON column (text from either backend: PostgreSQL's JSONB is read back as text)."""
    return None if text is None else json.loads(text)


def _check_page(offset: int, limit: int) -> None:
    if not isinstance(offset, int) or offset < 0:
        raise ValueError("offset must be a non-negative integer")
    if not isinstance(limit, int) or not 1 <= limit <= MAX_PAGE:
        raise ValueError(f"limit must be an integer from 1 to {MAX_PAGE}")


_SEQUENCE_LIGHT_COLUMNS = ("id, content_sha256, filename, sequence_id, spacecraft, camera_json, "
                           "first_time, n_snapshots, uploaded_at, status, camera_calibration")


def _sequence_row(row, full: bool) -> SequenceRow:
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


def _pattern_row(row) -> PatternVersion:
    return PatternVersion(id=row["id"], seq_id=row["seq_id"], version=row["version"],
                          kind=row["kind"], pattern=_loads(row["pattern_json"]),
                          operator=row["operator"], created_at=_time(row["created_at"]))


def _search_row(row) -> SearchRow:
    return SearchRow(id=row["id"], seq_id=row["seq_id"], pattern_version=row["pattern_version"],
                     method=row["method"], options=_loads(row["options_json"]),
                     result_json=row["result_json"], status=row["status"],
                     created_at=_time(row["created_at"]), elapsed_s=row["elapsed_s"])


def _calibration_row(row) -> CalibrationRow:
    return CalibrationRow(id=row["id"], spacecraft=row["spacecraft"], version=row["version"],
                          camera=_loads(row["camera_json"]), result=_loads(row["result_json"]),
                          sequences=_loads(row["sequences_json"]), operator=row["operator"],
                          created_at=_time(row["created_at"]))


def _confirmation_row(row) -> ConfirmationRow:
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
        override_reason=row["override_reason"], overridden=_loads(row["overridden_json"]),
        replaces_rejection=row["replaces_rejection"], withdrawn_by=row["withdrawn_by"],
        acm_text=row["acm_text"],
    )


#: Confirmations with the rejection that withdrew each (if any): use instead of ``SELECT * FROM confirmations``.
_CONFIRMATIONS = ("SELECT c.*, (SELECT r.id FROM rejections r WHERE r.replaces_confirmation = c.id) AS withdrawn_by "
                  "FROM confirmations c")
#: The sequence's current confirmation: not superseded by a newer one, not withdrawn by a rejection.
_CURRENT_CONFIRMATION = ("c.superseded_by IS NULL AND NOT EXISTS "
                         "(SELECT 1 FROM rejections r WHERE r.replaces_confirmation = c.id)")
#: Rejections with what replaced each (if anything).
#: Select from it as ``SELECT * FROM ({_REJECTIONS}) AS rj`` (PostgreSQL wants the alias).
_REJECTIONS = ("SELECT j.*, (SELECT c.id FROM confirmations c WHERE c.replaces_rejection = j.id) "
               "AS replaced_by_confirmation, (SELECT r.id FROM rejections r WHERE r.replaces_rejection = j.id) "
               "AS replaced_by_rejection FROM rejections j")


def _rejection_row(row) -> RejectionRow:
    return RejectionRow(id=row["id"], seq_id=row["seq_id"], search_id=row["search_id"], operator=row["operator"],
                        rejected_at=_time(row["rejected_at"]), reason=row["reason"],
                        replaces_confirmation=row["replaces_confirmation"],
                        replaces_rejection=row["replaces_rejection"],
                        replaced_by_confirmation=row["replaced_by_confirmation"],
                        replaced_by_rejection=row["replaced_by_rejection"])


# -- hot-pixel map records ------------------------------------------

class StaleHotPixelMap(StorageError):
    """A hot-pixel map was computed from a version that is no longer the newest."""


@dataclass(frozen=True)
class HotPixelMapRow:
    """One version of a camera's hot-pixel map (see :mod:`app.frames.hotpixels` for ``map``)."""

    id: int
    spacecraft: str
    sensor: str
    version: int
    map: dict
    frames: int
    hot_pixels: int
    seq_id: int | None
    created_at: datetime


def _hot_pixel_map_row(row) -> HotPixelMapRow:
    return HotPixelMapRow(id=row["id"], spacecraft=row["spacecraft"], sensor=row["sensor"], version=row["version"],
                          map=_loads(row["map_json"]), frames=row["frames"], hot_pixels=row["hot_pixels"],
                          seq_id=row["seq_id"], created_at=_time(row["created_at"]))


# -- frame previews -------------------------------------------

#: Largest PNG of one frame preview the archive stores (bytes); the schema refuses larger ones too.
MAX_PREVIEW_PNG_BYTES = 2 * 1024 * 1024
#: Largest overlay document of one frame preview (bytes of its JSON).
MAX_PREVIEW_OVERLAY_BYTES = 512 * 1024
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class FramePreviewRow:
    """The stored preview of one frame of a sequence uploaded as frames.

    ``width`` x ``height``: the frame's full size (sensor pixels); the PNG (``image_width`` x
    ``image_height``) is the frame stretched to 8 bits and averaged over ``scale`` x ``scale`` blocks.
    ``overlay``: detections, rejected blobs and hot pixels in full-resolution pixels (0, 0 = centre
    of the top-left pixel).  ``png`` is None in listings (:meth:`Storage.frame_previews`).
    """

    id: int
    seq_id: int
    snapshot: int
    width: int
    height: int
    scale: int
    image_width: int
    image_height: int
    overlay: dict
    created_at: datetime
    png: bytes | None = field(default=None, repr=False)


_FRAME_PREVIEW_LIGHT_COLUMNS = ("id, seq_id, snapshot, width, height, scale, image_width, image_height, "
                                "overlay_json, created_at")


def _frame_preview_row(row, png: bool = False) -> FramePreviewRow:
    return FramePreviewRow(id=row["id"], seq_id=row["seq_id"], snapshot=row["snapshot"], width=row["width"],
                           height=row["height"], scale=row["scale"], image_width=row["image_width"],
                           image_height=row["image_height"], overlay=_loads(row["overlay_json"]),
                           created_at=_time(row["created_at"]), png=bytes(row["png"]) if png else None)


def _check_frame_preview(preview: dict) -> tuple:
    """The INSERT parameters of one preview (``snapshot``, ``width``, ``height``, ``scale``, ``image_width``,
    ``image_height``, ``png``, ``overlay``), or ValueError."""
    try:
        snapshot, width, height, scale, image_width, image_height = (
            int(preview[k]) for k in ("snapshot", "width", "height", "scale", "image_width", "image_height"))
        png, overlay = preview["png"], preview["overlay"]
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"a frame preview needs snapshot, width, height, scale, image_width, image_height, "
                         f"png and overlay ({exc})") from None
    if snapshot < 0 or min(width, height, scale, image_width, image_height) < 1:
        raise ValueError("a frame preview's snapshot must be >= 0 and its sizes and scale >= 1")
    if image_width != -(-width // scale) or image_height != -(-height // scale):
        raise ValueError(f"a {width} x {height} frame at scale {scale} is a {-(-width // scale)} x "
                         f"{-(-height // scale)} image, not {image_width} x {image_height}")
    if not isinstance(png, (bytes, bytearray, memoryview)) or not bytes(png[:8]) == _PNG_MAGIC:
        raise ValueError("a frame preview's image must be PNG bytes")
    if len(png) > MAX_PREVIEW_PNG_BYTES:
        raise ValueError(f"a frame preview's PNG is {len(png)} bytes; at most {MAX_PREVIEW_PNG_BYTES}")
    overlay_text = _dumps(overlay)
    if not isinstance(overlay, dict) or len(overlay_text.encode()) > MAX_PREVIEW_OVERLAY_BYTES:
        raise ValueError(f"a frame preview's overlay must be an object of at most {MAX_PREVIEW_OVERLAY_BYTES} bytes")
    return snapshot, width, height, scale, image_width, image_height, bytes(png), overlay_text
