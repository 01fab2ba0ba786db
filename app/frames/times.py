"""The time of each frame, first found: the caller's, the sidecar's, the file's own (FITS header or EXIF),
else an assumed one; and what an assumed or zone-less time costs, in words.

A frame's time places the stars (proper motion to the epoch, annual
aberration from the Earth's velocity then, up to 20.5") and the planets.
Photographs and most star-tracker test frames carry no time a program can
read, and a frame is still worth solving without one:

* **EXIF** (:func:`exif_time`): ``DateTimeOriginal`` (+ ``SubSecTimeOriginal``)
  with ``OffsetTimeOriginal``, plus half the ``ExposureTime`` (mid-exposure,
  as DATE-OBS + EXPTIME/2 in FITS).  Without an offset it is the camera's
  local time in an unknown zone: taken as UTC and said so
  (:func:`zone_note`); up to 14 hours off moves the planets (the Moon by up
  to 7 degrees) and the aberration by < 0.2", the stars not otherwise.
* **No time at all** (:func:`assumed_times`): the frames are solved at
  :data:`ASSUMED_EPOCH` (J2000.0: ``julian_year`` is exactly 2000.0 there),
  1 s apart in file-name order (HDUs and pages in theirs; not the upload's
  order, so that the same frames are the same pass), and the sequence says
  so (``time_assumed``): the stars are then placed at their mean places, proper motion to 2000.0 and
  no aberration (what star atlases and astrometry.net's WCS give; the
  apparent place is up to 20.5" away), and planets are not looked for
  (:attr:`app.telemetry.Sequence.observer`).  Attitudes are then the mean
  place's, and rates per assumed second.  A pass where some frames have a
  time and others none is refused: 1 s steps among real times would be a
  made-up time that looks like a real one.
"""

from __future__ import annotations

import math
import re
from datetime import datetime, timedelta, timezone

from app.catalogue import julian_year
from app.telemetry.errors import ImageError
from app.timefmt import parse_utc_time, utc_text

#: The time given to frames that carry none: J2000.0 (12:00 UTC: 64 s from 12:00 TT, which moves no star
#: by more than 1e-4").
ASSUMED_EPOCH = datetime(2000, 1, 1, 12, 0, 0, tzinfo=timezone.utc)
#: Between frames of an assumed time, in file order.
ASSUMED_STEP = timedelta(seconds=1)

# EXIF tags (CIPA DC-008): the Exif IFD and the capture time's parts in it.
EXIF_IFD = 0x8769
DATE_TIME_ORIGINAL = 0x9003
OFFSET_TIME_ORIGINAL = 0x9011
SUBSEC_TIME_ORIGINAL = 0x9291
EXPOSURE_TIME = 0x829A

_EXIF_DATE = re.compile(r"([0-9]{4}):([0-9]{2}):([0-9]{2}) ([0-9]{2}):([0-9]{2}):([0-9]{2})")
_EXIF_OFFSET = re.compile(r"[+-][0-9]{2}:[0-9]{2}")


