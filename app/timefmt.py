"""UTC times as text: the one format the ground station writes (telemetry, API, view state).

ISO 8601 in UTC with a ``Z``: milliseconds as in the telemetry format's
examples, microseconds only when the time has sub-millisecond digits, so that
parsing the text gives back exactly the same time.  (Two formats stand apart
on purpose: the archive's fixed-width ``+00:00`` text, whose string order is
time order, in :mod:`app.storage`; and the CCSDS epoch, which the standard
writes without a zone, in :mod:`app.ccsds`.)
"""

from __future__ import annotations

from datetime import datetime, timezone


def utc_text(t: datetime | None) -> str | None:
    """``2024-05-01T12:00:00.250Z`` (None for None); naive times are taken as UTC."""
    if t is None:
        return None
    if t.tzinfo is not None:
        t = t.astimezone(timezone.utc)
    fraction = f"{t.microsecond // 1000:03d}" if t.microsecond % 1000 == 0 else f"{t.microsecond:06d}"
    return t.strftime("%Y-%m-%dT%H:%M:%S.") + fraction + "Z"


def parse_utc(text: str) -> datetime:
    """The aware UTC datetime of an ISO 8601 text (``Z`` or an offset; naive text is UTC).

    Raises ValueError for text that is not ISO 8601.
    """
    t = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    return t.replace(tzinfo=timezone.utc) if t.tzinfo is None else t.astimezone(timezone.utc)
