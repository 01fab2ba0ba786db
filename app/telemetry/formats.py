"""Reading and writing `tubsat-snapshots/1` telemetry: the JSON and the CSV form.

:func:`parse_telemetry` is the single gate between untrusted bytes and a
:class:`~app.telemetry.model.Sequence`.  Whatever it is given, it either
returns a Sequence whose every number is finite, whose sources lie on the
sensor and whose snapshot times strictly increase, or raises
:class:`~app.telemetry.errors.TelemetryError` listing the problems found.

Form detection: the first non-blank character ``{`` or ``[`` (or a file name
ending in ``.json``) means JSON, anything else is read as CSV.  The full
description of both forms, with examples, is in ``docs/formats.md``.

Choices made here (documented there too):

* Top-level JSON keys this format does not define are kept in
  ``Sequence.extra`` (newer writers may add metadata); unknown keys inside
  ``camera``, a snapshot or a source are errors, since there a typo such as
  ``"k_1"`` would silently change the geometry.
* Integers must be written as integers (``752``, not ``752.0``); JSON
  ``true`` is not a number.
* CSV columns may come in any order; extra columns are ignored (spreadsheet
  exports add them).  Rows of one snapshot must be contiguous.
* Times must lie in 1900..2099 UTC, where the astronomical corrections and
  the built-in planet ephemeris are valid.  ``time_assumed: true`` says they
  are not known (frames that carried none): the stars are then placed
  without aberration and planets are not looked for
  (:attr:`~app.telemetry.model.Sequence.observer`).
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import sys
import unicodedata
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

import numpy as np

from app.camera import CAMERAS, Camera, fold_radius
from app.config import MAX_SNAPSHOTS, MAX_SOURCES_PER_SNAPSHOT, settings
from app.telemetry.errors import Problem, ProblemCollector, TelemetryError
from app.telemetry.model import FORMAT_NAME, Sequence, Snapshot
from app.text import described, refused_character
from app.timefmt import NOT_ISO_8601, foreign_digit, parse_iso_time, utc_text

# --- limits ------------------------------------------------------------------
#: Required CSV columns, in the order :func:`dump_csv` writes them.
CSV_COLUMNS = ("snapshot", "time", "x", "y", "brightness")
MAX_SENSOR_SIZE_PX = 100_000
MAX_DISTORTION = 10.0          # |k1|, |k2|; real lenses are well below 1
# Physical bounds of a star camera.  Values beyond them are not cameras but typos or hostile input,
# and the numerics downstream (pixel <-> direction, chords, logarithms of areas) break on them
# with overflows, domain errors or meaningless fits rather than a clear refusal.
#: Field of view across the sensor diagonal (pinhole), degrees: star trackers see 1 to 60 deg,
#: 0.1 deg is a telescope's guide camera, a pinhole model past 120 deg is no longer a lens.
MIN_FIELD_OF_VIEW_DEG = 0.1
MAX_FIELD_OF_VIEW_DEG = 120.0
#: How far the principal point may lie off the sensor, as a fraction of the sensor's size on each
#: side (real decentring is a few percent; half a sensor beyond its edge is no camera model).
MAX_PRINCIPAL_POINT_OUTSIDE = 0.5
#: Radial distortion |k1 r^2 + k2 r^4| at the sensor corner, as a fraction of the corner's radius:
#: star camera lenses stay within a few percent; beyond a quarter the pinhole-plus-radial model
#: (and the fixed-point undistortion) no longer describes a lens.
MAX_CORNER_DISTORTION = 0.25
#: Faintest magnitude a sensor detects (Hp): below 0 only two or three stars of the whole sky are
#: seen, beyond 12 no star field sensor of this kind reaches.
MIN_MAG_LIMIT = 0.0
MAX_MAG_LIMIT = 12.0
MAX_FOCAL_LENGTH_TOLERANCE = 0.2   # a focal length known worse than 20 % is not a camera model
MAX_DISTORTION_BOUND = 1.0     # k1_bound, k2_bound: 1 is already extreme for a star camera
MAX_SPEED_KM_S = 100.0         # a spacecraft near the Earth moves at < 12 km/s
MAX_TEXT_LENGTH = 128          # sequence_id, spacecraft
MAX_INDEX = 2**31 - 1          # snapshot index; fits every database integer
MAX_JSON_DEPTH = 20            # the format itself needs 5 levels
EARLIEST_TIME = datetime(1900, 1, 1, tzinfo=timezone.utc)
LATEST_TIME = datetime(2100, 1, 1, tzinfo=timezone.utc)

_CAMERA_REQUIRED = ("width", "height", "focal_length_px", "cx", "cy")
_CAMERA_OPTIONAL = ("k1", "k2", "name", "mag_limit", "focal_length_tolerance", "k1_bound", "k2_bound",
                    "focal_length_unknown")
#: Optional camera fields bounded to [0, limit]: how well the declared optics are known.
_CAMERA_UNCERTAINTY_LIMITS = {"focal_length_tolerance": MAX_FOCAL_LENGTH_TOLERANCE,
                              "k1_bound": MAX_DISTORTION_BOUND, "k2_bound": MAX_DISTORTION_BOUND}
_TOP_LEVEL_KEYS = ("format", "sequence_id", "spacecraft", "camera", "snapshots", "velocity_km_s", "time_assumed")
_SNAPSHOT_KEYS = ("index", "time", "sources")
_SOURCE_KEYS = ("x", "y", "brightness")
_CSV_META_KEYS = ("format", "sequence_id", "spacecraft", "camera", "velocity_km_s", "time_assumed")

_CAMERA_NAME_RE = re.compile(r"[A-Za-z0-9._+-]{1,64}")
# ASCII digits only: Python's \d, int() and float() also take other scripts' digits ('٨٩', '１２'), which
# the format's plain decimals are not (and the JSON form never accepts).
_INT_RE = re.compile(r"[+-]?[0-9]{1,30}")
_NUMBER_RE = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NON_FINITE_WORDS = {"nan", "inf", "infinity"}
_META_RE = re.compile(r"#\s*([A-Za-z_][A-Za-z0-9_-]*)\s*:(.*)")
_MISSING = object()


# =============================================================================
# public API
# =============================================================================
def parse_telemetry(data: bytes | str, *, filename: str | None = None,
                    default_camera: Camera | None = None,
                    max_bytes: int | None = None, physical_bounds: bool = True) -> Sequence:
    """Validate a JSON or CSV telemetry document and return its Sequence.

    ``filename`` (optional) names the file in messages, supplies a missing
    ``sequence_id`` (its stem) and, ending in ``.json``, forces JSON.
    ``default_camera`` is used when the file has no camera; None means the
    configured one, ``CAMERAS[settings().default_camera]`` (an empty or
    unknown name there means: no default, a file without camera is invalid).
    ``max_bytes`` None means ``settings().max_upload_bytes``.
    ``physical_bounds`` False skips the camera's physical bounds (field of
    view, principal point, corner distortion, ``mag_limit`` range): only for
    text an archive accepted under earlier bounds, which must stay readable.

    Raises TelemetryError, and nothing else, for any bad input.
    """
    config = settings()
    limit = config.max_upload_bytes if max_bytes is None else max_bytes
    fallback_camera = default_camera if default_camera is not None else CAMERAS.get(config.default_camera)
    try:
        text = _decode(data, limit)
        if _looks_like_json(text, filename):
            return _sequence_from_json(text, filename, fallback_camera, physical_bounds)
        return _sequence_from_csv(text, filename, fallback_camera, physical_bounds)
    except TelemetryError as err:
        if filename is None or err.filename is not None:
            raise
        raise TelemetryError(err.problems, filename=filename, truncated=err.truncated) from None


def load_telemetry_file(path: str | os.PathLike, *, default_camera: Camera | None = None,
                        max_bytes: int | None = None) -> Sequence:
    """Read and parse one telemetry file; the size is checked before reading.

    Operating-system errors (missing file, a directory, no permission) become
    a TelemetryError at location ``file``.
    """
    limit = settings().max_upload_bytes if max_bytes is None else max_bytes
    name = os.fspath(path)
    name = name.decode("utf-8", "replace") if isinstance(name, bytes) else name
    try:
        size = os.stat(path).st_size
        if size > limit:
            raise TelemetryError.at("file", _too_large_message(size, limit), filename=name)
        with open(path, "rb") as stream:
            # Read one byte past the limit: the file may have grown since stat.
            data = stream.read(limit + 1)
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise TelemetryError.at("file", f"cannot read the file: {reason}", filename=name) from None
    return parse_telemetry(data, filename=name, default_camera=default_camera, max_bytes=limit)


def dump_json(seq: Sequence) -> str:
    """The JSON form of ``seq``: one line per top-level field and per source.

    Plain ``json.dumps(indent=2)`` would spend five lines on every source;
    this layout keeps a 16 x 10 sequence readable and diffable.
    """
    doc = seq.to_json_dict()
    snapshots = doc.pop("snapshots")
    fields = [f"  {json.dumps(key)}: {json.dumps(value, allow_nan=False)}" for key, value in doc.items()]
    parts = []
    for snap in snapshots:
        sources = ",\n".join("        " + json.dumps(s, allow_nan=False) for s in snap["sources"])
        body = f"[\n{sources}\n      ]" if sources else "[]"
        parts.append(f'    {{"index": {snap["index"]}, "time": {json.dumps(snap["time"])},\n'
                     f'      "sources": {body}}}')
    fields.append('  "snapshots": [\n' + ",\n".join(parts) + "\n  ]")
    return "{\n" + ",\n".join(fields) + "\n}\n"


def dump_csv(seq: Sequence) -> str:
    """The CSV form of ``seq``: header comments, then one row per source.

    ``Sequence.extra`` has no place in the CSV form and is not written.
    """
    lines = [f"# format: {FORMAT_NAME}", f"# sequence_id: {seq.sequence_id}"]
    if seq.spacecraft is not None:
        lines.append(f"# spacecraft: {seq.spacecraft}")
    camera = " ".join(f"{key}={_csv_value(value)}" for key, value in seq.camera.to_dict().items())
    lines.append(f"# camera: {camera}")
    if seq.velocity_km_s is not None:
        lines.append("# velocity_km_s: " + " ".join(repr(float(v)) for v in seq.velocity_km_s))
    if seq.time_assumed:
        lines.append("# time_assumed: true")
    lines.append(",".join(CSV_COLUMNS))
    for snap in seq.snapshots:
        time = utc_text(snap.time)
        if snap.n_sources == 0:
            lines.append(f"{snap.index},{time},,,")
        for (x, y), b in zip(snap.xy, snap.brightness):
            lines.append(f"{snap.index},{time},{float(x)!r},{float(y)!r},{float(b)!r}")
    return "\n".join(lines) + "\n"


# =============================================================================
# bytes -> text, form detection
# =============================================================================
def _too_large_message(size: int, limit: int) -> str:
    return f"the file is {size} bytes, larger than the limit of {limit} bytes"


def _decode(data: bytes | str, limit: int) -> str:
    """Check the size, decode UTF-8 (a BOM is dropped), reject empty input."""
    if isinstance(data, str):
        # A character is at least one byte, so this cheap test comes first.
        if len(data) > limit:
            raise TelemetryError.at("file", _too_large_message(len(data), limit))
        try:
            size = len(data.encode("utf-8"))
        except UnicodeEncodeError as err:
            raise TelemetryError.at(
                "file", f"not valid Unicode text: lone surrogate at character {err.start}") from None
        if size > limit:
            raise TelemetryError.at("file", _too_large_message(size, limit))
        text = data
    elif isinstance(data, (bytes, bytearray, memoryview)):
        raw = bytes(data)
        if len(raw) > limit:
            raise TelemetryError.at("file", _too_large_message(len(raw), limit))
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise TelemetryError.at(
                "file", f"not valid UTF-8 text: byte 0x{raw[err.start]:02x} at offset {err.start}") from None
    else:
        raise TypeError(f"telemetry data must be bytes or str, not {type(data).__name__}")
    text = text.removeprefix("\ufeff")
    if not text.strip():
        raise TelemetryError.at("file", "the file is empty")
    return text


def _looks_like_json(text: str, filename: str | None) -> bool:
    first = re.match(r"\s*(.?)", text).group(1)
    return first in ("{", "[") or (filename is not None and filename.lower().endswith(".json"))


# =============================================================================
# value checks shared by both forms
# =============================================================================
def describe_value(value: Any) -> str:
    """A JSON value as a user would call it, for "got ..." messages (the API's request bodies say it so too)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, _NonFinite):
        return value.token
    if isinstance(value, _ForeignDigits):
        return repr(value.text)
    if isinstance(value, str):
        shown = value if len(value) <= 40 else value[:37] + "..."
        return f"a string ({shown!r})"
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return "an array"
    return f"{value!r}"


def _as_number(value: Any, loc: str, problems: ProblemCollector) -> float | None:
    """A finite float from a JSON number (never a boolean), else a problem."""
    if isinstance(value, _NonFinite):
        problems.add(loc, f"{value.token} is not allowed: numbers must be finite")
        return None
    if isinstance(value, _ForeignDigits):
        problems.add(loc, value.message)
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        problems.add(loc, f"must be a number, got {describe_value(value)}")
        return None
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        problems.add(loc, f"must be a finite number, got {describe_value(value)[:40]} (out of range)")
        return None
    return number


def _as_int(value: Any, loc: str, problems: ProblemCollector, low: int, high: int) -> int | None:
    """An int in [low, high] from a JSON integer (not a float, not a boolean)."""
    if isinstance(value, _ForeignDigits):
        problems.add(loc, value.message)
        return None
    if isinstance(value, bool) or not isinstance(value, int):
        problems.add(loc, f"must be an integer, got {describe_value(value)}")
        return None
    if not low <= value <= high:
        shown = value if abs(value) < 10**20 else "a huge number"
        problems.add(loc, f"must be an integer from {low} to {high}, got {shown}")
        return None
    return value


def _as_text(value: Any, loc: str, problems: ProblemCollector) -> str | None:
    """A non-blank string of printable characters, stripped of outer spaces."""
    if not isinstance(value, str):
        problems.add(loc, f"must be a string, got {describe_value(value)}")
        return None
    text = value.strip()
    if not text:
        problems.add(loc, "must not be empty")
        return None
    if len(text) > MAX_TEXT_LENGTH:
        problems.add(loc, f"must be at most {MAX_TEXT_LENGTH} characters, got {len(text)}")
        return None
    # Control characters would break the CSV form and log lines; surrogates
    # cannot be stored as UTF-8.
    if any(unicodedata.category(c) in ("Cc", "Cs") for c in text):
        problems.add(loc, "must not contain control characters or lone surrogates")
        return None
    # A bidirectional override would make the name read as another one in consoles and CCSDS files.
    refused = refused_character(text)
    if refused is not None:
        problems.add(loc, f"must not contain {described(refused)}")
        return None
    return text


def _as_time(value: Any, loc: str, problems: ProblemCollector) -> datetime | None:
    """ISO 8601 text -> aware UTC datetime; no offset means UTC."""
    if not isinstance(value, str):
        problems.add(loc, f"must be an ISO 8601 time string, got {describe_value(value)}")
        return None
    try:
        parsed = parse_iso_time(value.strip())
    except ValueError as err:
        # A leap second or a date that does not exist is said as such; other text is shown after the reason.
        reason = str(err)
        problems.add(loc, f"{reason}: {describe_value(value)}" if reason == NOT_ISO_8601 else reason)
        return None
    try:
        if parsed.tzinfo is None:
            parsed = parsed.replace(tzinfo=timezone.utc)
        parsed = parsed.astimezone(timezone.utc)
    except (ValueError, OverflowError):
        problems.add(loc, f"{NOT_ISO_8601}: {describe_value(value)}")
        return None
    if not EARLIEST_TIME <= parsed < LATEST_TIME:
        problems.add(loc, f"time {utc_text(parsed)} is outside the supported years 1900 to 2099")
        return None
    return parsed


def _check_on_sensor(value: float | None, size: int, axis: str, loc: str,
                     problems: ProblemCollector) -> float | None:
    """Pixel centres run 0..size-1, so the sensor spans -0.5..size-0.5."""
    if value is None:
        return None
    if not -0.5 <= value <= size - 0.5:
        problems.add(loc, f"{axis} = {value:g} is outside the sensor (-0.5 to {size - 0.5:g})")
        return None
    return value


def _check_brightness(value: float | None, loc: str, problems: ProblemCollector) -> float | None:
    if value is not None and value < 0:
        problems.add(loc, f"brightness must be >= 0, got {value:g}")
        return None
    return value


def _camera_from_fields(fields: Mapping[str, Any], where: Callable[[str], str],
                        problems: ProblemCollector) -> Camera | None:
    """Validate camera parameters (JSON values, or CSV text already converted).

    ``where(key)`` gives the location of one field.
    """
    ok = True
    for key in fields:
        if key not in _CAMERA_REQUIRED + _CAMERA_OPTIONAL:
            problems.add(where(key), "unknown camera field; expected "
                         + ", ".join(_CAMERA_REQUIRED + _CAMERA_OPTIONAL))
            ok = False
    for key in _CAMERA_REQUIRED:
        if key not in fields:
            problems.add(where(key), "missing (required camera field)")
            ok = False
    values: dict[str, Any] = {}
    for key in ("width", "height"):
        if key in fields:
            values[key] = _as_int(fields[key], where(key), problems, 1, MAX_SENSOR_SIZE_PX)
    for key in ("focal_length_px", "cx", "cy"):
        if key in fields:
            values[key] = _as_number(fields[key], where(key), problems)
    for key in ("k1", "k2", "mag_limit", *_CAMERA_UNCERTAINTY_LIMITS):  # optional: null is absent
        if fields.get(key) is not None:
            values[key] = _as_number(fields[key], where(key), problems)
    focal = values.get("focal_length_px")
    if focal is not None and focal <= 0:
        problems.add(where("focal_length_px"), f"must be > 0, got {focal:g}")
        values["focal_length_px"] = None
    for key in ("k1", "k2"):
        if values.get(key) is not None and abs(values[key]) > MAX_DISTORTION:
            problems.add(where(key), f"must be within +-{MAX_DISTORTION:g}, got {values[key]:g}")
            values[key] = None
    if problems.physical_bounds:
        _check_physical_bounds(values, where, problems)
    for key, limit in _CAMERA_UNCERTAINTY_LIMITS.items():
        if values.get(key) is not None and not 0.0 <= values[key] <= limit:
            problems.add(where(key), f"must be between 0 and {limit:g}, got {values[key]:g}")
            values[key] = None
    unknown = fields.get("focal_length_unknown")
    if unknown is not None and not isinstance(unknown, bool):
        problems.add(where("focal_length_unknown"), "must be true or false, got " + describe_value(unknown))
        ok = False
    elif unknown:
        values["focal_length_unknown"] = True
    if fields.get("name") is not None:
        name = fields["name"]
        if not isinstance(name, str) or not _CAMERA_NAME_RE.fullmatch(name):
            problems.add(where("name"), "must be 1 to 64 letters, digits or . _ + -, got "
                         + describe_value(name))
            ok = False
        else:
            values["name"] = name
    if not ok or any(v is None for v in values.values()):
        return None
    return Camera(width=values["width"], height=values["height"],
                  focal_length_px=values["focal_length_px"], cx=values["cx"], cy=values["cy"],
                  k1=values.get("k1", 0.0), k2=values.get("k2", 0.0), name=values.get("name"),
                  mag_limit=values.get("mag_limit"), focal_length_unknown=values.get("focal_length_unknown", False),
                  **{key: values[key] for key in _CAMERA_UNCERTAINTY_LIMITS if key in values})


def _check_physical_bounds(values: dict[str, Any], where: Callable[[str], str], problems: ProblemCollector) -> None:
    """Physical bounds of a star camera: magnitude limit, field of view, principal point, distortion.

    Each check runs only when the fields it needs are valid on their own; a
    failing field is set to None in ``values`` (the camera is then refused).
    """
    mag_limit = values.get("mag_limit")
    if mag_limit is not None and not MIN_MAG_LIMIT <= mag_limit <= MAX_MAG_LIMIT:
        problems.add(where("mag_limit"), f"must be between {MIN_MAG_LIMIT:g} and {MAX_MAG_LIMIT:g} "
                                         f"(the faintest Hipparcos magnitude the sensor detects), got {mag_limit:g}")
        values["mag_limit"] = None
    width, height, focal = values.get("width"), values.get("height"), values.get("focal_length_px")
    if width is None or height is None:
        return
    if focal is not None:
        diagonal_deg = 2.0 * math.degrees(math.atan(math.hypot(width, height) / (2.0 * focal)))
        if not MIN_FIELD_OF_VIEW_DEG <= diagonal_deg <= MAX_FIELD_OF_VIEW_DEG:
            problems.add(where("focal_length_px"),
                         f"{focal:g} px gives the {width}x{height} sensor a field of view of {diagonal_deg:.3g} deg "
                         f"across its diagonal; a star camera sees {MIN_FIELD_OF_VIEW_DEG:g} to "
                         f"{MAX_FIELD_OF_VIEW_DEG:g} deg")
            values["focal_length_px"] = focal = None
    for key, size in (("cx", width), ("cy", height)):
        value = values.get(key)
        margin = MAX_PRINCIPAL_POINT_OUTSIDE * size
        low, high = -0.5 - margin, size - 0.5 + margin
        if value is not None and not low <= value <= high:
            problems.add(where(key), f"{key} = {value:g} puts the principal point far off the sensor: it must lie "
                                     f"within {low:g} to {high:g} px (the sensor widened by half its size)")
            values[key] = None
    k1, k2 = values.get("k1", 0.0), values.get("k2", 0.0)
    if focal is None or values.get("cx") is None or values.get("cy") is None or k1 is None or k2 is None:
        return
    if k1 == 0.0 and k2 == 0.0:
        return
    # The normalised radius of the sensor corner farthest from the principal point (Camera.corner_radius).
    r = math.hypot(max(values["cx"] + 0.5, width - 0.5 - values["cx"]),
                   max(values["cy"] + 0.5, height - 0.5 - values["cy"])) / focal
    corner = k1 * r**2 + k2 * r**4
    # d/dr [r (1 + k1 r^2 + k2 r^4)] > 0 out to the corner: else two directions land on one pixel.
    increasing = fold_radius(k1, k2) > r
    key = "k2" if k1 == 0.0 else "k1"
    if abs(corner) > MAX_CORNER_DISTORTION:
        problems.add(where(key), f"k1 = {k1:g}, k2 = {k2:g} move the sensor corner by {100 * corner:.3g} % of its "
                                 f"distance from the principal point; a star camera's lens distorts at most "
                                 f"{100 * MAX_CORNER_DISTORTION:g} %")
        values[key] = None
    elif not increasing:
        problems.add(where(key), f"k1 = {k1:g}, k2 = {k2:g} fold the image over before the sensor corner "
                                 "(the radial distortion must grow monotonically out to it)")
        values[key] = None


def _named_camera(name: str, loc: str, problems: ProblemCollector) -> Camera | None:
    camera = CAMERAS.get(name)
    if camera is None:
        problems.add(loc, f"unknown camera {name!r}; known cameras: " + ", ".join(CAMERAS))
    return camera


def _missing_camera(loc: str, problems: ProblemCollector) -> None:
    problems.add(loc, "missing camera: the file has no camera and no default camera is configured "
                      "(STARID_DEFAULT_CAMERA)")


def _velocity(components: Any, loc: str, problems: ProblemCollector
              ) -> tuple[float, float, float] | None:
    """Three finite numbers (km/s, GCRS) with a speed below MAX_SPEED_KM_S."""
    if not isinstance(components, list) or len(components) != 3:
        problems.add(loc, f"must be an array of 3 numbers [vx, vy, vz] in km/s, got {describe_value(components)}"
                          + (f" of {len(components)}" if isinstance(components, list) else ""))
        return None
    values = [_as_number(v, f"{loc}[{i}]", problems) for i, v in enumerate(components)]
    if any(v is None for v in values):
        return None
    speed = math.sqrt(sum(v * v for v in values))
    if speed >= MAX_SPEED_KM_S:
        problems.add(loc, f"speed {speed:g} km/s is not below {MAX_SPEED_KM_S:g} km/s")
        return None
    return (values[0], values[1], values[2])


def _sequence_id_from_filename(filename: str | None) -> str | None:
    """The file's stem: 'uploads/A-0427.json' -> 'A-0427' (also for Windows paths)."""
    if not filename:
        return None
    name = re.split(r"[\\/]", filename)[-1]
    stem = name.rsplit(".", 1)[0] if "." in name.lstrip(".") else name
    return stem or None


def _sequence_id(value: Any, loc: str, filename: str | None, problems: ProblemCollector) -> str | None:
    if value is _MISSING or value is None:
        derived = _sequence_id_from_filename(filename)
        if derived is None:
            problems.add(loc, "missing: give a sequence_id (or a file name to take it from)")
            return None
        return _as_text(derived, f"{loc} (from the file name)", problems)
    return _as_text(value, loc, problems)


# =============================================================================
# snapshots: drafts shared by both forms, then cross-snapshot checks
# =============================================================================
@dataclass
class _Draft:
    """A snapshot being assembled; None fields failed validation."""

    index: int | None
    index_loc: str
    time: datetime | None
    time_loc: str
    xy: list[tuple[float, float]] = field(default_factory=list)
    brightness: list[float] = field(default_factory=list)


def _check_order(drafts: list[_Draft], problems: ProblemCollector) -> None:
    """Snapshot indices are unique; times strictly increase in file order."""
    seen: dict[int, str] = {}
    previous: _Draft | None = None
    for draft in drafts:
        if draft.index is not None:
            if draft.index in seen:
                problems.add(draft.index_loc,
                             f"duplicate snapshot index {draft.index} (also at {seen[draft.index]})")
            else:
                seen[draft.index] = draft.index_loc
        if draft.time is None:
            continue
        if previous is not None and draft.time <= previous.time:
            problems.add(draft.time_loc,
                         f"times must strictly increase: {utc_text(draft.time)} is not after "
                         f"{utc_text(previous.time)} ({previous.time_loc})")
        previous = draft


def _snapshot(draft: _Draft) -> Snapshot:
    xy = np.array(draft.xy, dtype=np.float64).reshape(-1, 2)
    return Snapshot(index=draft.index, time=draft.time, xy=xy,
                    brightness=np.array(draft.brightness, dtype=np.float64))


# =============================================================================
# JSON form
# =============================================================================
class _NonFinite:
    """Stands in for NaN/Infinity, which Python's json would otherwise accept."""

    __slots__ = ("token",)

    def __init__(self, token: str):
        self.token = token


def _load_json(text: str, problems: ProblemCollector) -> Any:
    """json.loads with NaN/Infinity flagged and duplicate keys reported."""
    duplicates: list[str] = []

    def pairs_to_dict(pairs: list[tuple[str, Any]]) -> dict:
        obj: dict = {}
        for key, value in pairs:
            if key in obj:
                duplicates.append(key)
            obj[key] = value
        return obj

    try:
        doc = json.loads(text, parse_constant=_NonFinite, object_pairs_hook=pairs_to_dict)
    except json.JSONDecodeError as err:
        raise TelemetryError.at("file", f"not valid JSON: {err.msg} (line {err.lineno}, column {err.colno})"
                                ) from None
    except RecursionError:
        raise TelemetryError.at("file", f"JSON nested deeper than {MAX_JSON_DEPTH} levels") from None
    except ValueError as err:  # an integer with more than 4300 digits (Python's guard) or the like
        raise TelemetryError.at("file", _json_value_error(text, err)) from None
    for key in duplicates:
        problems.add("file", f"duplicate key {key!r} in a JSON object")
    if _nesting_depth(doc, MAX_JSON_DEPTH) > MAX_JSON_DEPTH:
        raise TelemetryError.at("file", f"JSON nested deeper than {MAX_JSON_DEPTH} levels")
    return doc


def _json_value_error(text: str, err: ValueError) -> str:
    """The message of a JSON value Python refuses to convert, located when it is an over-long integer."""
    limit = sys.get_int_max_str_digits()
    # An integer: a run of digits not part of a fraction or an exponent (floats have no such limit).
    long_number = re.search(r"(?<![\d.eE])\d{%d,}(?![\d.eE])" % (limit + 1), text) if limit else None
    if long_number is None:
        return f"not valid JSON: {err}"
    line = text.count("\n", 0, long_number.start()) + 1
    column = long_number.start() - text.rfind("\n", 0, long_number.start())
    return (f"not valid JSON: a number of {len(long_number.group())} digits (line {line}, column {column}); "
            f"numbers have at most {limit}")


def _nesting_depth(value: Any, limit: int) -> int:
    """Levels of nested arrays/objects (a scalar is 0); stops once past ``limit``."""
    deepest = 0
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else None
        if children is None:
            continue
        deepest = max(deepest, depth)
        if deepest > limit:
            break
        stack.extend((child, depth + 1) for child in children)
    return deepest


def _key_label(key: str) -> str:
    """A user-supplied key made safe for a location string (no control
    characters or surrogates, bounded length)."""
    return key if re.fullmatch(r"[\w.+-]{1,40}", key) else ascii(key[:40])


def _has_surrogate(text: str) -> bool:
    return any(0xD800 <= ord(c) <= 0xDFFF for c in text)


def _check_extra(extra: dict, problems: ProblemCollector) -> None:
    """Kept-but-unknown values must still be writable as strict JSON and UTF-8.

    JSON escapes such as "\\ud800" can produce lone surrogates, which no UTF-8
    store accepts; NaN/Infinity and overflowing numbers are not strict JSON.
    """
    stack: list[tuple[str, Any]] = [("", extra)]
    while stack and not problems.full:
        loc, item = stack.pop()
        if isinstance(item, dict):
            for key, child in item.items():
                child_loc = f"{loc}.{_key_label(key)}" if loc else _key_label(key)
                if _has_surrogate(key):
                    problems.add(child_loc, "the key is not valid Unicode (lone surrogate)")
                else:
                    stack.append((child_loc, child))
        elif isinstance(item, list):
            stack.extend((f"{loc}[{i}]", child) for i, child in enumerate(item))
        elif isinstance(item, _NonFinite):
            problems.add(loc, f"{item.token} is not allowed: numbers must be finite")
        elif isinstance(item, float) and not math.isfinite(item):
            problems.add(loc, "number out of range")
        elif isinstance(item, str) and _has_surrogate(item):
            problems.add(loc, "not valid Unicode (lone surrogate)")


def _unknown_keys(obj: dict, allowed: tuple[str, ...], loc: str, what: str,
                  problems: ProblemCollector) -> None:
    for key in obj:
        if key not in allowed:
            problems.add(f"{loc}.{_key_label(key)}", f"unknown {what} field; expected " + ", ".join(allowed))


def _json_camera(value: Any, default: Camera | None, problems: ProblemCollector) -> Camera | None:
    if value is _MISSING or value is None:
        if default is None:
            _missing_camera("camera", problems)
        return default
    if isinstance(value, str):
        return _named_camera(value, "camera", problems)
    if not isinstance(value, dict):
        problems.add("camera", f"must be an object or a camera name, got {describe_value(value)}")
        return None
    return _camera_from_fields(value, lambda key: f"camera.{_key_label(key)}", problems)


def _json_source(value: Any, loc: str, camera: Camera | None, problems: ProblemCollector
                 ) -> tuple[float, float, float] | None:
    if not isinstance(value, dict):
        problems.add(loc, f"must be an object {{\"x\", \"y\", \"brightness\"}}, got {describe_value(value)}")
        return None
    _unknown_keys(value, _SOURCE_KEYS, loc, "source", problems)
    numbers = {}
    for key in _SOURCE_KEYS:
        if key not in value:
            problems.add(f"{loc}.{key}", "missing (required)")
            numbers[key] = None
        else:
            numbers[key] = _as_number(value[key], f"{loc}.{key}", problems)
    x, y, b = numbers["x"], numbers["y"], numbers["brightness"]
    if camera is not None:
        x = _check_on_sensor(x, camera.width, "x", f"{loc}.x", problems)
        y = _check_on_sensor(y, camera.height, "y", f"{loc}.y", problems)
    b = _check_brightness(b, f"{loc}.brightness", problems)
    if x is None or y is None or b is None:
        return None
    return x, y, b


def _json_snapshot(value: Any, loc: str, camera: Camera | None, problems: ProblemCollector
                   ) -> _Draft | None:
    if not isinstance(value, dict):
        problems.add(loc, f"must be an object {{\"index\", \"time\", \"sources\"}}, got {describe_value(value)}")
        return None
    _unknown_keys(value, _SNAPSHOT_KEYS, loc, "snapshot", problems)
    for key in _SNAPSHOT_KEYS:
        if key not in value:
            problems.add(f"{loc}.{key}", "missing (required)")
    index = _as_int(value["index"], f"{loc}.index", problems, 0, MAX_INDEX) if "index" in value else None
    time = _as_time(value["time"], f"{loc}.time", problems) if "time" in value else None
    draft = _Draft(index, f"{loc}.index", time, f"{loc}.time")
    sources = value.get("sources", [])
    if not isinstance(sources, list):
        problems.add(f"{loc}.sources", f"must be an array of sources, got {describe_value(sources)}")
    elif len(sources) > MAX_SOURCES_PER_SNAPSHOT:
        problems.add(f"{loc}.sources",
                     f"{len(sources)} sources; at most {MAX_SOURCES_PER_SNAPSHOT} are allowed per snapshot")
    else:
        for j, item in enumerate(sources):
            source = _json_source(item, f"{loc}.sources[{j}]", camera, problems)
            if source is not None:
                draft.xy.append(source[:2])
                draft.brightness.append(source[2])
            if problems.full:
                break
    return draft


def _json_snapshots(value: Any, camera: Camera | None, problems: ProblemCollector) -> list[_Draft]:
    if value is _MISSING:
        problems.add("snapshots", "missing (required)")
        return []
    if not isinstance(value, list):
        problems.add("snapshots", f"must be an array of snapshots, got {describe_value(value)}")
        return []
    if not value:
        problems.add("snapshots", "must hold at least one snapshot")
        return []
    if len(value) > MAX_SNAPSHOTS:
        # Checking each of thousands of snapshots would only drown the message.
        problems.add("snapshots", f"{len(value)} snapshots; at most {MAX_SNAPSHOTS} are allowed")
        return []
    drafts = []
    for i, item in enumerate(value):
        draft = _json_snapshot(item, f"snapshots[{i}]", camera, problems)
        if draft is not None:
            drafts.append(draft)
        if problems.full:
            break
    _check_order(drafts, problems)
    return drafts


def _sequence_from_json(text: str, filename: str | None, default_camera: Camera | None,
                        physical_bounds: bool = True) -> Sequence:
    problems = ProblemCollector(physical_bounds=physical_bounds)
    doc = _load_json(text, problems)
    if not isinstance(doc, dict):
        raise TelemetryError.at("file", f"the top level must be a JSON object {{...}}, got {describe_value(doc)}")
    if "format" in doc and doc["format"] != FORMAT_NAME:
        problems.add("format", f"unsupported format: must be {FORMAT_NAME!r}, got {describe_value(doc['format'])}")
    sequence_id = _sequence_id(doc.get("sequence_id", _MISSING), "sequence_id", filename, problems)
    spacecraft = doc.get("spacecraft")
    if spacecraft is not None:
        spacecraft = _as_text(spacecraft, "spacecraft", problems)
    camera = _json_camera(doc.get("camera", _MISSING), default_camera, problems)
    velocity = doc.get("velocity_km_s")
    if velocity is not None:
        velocity = _velocity(velocity, "velocity_km_s", problems)
    drafts = _json_snapshots(doc.get("snapshots", _MISSING), camera, problems)
    time_assumed = doc.get("time_assumed", False)
    if not isinstance(time_assumed, bool):
        problems.add("time_assumed", f"must be true or false, got {describe_value(time_assumed)}")
    extra = {key: value for key, value in doc.items() if key not in _TOP_LEVEL_KEYS}
    _check_extra(extra, problems)
    problems.raise_if_any()
    return Sequence(sequence_id=sequence_id, spacecraft=spacecraft, camera=camera,
                    snapshots=tuple(_snapshot(d) for d in drafts), velocity_km_s=velocity, extra=extra,
                    time_assumed=time_assumed)


# =============================================================================
# CSV form
# =============================================================================
def _csv_value(value: Any) -> str:
    """A camera parameter as written in the CSV header comment."""
    if isinstance(value, bool):  # focal_length_unknown: JSON's spelling, read back by _csv_camera
        return "true" if value else "false"
    return repr(float(value)) if isinstance(value, float) else str(value)


class _ForeignDigits:
    """Stands in for CSV text with digits of another script ('٨٩', '１２'): int() and float() would read it as
    a number, but the format's numbers are plain ASCII decimals, so it is refused with that reason."""

    __slots__ = ("text",)

    def __init__(self, text: str):
        self.text = text

    @property
    def message(self) -> str:
        return f"{self.text!r} is not a plain decimal number (ASCII digits)"


def _csv_scalar(text: str) -> Any:
    """Text from a CSV cell or header comment -> int, float or (non-numeric) str.

    The result goes through the same checks as JSON values, so "752.0" for a
    width is reported as "must be an integer", as in JSON.  Only ASCII digits
    make a number; text with other digits becomes a :class:`_ForeignDigits`.
    """
    if _INT_RE.fullmatch(text):
        return int(text)
    if _NUMBER_RE.fullmatch(text):
        return float(text)
    if text.lower().lstrip("+-") in _NON_FINITE_WORDS:
        return _NonFinite(text)
    if foreign_digit(text) is not None:
        return _ForeignDigits(text)
    return text


def _csv_number(text: str, loc: str, problems: ProblemCollector) -> float | None:
    if not text:
        problems.add(loc, "missing value")
        return None
    return _as_number(_csv_scalar(text), loc, problems)


def _csv_int(text: str, loc: str, problems: ProblemCollector, low: int, high: int) -> int | None:
    if not text:
        problems.add(loc, "missing value")
        return None
    return _as_int(_csv_scalar(text), loc, problems, low, high)


@dataclass
class _CsvHeader:
    meta: dict[str, tuple[str, int]]      # key -> (value text, line number)
    columns: dict[str, int]               # required column -> field position
    n_fields: int
    line_no: int


def _csv_preamble(lines: list[str], problems: ProblemCollector) -> _CsvHeader:
    """Header comments (``# key: value``) up to the header line, then the header."""
    meta: dict[str, tuple[str, int]] = {}
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            match = _META_RE.fullmatch(stripped)
            key = match.group(1).lower() if match else None
            if key in _CSV_META_KEYS:
                if key in meta:
                    problems.add(f"line {number}, {key}", f"given twice (first at line {meta[key][1]})")
                else:
                    meta[key] = (match.group(2).strip(), number)
            continue  # other comments are free text
        return _csv_columns(stripped, number, meta, problems)
    raise TelemetryError.at("file", "no CSV header line " + ",".join(CSV_COLUMNS) + " found")


def _csv_columns(line: str, number: int, meta: dict, problems: ProblemCollector) -> _CsvHeader:
    try:
        names = [name.strip().lower() for name in next(csv.reader([line]))]
    except csv.Error as err:
        raise TelemetryError.at(f"line {number}", f"not a valid CSV header: {err}") from None
    missing = [c for c in CSV_COLUMNS if c not in names]
    if len(missing) == len(CSV_COLUMNS) and not meta:
        raise TelemetryError.at(
            "file", "neither JSON nor CSV: JSON starts with '{', CSV needs the header line "
                    + ",".join(CSV_COLUMNS))
    if missing:
        raise TelemetryError.at(f"line {number}", "the CSV header lacks the column(s) "
                                + ", ".join(f'"{c}"' for c in missing))
    twice = [c for c in CSV_COLUMNS if names.count(c) > 1]
    if twice:
        raise TelemetryError.at(f"line {number}", "the CSV header repeats the column(s) "
                                + ", ".join(f'"{c}"' for c in twice))
    return _CsvHeader(meta, {c: names.index(c) for c in CSV_COLUMNS}, len(names), number)


def _csv_camera(meta: dict[str, tuple[str, int]], default: Camera | None,
                problems: ProblemCollector) -> Camera | None:
    """``# camera: NAME`` or ``# camera: width=752 height=582 ...`` (spaces or commas)."""
    if "camera" not in meta:
        if default is None:
            _missing_camera("file", problems)
        return default
    text, number = meta["camera"]
    loc = f"line {number}, camera"
    if "=" not in text:
        if not text:
            problems.add(loc, "empty: give a camera name or width=... height=... fields")
            return None
        return _named_camera(text, loc, problems)
    fields: dict[str, Any] = {}
    for token in re.split(r"[\s,;]+", text):
        if not token:
            continue
        key, sep, value = token.partition("=")
        if not sep or not key:
            problems.add(loc, f"expected key=value, got {token!r}")
            return None
        if key in fields:
            problems.add(f"{loc}.{_key_label(key)}", "given twice")
            return None
        fields[key] = (value if key == "name" else {"true": True, "false": False}.get(value, value)
                       if key == "focal_length_unknown" else _csv_scalar(value))
    return _camera_from_fields(fields, lambda key: f"{loc}.{_key_label(key)}", problems)


def _csv_velocity(meta: dict[str, tuple[str, int]], problems: ProblemCollector
                  ) -> tuple[float, float, float] | None:
    if "velocity_km_s" not in meta:
        return None
    text, number = meta["velocity_km_s"]
    parts = [_csv_scalar(p) for p in re.split(r"[\s,;]+", text.strip().strip("[]")) if p]
    return _velocity(parts, f"line {number}, velocity_km_s", problems)


@dataclass
class _CsvGroup:
    """The rows of one snapshot seen so far."""

    draft: _Draft
    time_text: str
    first_line: int
    empty_row: bool = False
    source_rows: int = 0


def _csv_rows(lines: list[str], header: _CsvHeader, camera: Camera | None,
              problems: ProblemCollector) -> list[_Draft]:
    """One row per source; rows of a snapshot contiguous and with one time."""
    groups: list[_CsvGroup] = []
    ended: dict[int, int] = {}  # snapshot index -> first line of its rows
    for number in range(header.line_no + 1, len(lines) + 1):
        line = lines[number - 1]
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        if problems.full:
            break
        try:
            fields = next(csv.reader([line]))
        except csv.Error as err:
            problems.add(f"line {number}", f"not a valid CSV row: {err}")
            continue
        if len(fields) != header.n_fields:
            problems.add(f"line {number}", f"expected {header.n_fields} fields as in the header, "
                                           f"got {len(fields)}")
            continue

        def cell(name: str) -> str:
            return fields[header.columns[name]].strip()

        def loc(name: str) -> str:
            return f'line {number}, column "{name}"'

        index = _csv_int(cell("snapshot"), loc("snapshot"), problems, 0, MAX_INDEX)
        if index is None:
            continue
        group = groups[-1] if groups and groups[-1].draft.index == index else None
        if group is None:
            if index in ended:
                problems.add(loc("snapshot"), f"rows of snapshot {index} must be contiguous; "
                                              f"it already appeared at line {ended[index]}")
                continue
            if len(groups) == MAX_SNAPSHOTS:
                problems.add(loc("snapshot"), f"more than {MAX_SNAPSHOTS} snapshots")
                break
            ended[index] = number
            time = _as_time(cell("time"), loc("time"), problems)
            group = _CsvGroup(_Draft(index, loc("snapshot"), time, loc("time")), cell("time"), number)
            groups.append(group)
        elif cell("time") != group.time_text:
            other = _as_time(cell("time"), loc("time"), problems)
            if other is not None and other != group.draft.time:
                problems.add(loc("time"), f"all rows of snapshot {index} must have the same time "
                                          f"(line {group.first_line} has {group.time_text!r})")
        _csv_source(cell, loc, group, camera, problems)
    return [g.draft for g in groups]


def _csv_source(cell: Callable[[str], str], loc: Callable[[str], str], group: _CsvGroup,
                camera: Camera | None, problems: ProblemCollector) -> None:
    """Add one row's source to its snapshot, or note an empty (no sources) row."""
    draft = group.draft
    texts = [cell(key) for key in _SOURCE_KEYS]
    is_empty_row = not any(texts)
    if is_empty_row or group.empty_row:
        if group.empty_row or group.source_rows or not is_empty_row:
            problems.add(loc("x"), f"snapshot {draft.index} mixes an empty row (no sources) with other rows; "
                                   "a snapshot without sources is a single row with empty x, y, brightness")
        group.empty_row = True
        return
    group.source_rows += 1
    if group.source_rows > MAX_SOURCES_PER_SNAPSHOT:
        if group.source_rows == MAX_SOURCES_PER_SNAPSHOT + 1:
            problems.add(loc("x"), f"snapshot {draft.index} has more than {MAX_SOURCES_PER_SNAPSHOT} sources")
        return
    x = _csv_number(texts[0], loc("x"), problems)
    y = _csv_number(texts[1], loc("y"), problems)
    b = _check_brightness(_csv_number(texts[2], loc("brightness"), problems), loc("brightness"), problems)
    if camera is not None:
        x = _check_on_sensor(x, camera.width, "x", loc("x"), problems)
        y = _check_on_sensor(y, camera.height, "y", loc("y"), problems)
    if x is not None and y is not None and b is not None:
        draft.xy.append((x, y))
        draft.brightness.append(b)


def _sequence_from_csv(text: str, filename: str | None, default_camera: Camera | None,
                       physical_bounds: bool = True) -> Sequence:
    problems = ProblemCollector(physical_bounds=physical_bounds)
    # Split on newlines only: str.splitlines would also split on \x0c, \u2028...
    lines = [line.removesuffix("\r") for line in text.split("\n")]
    header = _csv_preamble(lines, problems)
    meta = header.meta

    def meta_loc(key: str) -> str:
        return f"line {meta[key][1]}, {key}"

    if "format" in meta and meta["format"][0] != FORMAT_NAME:
        problems.add(meta_loc("format"),
                     f"unsupported format: must be {FORMAT_NAME!r}, got {describe_value(meta['format'][0])}")
    sequence_id = _sequence_id(meta["sequence_id"][0] if "sequence_id" in meta else _MISSING,
                               meta_loc("sequence_id") if "sequence_id" in meta else "sequence_id",
                               filename, problems)
    spacecraft = None
    if "spacecraft" in meta:
        spacecraft = _as_text(meta["spacecraft"][0], meta_loc("spacecraft"), problems)
    camera = _csv_camera(meta, default_camera, problems)
    velocity = _csv_velocity(meta, problems)
    time_assumed = False
    if "time_assumed" in meta:
        text = meta["time_assumed"][0]
        time_assumed = {"true": True, "false": False}.get(text.lower())
        if time_assumed is None:
            problems.add(meta_loc("time_assumed"), f"must be true or false, got {describe_value(text)}")
    drafts = _csv_rows(lines, header, camera, problems)
    if not drafts and not problems:
        problems.add("file", "no snapshot rows after the header: at least one snapshot is required")
    _check_order(drafts, problems)
    problems.raise_if_any()
    return Sequence(sequence_id=sequence_id, spacecraft=spacecraft, camera=camera,
                    snapshots=tuple(_snapshot(d) for d in drafts), velocity_km_s=velocity,
                    time_assumed=bool(time_assumed))


__all__ = ["CSV_COLUMNS", "Problem", "TelemetryError", "dump_csv", "dump_json",
           "load_telemetry_file", "parse_telemetry"]