def exif_time(image, location: str) -> tuple[datetime | None, str | None]:
    """``(mid-exposure UTC time, note)`` from a Pillow image's EXIF (read after its pixels: a PNG's
    ``eXIf`` chunk may follow them), ``(None, None)`` without a ``DateTimeOriginal`` or with an EXIF
    block Pillow cannot parse (a maker's odd block is no reason to refuse a frame that needs no time);
    the note says when the time had no zone and was taken as UTC.

    Raises ImageError located as ``a.jpg.exif.DateTimeOriginal`` for a value that is no time.
    """
    try:
        tags = image.getexif().get_ifd(EXIF_IFD)
    except Exception:  # noqa: BLE001 - Pillow raises many kinds for a corrupt EXIF block
        return None, None
    text = _exif_text(tags.get(DATE_TIME_ORIGINAL))
    if text is None:
        return None, None
    where = f"{location}.exif.DateTimeOriginal"
    fields = _EXIF_DATE.fullmatch(text)
    if fields is None:
        raise ImageError.at(where, f"not an EXIF time 'YYYY:MM:DD HH:MM:SS': {text[:40]!r}")
    iso = "{}-{}-{}T{}:{}:{}".format(*fields.groups())
    subsec = _exif_text(tags.get(SUBSEC_TIME_ORIGINAL))
    if subsec is not None:
        if not subsec.isascii() or not subsec.isdigit():
            raise ImageError.at(f"{location}.exif.SubSecTimeOriginal", f"must be digits, got {subsec[:40]!r}")
        iso += "." + subsec[:6]
    offset = _exif_text(tags.get(OFFSET_TIME_ORIGINAL))
    if offset is not None and not _EXIF_OFFSET.fullmatch(offset):
        raise ImageError.at(f"{location}.exif.OffsetTimeOriginal", f"not a zone '+HH:MM': {offset[:40]!r}")
    try:
        t = parse_utc_time(iso + (offset or ""))
    except ValueError as exc:
        raise ImageError.at(where, str(exc)) from None
    t += timedelta(seconds=_half_exposure(tags.get(EXPOSURE_TIME), location))
    return t, None if offset is not None else zone_note(location, text)


def _exif_text(value) -> str | None:
    """An EXIF ASCII value as text, None when absent or blank (EXIF writes spaces or colons for "unknown")."""
    if isinstance(value, bytes):
        value = value.decode("ascii", "replace")
    if not isinstance(value, str):
        return None
    text = value.strip().strip("\x00").strip()
    return text if text.strip(": 0") else None


def _half_exposure(value, location: str) -> float:
    """Half of ``ExposureTime`` (seconds): 0 when absent or unknown (0/0), refused beyond 0 to 86400 s."""
    try:
        seconds = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return 0.0
    if math.isnan(seconds):
        return 0.0
    if not 0 <= seconds <= 86400:
        raise ImageError.at(f"{location}.exif.ExposureTime", f"must be 0 to 86400 s, got {seconds:g}")
    return seconds / 2.0


def zone_note(location: str, text: str) -> str:
    """What taking a zone-less EXIF time as UTC costs."""
    return (f"{location}: the EXIF time {text} has no zone (no OffsetTimeOriginal): it is the camera's local "
            "time, taken as UTC; the hours of its zone move only the planets (the Moon by up to 7 degrees) and "
            "the aberration (by < 0.2\")")


def assumed_times(count: int) -> list[datetime]:
    """The times of ``count`` frames that carry none, in file order."""
    return [ASSUMED_EPOCH + k * ASSUMED_STEP for k in range(count)]


def mixed_times_error(untimed_location: str, timed_location: str) -> ImageError:
    """A pass where some frames have a time and others none."""
    return ImageError.at(f"{untimed_location}.time",
                         f"no time, but {timed_location} has one: give every frame of a pass its time "
                         "(in the sidecar, or DATE-OBS, or EXIF DateTimeOriginal) or none (then all are "
                         "solved at an assumed time, J2000.0 and 1 s apart)")


def time_notes(sequence) -> list[str]:
    """What an answer's reader should know of a sequence's times: the frames' own notes on them (a zone
    taken as UTC, in the ``frames`` block) and, for an assumed time, what solving without one costs."""
    frames_block = sequence.extra.get("frames")
    listed = frames_block.get("notes") if isinstance(frames_block, dict) else None
    notes = [n for n in listed if isinstance(n, str)] if isinstance(listed, list) else []
    if sequence.time_assumed:
        first = sequence.snapshots[0].time
        epoch = "J2000.0" if first == ASSUMED_EPOCH else utc_text(first)
        note = (f"no time: solved at epoch {epoch} without aberration (up to 20.5\" of apparent place), "
                f"proper motion to {julian_year(first):.1f}, planets not checked")
        if len(sequence.snapshots) > 1:
            note += ("; the snapshots' times are assumed too (frames: 1 s apart in file-name order), so rates "
                     "are per assumed second")
        notes.append(note)
    return notes
