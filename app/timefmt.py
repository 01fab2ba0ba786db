"""UTC times as text: the one format the ground station writes (telemetry, API, view state).

ISO 8601 in UTC with a ``Z``: milliseconds as in the telemetry format's
examples, microseconds only when the time has sub-millisecond digits, so that
parsing the text gives back exactly the same time.  (Two formats stand apart
on purpose: the archive's fixed-width ``+00:00`` text, whose string order is
time order, in :mod:`app.storage`; and the CCSDS epoch, which the standard
writes without a zone, in :mod:`app.ccsds`.)

Reading: :func:`parse_utc` for the ground station's own text, and
:func:`parse_iso_time` for text from outside, with the reason when it is not
a time (:func:`parse_utc_time`: the same, as UTC within the supported
years).  :func:`datetime.fromisoformat` answers "second must be in 0..59" or
"day is out of range for month", and a parser that turns every such failure
into "not an ISO 8601 time" is wrong for ``2020-02-30T00:00:00Z`` (well
formed, but the date does not exist) and misleading for a leap second
(``2016-12-31T23:59:60Z`` is valid UTC).

Leap seconds are refused, on purpose: a :class:`datetime` has no 61st
second, and the archive, the sequence fit and the CCSDS exports all count
time in UTC without leap seconds.  Moving a snapshot tagged 23:59:60.x to
23:59:59.999999 or to the next second would misdate it by up to a second, put
two snapshots of a 1 Hz or faster sequence at one time (an error about
ordering that hides the cause), and skew the body rate fitted over the
sequence by the rate times that second.  A clear refusal costs one snapshot.
"""

from __future__ import annotations

import calendar
import re
import unicodedata
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



#: The example the messages give.
ISO_EXAMPLE = "1994-03-12T21:04:10.000Z"
#: The reason for a text that is not ISO 8601 at all (callers add the text itself to it).
NOT_ISO_8601 = f"not an ISO 8601 time such as {ISO_EXAMPLE}"
#: Month names in English whatever the locale (calendar.month_name follows LC_TIME).
MONTHS = ("January", "February", "March", "April", "May", "June", "July", "August", "September", "October",
          "November", "December")

# The extended layout YYYY-MM-DD[Thh[:mm[:ss[.f]]]][zone], ASCII digits only: the shape a time has
# when fromisoformat refuses it for a value (a day, an hour, a second) rather than for its form.
_LAYOUT = re.compile(
    r"(?P<year>[0-9]{4})-(?P<month>[0-9]{2})-(?P<day>[0-9]{2})"
    r"(?:[T ](?P<hour>[0-9]{2})(?::(?P<minute>[0-9]{2})(?::(?P<second>[0-9]{2})(?:[.,][0-9]+)?)?)?)?"
    r"(?:[Zz]|[+-][0-9]{2}(?::?[0-9]{2})?)?")


def parse_iso_time(text: str) -> datetime:
    """The datetime of an ISO 8601 text, naive or aware as written (callers decide the zone).

    Raises ValueError whose message says why the text is not a time
    (:func:`why_not_a_time`), so callers can put it after the location.
    """
    try:
        return datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(why_not_a_time(text)) from None


#: The years a time may lie in: where the astronomical corrections and the built-in planet ephemeris hold.
FIRST_YEAR, LAST_YEAR = 1900, 2099


def parse_utc_time(text: str) -> datetime:
    """An outside ISO 8601 text (``Z``, an offset, or none: then UTC) as an aware UTC datetime of
    :data:`FIRST_YEAR` to :data:`LAST_YEAR`: the rule of every time a caller gives besides the telemetry
    itself (a sidecar's, ``--time``, the API's ``time`` field, an EXIF time).

    Raises ValueError whose message says why, with the text when it is no time at all, so callers put
    only the location before it.
    """
    stripped = text.strip()
    try:
        t = parse_iso_time(stripped.removesuffix("Z").removesuffix("z"))
    except ValueError as exc:
        reason = str(exc)
        raise ValueError(f"{reason}: {stripped[:40]!r}" if reason == NOT_ISO_8601 else reason) from None
    try:  # an offset can carry year 1 or 9999 out of datetime's range
        t = t.replace(tzinfo=timezone.utc) if t.tzinfo is None else t.astimezone(timezone.utc)
    except OverflowError:
        t = None
    if t is None or not FIRST_YEAR <= t.year <= LAST_YEAR:
        raise ValueError(f"{stripped[:40]!r} is outside the supported years {FIRST_YEAR} to {LAST_YEAR}")
    return t


def why_not_a_time(text: str) -> str:
    """Why ``text`` is not a time: a leap second, a date or clock field that does not exist, digits
    other than ASCII ones, or (the rest) not ISO 8601 at all."""
    foreign = foreign_digit(text)
    if foreign is not None:
        return f"{NOT_ISO_8601}: it has the digit {foreign!r}; times are written with the ASCII digits 0-9"
    fields = _LAYOUT.fullmatch(text)
    return (_field_problem(text, fields) if fields else None) or NOT_ISO_8601


def foreign_digit(text: str) -> str | None:
    """The first decimal digit of another script (Arabic-Indic, fullwidth...) in ``text``: fromisoformat
    refuses it without saying why, and int() and float() read it as a digit."""
    return next((c for c in text if not c.isascii() and unicodedata.decimal(c, None) is not None), None)


def _field_problem(text: str, fields: re.Match) -> str | None:
    """The field of a well-formed time whose value does not exist, in words; None if all exist."""
    year, month, day = (int(fields[name]) for name in ("year", "month", "day"))
    if not 1 <= month <= 12:
        return f"the date {fields['year']}-{fields['month']}-{fields['day']} does not exist (months run from 01 to 12)"
    if year >= 1:
        days = calendar.monthrange(year, month)[1]
        if not 1 <= day <= days:
            return (f"the date {fields['year']}-{fields['month']}-{fields['day']} does not exist "
                    f"({MONTHS[month - 1]} {year} has {days} days)")
    for name, largest in (("hour", 23), ("minute", 59)):
        if fields[name] is not None and int(fields[name]) > largest:
            return f"{name} {fields[name]} does not exist ({name}s run from 00 to {largest})"
    second = fields["second"]
    if second == "60":
        return (f"{text.strip()} is a leap second, which is not supported: times are held in UTC without leap "
                "seconds, and moving a snapshot to a neighbouring second would misdate it by up to 1 s and skew "
                "the body rate fitted over its sequence")
    if second is not None and int(second) > 59:
        return f"second {second} does not exist (seconds run from 00 to 59, 60 only in a leap second)"
    return None
