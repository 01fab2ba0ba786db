"""Frames of one pass -> one :class:`app.telemetry.Sequence` (the same downstream as spot lists).

:func:`frames_to_sequence` reads every file (:mod:`app.frames.images`), detects and centroids
each frame (:mod:`app.frames.detect`), counts hot-pixel candidates into the camera's map
(:mod:`app.frames.hotpixels`), drops detections on hot pixels, keeps the ``max_sources``
brightest stars of each frame, orders the frames by time and writes the result as a
`tubsat-snapshots/1` document, which :func:`app.telemetry.parse_telemetry` validates like any
upload.  The document carries a top-level ``frames`` block (kept by the format as an unknown
top-level key): the frames' content hash, the detector and its options, and per frame its file,
hash, size, noise, what was detected and what was rejected and why.  A frame larger than the
detection budget is searched as the means of ``binned`` x ``binned`` blocks (:mod:`app.frames.binning`,
read so by :mod:`app.frames.images`); its detections are brought back to the image's own pixels at
once, and the frames block records ``binned`` per frame and a note.

Times, first found (:mod:`app.frames.times`): the caller's (one frame), the sidecar's
(``tubsat-frames/1``, docs/formats.md), the FITS headers' (DATE-AVG, DATE-OBS + EXPTIME/2, MJD-OBS)
or the EXIF ``DateTimeOriginal``; frames with none at all get an assumed time (J2000.0, 1 s apart
in file-name order) and the sequence ``time_assumed``.  Optics from the sidecar's camera block, a field of
view (sidecar ``fov_deg`` or the caller's ``fov_deg``) or the FITS header (FOCALLEN + XPIXSZ, or
a WCS scale).  A field of view gives a camera with ``focal_length_tolerance`` 0.10: the
identification searches focal lengths within +-10 % (:mod:`app.identification.optics`).  With no optics
at all the camera block says ``focal_length_unknown`` and the identification searches the field of view
(:mod:`app.identification.scale_free`).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import time
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime

import numpy as np

from app.camera import CAMERAS
from app.frames.binning import detect_on_blocks
from app.frames.detect import REJECTING_FLAGS, DetectionError, DetectionOptions, Detections
from app.frames.hotpixels import HotPixelMap, near_hot_pixel, stationary_candidates
from app.frames.images import Frame, FrameLimits, file_sha256, read_frames
from app.frames.times import assumed_times, mixed_times_error
from app.telemetry.errors import ImageError, Problem, ProblemCollector, TelemetryError
from app.telemetry.formats import dump_json, parse_telemetry
from app.telemetry.model import FORMAT_NAME, Sequence
from app.timefmt import parse_utc_time, utc_text

SIDECAR_FORMAT = "tubsat-frames/1"
#: Focal length tolerance declared for optics given only as a field of view or a header focal length: a field
#: of view known to +-5 % (a lens's nominal focal length, a guess from a photograph) plus the few per cent by
#: which a real lens's distortion moves the pinhole focal length that fits its stars best (seen on real frames:
#: a field of view 5 % long gave a focal length fitted 5.9 % from the declared one).
FOV_FOCAL_TOLERANCE = 0.10
#: How well a field of view given by hand is known, a fraction of the angle (a lens's nominal focal length, a
#: guess from a photograph); the distortion's share of :data:`FOV_FOCAL_TOLERANCE` is the rest.
FOV_TOLERANCE = 0.05
#: Horizontal fields of view (deg) a frame's optics may be given as (``fov_deg``, a sidecar's, an EXIF hint):
#: 0.1 is a telescope's guide camera; past 120 a pinhole is no lens.
FOV_BOUNDS_DEG = (0.1, 120.0)
#: The nominal field of view of frames whose optics are unknown (display only: identification searches the
#: field of view, :mod:`app.identification.scale_free`).
UNKNOWN_OPTICS_NOMINAL_FOV_DEG = 20.0
#: Rejected blobs listed per frame in the ``frames`` block (the brightest).
MAX_REJECTED_LISTED = 32
#: The fewest sources a frame must keep to make a pattern (:func:`app.identification.identify` needs 3).
MIN_PATTERN_SOURCES = 3
_SIDECAR_KEYS = ("format", "sequence_id", "spacecraft", "camera", "fov_deg", "frames", "max_sources",
                 "threshold_sigma", "velocity_km_s")
_SIDECAR_FRAME_KEYS = ("file", "time", "part")
_ID_RE = re.compile(r"[^A-Za-z0-9._+-]+")


class FramesTimeout(Exception):
    """Reading and detecting the pass took longer than its budget."""


@dataclass(frozen=True)
class Sidecar:
    """A validated ``tubsat-frames/1`` sidecar."""

    sequence_id: str | None = None
    spacecraft: str | None = None
    camera: dict | str | None = None
    fov_deg: float | None = None
    #: (file, part) -> time; part None: every image of the file (a FITS file's HDUs need their own).
    times: dict[tuple[str, int | None], datetime] = field(default_factory=dict)
    max_sources: int | None = None
    threshold_sigma: float | None = None
    velocity_km_s: list | None = None


@dataclass(frozen=True, eq=False)
class FramePass:
    """The result: the sequence, its document text, the camera's updated hot-pixel map, per-frame detections."""

    sequence: Sequence
    raw_text: str
    hot_map: HotPixelMap
    detections: list[Detections]
    frames_sha256: str
    #: Per frame (time order), the hot-pixel candidates counted into ``hot_map``.
    candidates: list[list[tuple[int, int]]] = field(default_factory=list)


def _sidecar_time(value, loc: str, problems: ProblemCollector) -> datetime | None:
    if not isinstance(value, str):
        problems.add(loc, "must be an ISO 8601 time string such as 2024-03-12T21:04:10.000Z")
        return None
    try:
        return parse_utc_time(value)
    except ValueError as exc:  # a leap second or a date that does not exist is said as such
        problems.add(loc, str(exc))
        return None


def parse_sidecar(data: bytes | str, name: str = "sidecar") -> Sidecar:
    """Validate a sidecar; ImageError with problems located as ``sidecar.frames[2].time`` (``name``: the
    sidecar's file name where one was found beside the images, its form field's otherwise)."""
    if not data.strip():
        raise ImageError.at(name, "the file is empty")
    try:
        text = data.decode("utf-8") if isinstance(data, (bytes, bytearray)) else data
        doc = json.loads(text)
    except (UnicodeDecodeError, ValueError) as exc:
        raise ImageError.at(name, f"not valid JSON ({str(exc)[:120]})") from None
    if not isinstance(doc, dict):
        raise ImageError.at(name, "must be a JSON object")
    problems = ProblemCollector()
    for key in doc:
        if key not in _SIDECAR_KEYS:
            problems.add(f"{name}.{key}", "unknown key; expected " + ", ".join(_SIDECAR_KEYS))
    if doc.get("format", SIDECAR_FORMAT) != SIDECAR_FORMAT:
        problems.add(f"{name}.format", f"must be {SIDECAR_FORMAT!r}")
    texts = {}
    for key in ("sequence_id", "spacecraft"):
        value = doc.get(key)
        if value is not None and (not isinstance(value, str) or not value.strip() or len(value) > 128):
            problems.add(f"{name}.{key}", "must be a non-empty string of at most 128 characters")
        else:
            texts[key] = value.strip() if isinstance(value, str) else None
    camera = doc.get("camera")
    if camera is not None and not isinstance(camera, (dict, str)):
        problems.add(f"{name}.camera", "must be a camera object or a camera name")
    fov = _bounded_number(doc, "fov_deg", name, problems, *FOV_BOUNDS_DEG)
    max_sources = doc.get("max_sources")
    if max_sources is not None and (isinstance(max_sources, bool) or not isinstance(max_sources, int)
                                    or not 3 <= max_sources <= 64):
        problems.add(f"{name}.max_sources", "must be an integer from 3 to 64")
        max_sources = None
    threshold = _bounded_number(doc, "threshold_sigma", name, problems, 2.0, 100.0)
    times: dict[tuple[str, int | None], datetime] = {}
    frames = doc.get("frames", [])
    if not isinstance(frames, list):
        problems.add(f"{name}.frames", "must be an array of {\"file\", \"time\"} objects")
        frames = []
    for i, entry in enumerate(frames):
        loc = f"{name}.frames[{i}]"
        if not isinstance(entry, dict):
            problems.add(loc, "must be an object {\"file\", \"time\"}")
            continue
        for key in entry:
            if key not in _SIDECAR_FRAME_KEYS:
                problems.add(f"{loc}.{key}", "unknown key; expected file, time, part")
        file = entry.get("file")
        if not isinstance(file, str) or not file.strip():
            problems.add(f"{loc}.file", "must be the image's file name")
            continue
        part = entry.get("part")
        if part is not None and (isinstance(part, bool) or not isinstance(part, int) or part < 0):
            problems.add(f"{loc}.part", "must be the HDU (FITS) or page (TIFF) number, >= 0")
            continue
        t = _sidecar_time(entry.get("time"), f"{loc}.time", problems)
        key = (_base_name(file), part)
        if key in times:
            problems.add(f"{loc}.file", f"{file!r} is listed twice")
        elif t is not None:
            times[key] = t
    problems.raise_if_any(error=ImageError)
    return Sidecar(sequence_id=texts.get("sequence_id"), spacecraft=texts.get("spacecraft"), camera=camera,
                   fov_deg=fov, times=times, max_sources=max_sources, threshold_sigma=threshold,
                   velocity_km_s=doc.get("velocity_km_s"))


def _bounded_number(doc: dict, key: str, name: str, problems: ProblemCollector, low: float, high: float):
    value = doc.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not low <= value <= high:
        problems.add(f"{name}.{key}", f"must be a number from {low:g} to {high:g}")
        return None
    return float(value)


def _base_name(name: str) -> str:
    return re.split(r"[\\/]", name)[-1]


def frames_content_sha256(file_hashes: list[str]) -> str:
    """The frames' content hash: SHA-256 of their files' SHA-256s, sorted (names and order do not count)."""
    return hashlib.sha256("\n".join(sorted(file_hashes)).encode()).hexdigest()


@dataclass
class _Measured:
    frame_location: str
    file: str
    part: int | None
    time: datetime | None  # None until the pass's frames are known (then assumed)
    #: Where the time came from: caller, sidecar, file (its FITS header or EXIF) or assumed.
    time_from: str
    width: int
    height: int
    bits: int
    detections: Detections
    sha256: str
    #: The side of the blocks detection searched (1: the image's own pixels; app.frames.binning).
    binned: int = 1


def frames_to_sequence(files: list[tuple[str, bytes]], *, sidecar: Sidecar | None = None,
                       sequence_id: str | None = None, spacecraft: str | None = None,
                       fov_deg: float | None = None, default_id: str | None = None,
                       options: DetectionOptions | None = None, hot_map: HotPixelMap | None = None,
                       limits: FrameLimits | None = None, deadline: float | None = None,
                       decoded: list[Frame] | None = None, caller_time: datetime | None = None) -> FramePass:
    """One pass of frames -> its Sequence (see the module).  ``files``: (name, bytes), any order.

    ``sequence_id``, ``spacecraft``, ``fov_deg`` given here win over the sidecar's, which win over
    the FITS headers'; the id falls back to ``default_id``, then the first file's stem.
    ``hot_map``: the camera's stored map (applied before detection when its sensor size matches).
    ``deadline``: a ``time.monotonic()`` value; past it :class:`FramesTimeout` is raised between frames.
    ``decoded``: frames already read (``files`` then empty; their hash is their pixels'), for benchmarks.
    ``caller_time``: the time of a pass of one frame (``--time``, the API's ``time`` field), over the
    sidecar's and the file's; frames without any time are assumed 1 s apart in file-name order (HDUs and
    pages in theirs), whatever order ``files`` come in.
    Raises ImageError (located) for anything invalid.
    """
    limits = limits or FrameLimits()
    sidecar = sidecar or Sidecar()
    base = options or DetectionOptions()
    options = DetectionOptions(**{**base.to_dict(),
                                  **({"max_sources": sidecar.max_sources} if sidecar.max_sources else {}),
                                  **({"threshold_sigma": sidecar.threshold_sigma} if sidecar.threshold_sigma else {})})
    if decoded is not None:  # no file, no hash: the location stands for both
        files = [(frame.location, frame.location.encode()) for frame in decoded]
    if not files:
        raise ImageError.at("files", "no image file given")
    if len(files) > limits.max_frames:
        raise ImageError.at("files", f"{len(files)} files; at most {limits.max_frames} frames per pass")
    total = sum(len(data) for _, data in files)
    if total > limits.max_bytes:
        raise ImageError.at("files", f"{total} bytes; at most {limits.max_bytes} per pass (STARID_FRAMES_MAX_BYTES)")
    names = [_base_name(name) for name, _ in files]
    if len(set(names)) != len(names):
        raise ImageError.at("files", "two files have the same name: " +
                            next(n for n in names if names.count(n) > 1))
    listed = {file for file, _ in sidecar.times}
    unknown = sorted(listed - set(names))
    if unknown:
        raise ImageError.at("sidecar.frames", f"names file(s) not given: {', '.join(unknown[:5])}")
    measured: list[_Measured] = []
    file_notes: list[str] = []
    first_meta: dict = {}
    size: tuple[int, int] | None = None
    pixels_total = 0
    prior_hot = hot_map.hot if hot_map is not None else []
    def frames_of(index: int, data: bytes, short: str):
        return iter([decoded[index]]) if decoded is not None else read_frames(data, short, limits)

    for index, ((name, data), short) in enumerate(zip(files, names)):
        digest = file_sha256(data)
        for frame in frames_of(index, data, short):
            if deadline is not None and time.monotonic() > deadline:
                raise FramesTimeout(f"reading and detecting the frames took longer than {limits.timeout_s:g} s")
            if size is None:
                size = (frame.width, frame.height)
                first_meta = frame.meta
                if hot_map is not None and (hot_map.width, hot_map.height) != size:
                    prior_hot = []
            elif (frame.width, frame.height) != size:
                raise ImageError.at(frame.location, f"{frame.width} x {frame.height} pixels, but the first frame "
                                                        f"is {size[0]} x {size[1]}: one pass, one camera")
            if len(measured) >= limits.max_frames:
                raise ImageError.at(frame.location, f"more than {limits.max_frames} frames in the pass")
            pixels_total += frame.width * frame.height
            if pixels_total > limits.max_total_pixels:
                raise ImageError.at(frame.location, f"the frames hold more than {limits.max_total_pixels} pixels "
                                                        "in all (STARID_FRAMES_MAX_TOTAL_PIXELS)")
            if caller_time is not None and measured:
                raise ImageError.at("time", "one time (--time, the time field) was given for a pass of several "
                                                "frames: list each frame's time in the sidecar instead")
            listed = sidecar.times.get((short, frame.part), sidecar.times.get((short, None)))
            found_times = [(caller_time, "caller"), (listed, "sidecar"), (frame.time, "file")]
            when, time_from = next(((t, source) for t, source in found_times if t is not None), (None, "assumed"))
            try:  # a frame over the detection budget is searched as block means; found in its own pixels
                found = detect_on_blocks(frame.detection_pixels, frame.binned, options,
                                         integer_values=frame.integer_values, saturation=frame.saturation,
                                         hot_pixels=prior_hot)
            except DetectionError as exc:
                raise ImageError.at(frame.location, str(exc)) from None
            measured.append(_Measured(frame.location, short, frame.part, when, time_from, frame.width,
                                      frame.height, frame.bits, found, digest, binned=frame.binned))
            if frame.meta.get("time_note") and time_from == "file":
                file_notes.append(frame.meta["time_note"])
            if frame.meta.get("orientation_note"):
                file_notes.append(frame.meta["orientation_note"])
    if deadline is not None and time.monotonic() > deadline:
        raise FramesTimeout(f"reading and detecting the frames took longer than {limits.timeout_s:g} s")
    untimed = [m for m in measured if m.time is None]
    if untimed and len(untimed) < len(measured):
        raise mixed_times_error(untimed[0].frame_location, next(m.frame_location for m in measured if m.time))
    for m, t in zip(sorted(untimed, key=lambda m: (m.file, -1 if m.part is None else m.part)),
                    assumed_times(len(untimed))):
        m.time = t
    measured.sort(key=lambda m: m.time)
    for earlier, later in zip(measured, measured[1:]):
        if later.time == earlier.time:
            raise ImageError.at(f"{later.frame_location}.time",
                                f"the same time as {earlier.frame_location} ({utc_text(later.time)}): "
                                "each frame needs its own time")
    width, height = size
    start_map = hot_map if hot_map is not None and (hot_map.width, hot_map.height) == size \
        else HotPixelMap.empty(width, height)
    stars = [np.flatnonzero(m.detections.is_star) for m in measured]
    stationary = stationary_candidates([[tuple(int(v) for v in m.detections.peak_pixel[k]) for k in ks]
                                        for m, ks in zip(measured, stars)],
                                       [m.detections.xy[ks] for m, ks in zip(measured, stars)])
    candidates = [m.detections.hot_pixel_candidates() + still for m, still in zip(measured, stationary)]
    updated = start_map.with_frames(candidates)
    hot = updated.hot
    camera, optics_from = _camera_block(sidecar, fov_deg, first_meta, width, height)
    snapshots, reports = [], []
    for i, m in enumerate(measured):
        d = m.detections
        on_hot = near_hot_pixel(d.peak_pixel, hot, radius_px=1.0) if len(d) else np.zeros(0, bool)
        usable = d.is_star & ~on_hot
        kept = np.flatnonzero(usable)[:options.max_sources]
        snapshots.append({"index": i, "time": utc_text(m.time),
                          "sources": [{"x": round(float(d.xy[k, 0]), 3), "y": round(float(d.xy[k, 1]), 3),
                                       "brightness": round(float(d.flux[k]), 2)} for k in kept]})
        rejected = []
        for k in range(len(d)):
            reasons = [f for f in d.flags[k] if f in REJECTING_FLAGS]
            if on_hot[k] and "hot_pixel" not in reasons:
                reasons.append("mapped_hot_pixel")
            if reasons and len(rejected) < MAX_REJECTED_LISTED:
                rejected.append([round(float(d.xy[k, 0]), 2), round(float(d.xy[k, 1]), 2), "+".join(reasons)])
        reports.append({"file": m.file, "part": m.part, "sha256": m.sha256, "time_from": m.time_from,
                        "width": m.width, "height": m.height, **({"binned": m.binned} if m.binned > 1 else {}),
                        "bits": m.bits, "background": round(d.background, 3), "noise": round(d.noise, 4),
                        "detected": len(d), "kept": len(kept),
                        "saturated_kept": int(sum("saturated" in d.flags[k] for k in kept)),
                        **({"trailed": round(d.smear, 2)} if d.smear is not None else {}),
                        "rejected": rejected})
    frames_sha = frames_content_sha256(sorted({m.sha256 for m in measured}))
    binned = [m for m in measured if m.binned > 1]  # one pass, one size: all frames or none
    notes = ([binning_note(binned[0], len(binned), limits.max_pixels_per_frame)] if binned else []) + file_notes
    trailed = [m for m in measured if m.detections.smear is not None]
    if trailed:
        notes.append(trailed_note(trailed, len(measured)))
    few = [(m, r) for m, r in zip(measured, reports) if r["kept"] < MIN_PATTERN_SOURCES]
    if few:
        notes.append(few_sources_note(*few[0], len(few)))
    import sep

    doc = {
        "format": FORMAT_NAME,
        "sequence_id": _sequence_id(sequence_id or sidecar.sequence_id or first_meta.get("sequence_id")
                                    or default_id or names[0]),
        "spacecraft": spacecraft or sidecar.spacecraft or first_meta.get("spacecraft"),
        "camera": camera,
        "snapshots": snapshots,
        "frames": {"format": SIDECAR_FORMAT, "content_sha256": frames_sha, "detector": f"sep {sep.__version__}",
                   "options": options.to_dict(), "optics_from": optics_from,
                   "hot_pixel_map": {"version": start_map.version, "hot_pixels": len(hot),
                                     "frames_counted": updated.frames},
                   "frames": reports, **({"notes": notes} if notes else {})},
    }
    if doc["spacecraft"] is None:
        del doc["spacecraft"]
    if sidecar.velocity_km_s is not None:
        doc["velocity_km_s"] = sidecar.velocity_km_s
    if untimed:
        doc["time_assumed"] = True
    text = json.dumps(doc)
    try:
        sequence = parse_telemetry(text, max_bytes=len(text.encode()) + 1)
    except TelemetryError as exc:
        raise _relocated(exc, camera_from_sidecar=isinstance(sidecar.camera, (dict, str))) from None
    return FramePass(sequence=sequence, raw_text=dump_json(sequence), hot_map=updated,
                     detections=[m.detections for m in measured], frames_sha256=frames_sha, candidates=candidates)


def trailed_note(trailed: list[_Measured], count: int) -> str:
    """What the frames block says of frames whose stars are trailed alike (:func:`app.frames.detect._smear`)."""
    where = trailed[0].frame_location if count == 1 else f"{len(trailed)} of the {count} frames"
    elongation = float(np.median([m.detections.smear for m in trailed]))
    return (f"{where}: the stars are trailed (a / b {elongation:.1f}: a fixed camera under the turning sky, or a "
            "camera turning during the exposure); each is detected whole, at its middle (the mid-exposure place)")


def few_sources_note(first: _Measured, report: dict, count: int) -> str:
    """What the frames block says of frames that kept fewer star-like sources than a pattern needs (``count`` of
    them, ``first`` with its ``report``): how many were detected and why the rest were set aside, so that an
    operator reads "nothing like a star here" rather than a pattern too small."""
    others = f"; {count - 1} other frame(s) kept fewer than {MIN_PATTERN_SOURCES} too" if count > 1 else ""
    reasons = Counter(flag for flags in first.detections.flags for flag in flags if flag in REJECTING_FLAGS)
    kept = report["kept"]
    found = "no star-like source" if kept == 0 else f"{kept} star-like source{'s' * (kept != 1)}"
    if not report["detected"]:
        seen = "nothing stands out of the sky's noise"
    else:
        seen = (f"{report['detected']} blob(s) detected"
                + (", set aside as " + ", ".join(f"{reason} ({n})" for reason, n in reasons.most_common())
                   if reasons else ""))
    return f"{first.frame_location}: {found} ({seen}); a pattern needs at least {MIN_PATTERN_SOURCES}{others}"


def binning_note(first: _Measured, count: int, budget: int) -> str:
    """What the frames block says of a pass searched as block means: ``count`` frames of one size,
    ``first`` of them."""
    width, height, b = first.width, first.height, first.binned
    where = first.frame_location + (f" and the {count - 1} other frame(s)" if count > 1 else "")
    note = (f"{where}: {width} x {height} pixels, more than the {budget} searched per frame "
            f"(STARID_FRAMES_MAX_PIXELS): searched as the means of {b} x {b} blocks ({width // b} x {height // b}); "
            "positions are in the image's own pixels")
    cols, rows = width % b, height % b
    if cols or rows:
        note += (f"; its last {cols} column(s) and {rows} row(s) on the right and at the bottom, less than a "
                 "block, were not searched")
    return note


def _sequence_id(text: str) -> str:
    """A file stem or name reduced to an id: extension dropped, odd characters as '-'."""
    stem = re.sub(r"\.(fits|fit|fts|png|jpe?g|tiff?)$", "", text.strip(), flags=re.IGNORECASE)
    return (_ID_RE.sub("-", stem).strip("-") or "frames")[:128]


def camera_for_fov(width: int, height: int, fov_deg: float) -> dict:
    """A camera block for a horizontal field of view across ``width`` (centred principal point), its focal
    length known to :func:`fov_focal_tolerance`."""
    return _centred_camera(width, height, (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0),
                           round(fov_focal_tolerance(fov_deg), 4))


def _centred_camera(width: int, height: int, focal_px: float, tolerance: float | None) -> dict:
    """A camera block: a pinhole of ``focal_px`` centred on the frame, known to ``tolerance`` (None: left out)."""
    block = {"width": width, "height": height, "focal_length_px": round(focal_px, 3), "cx": (width - 1) / 2.0,
             "cy": (height - 1) / 2.0}
    return block if tolerance is None else {**block, "focal_length_tolerance": tolerance}


def fov_focal_tolerance(fov_deg: float) -> float:
    """The focal length's tolerance for a field of view known to :data:`FOV_TOLERANCE`: the focal lengths of
    the field +-5 % (f = w / 2 / tan(fov / 2), so a fraction of the angle is about ``fov / sin(fov)`` times
    that fraction of the focal length: 1.0x at 10 deg, 1.9x at 105 deg), plus the distortion's share of
    :data:`FOV_FOCAL_TOLERANCE`; never less than that, at most 0.2 (a camera model's bound)."""
    half = math.radians(fov_deg) / 2.0
    spans = [abs(math.tan(half) / math.tan(half * (1.0 + s)) - 1.0) for s in (-FOV_TOLERANCE, FOV_TOLERANCE)]
    return min(0.2, max(FOV_FOCAL_TOLERANCE, max(spans) + FOV_FOCAL_TOLERANCE - FOV_TOLERANCE))


def _camera_block(sidecar: Sidecar, fov_deg: float | None, meta: dict, width: int, height: int):
    """(camera block or name, where the optics came from)."""
    if fov_deg is not None:
        if not (isinstance(fov_deg, (int, float)) and math.isfinite(fov_deg)
                and FOV_BOUNDS_DEG[0] <= fov_deg <= FOV_BOUNDS_DEG[1]):
            raise ImageError.at("fov_deg", f"must be a number from {FOV_BOUNDS_DEG[0]:g} to {FOV_BOUNDS_DEG[1]:g} "
                                               f"degrees, got {fov_deg!r}")
        return camera_for_fov(width, height, float(fov_deg)), f"fov_deg {float(fov_deg):g}"
    if isinstance(sidecar.camera, dict):
        _check_camera_object(sidecar.camera, width, height)
        return {"width": width, "height": height, **sidecar.camera}, "sidecar camera"
    if isinstance(sidecar.camera, str):
        _check_named_camera(sidecar.camera, width, height)
        return sidecar.camera, f"camera {sidecar.camera}"
    if sidecar.fov_deg is not None:
        return camera_for_fov(width, height, sidecar.fov_deg), f"sidecar fov_deg {sidecar.fov_deg:g}"
    if meta.get("focal_length_px"):
        return _centred_camera(width, height, float(meta["focal_length_px"]), FOV_FOCAL_TOLERANCE), meta["optics_from"]
    # No optics declared: identification searches the field of view (app.identification.scale_free), first
    # within the tolerance of a field of view given for it at a hinted focal length (a photograph's EXIF lens).
    hint = meta.get("focal_length_hint_px")
    if hint:
        fov = math.degrees(2.0 * math.atan(width / 2.0 / hint))
        if FOV_BOUNDS_DEG[0] <= fov <= FOV_BOUNDS_DEG[1]:
            hinted = _centred_camera(width, height, hint, round(fov_focal_tolerance(fov), 4))
            return ({**hinted, "focal_length_unknown": True},
                    f"{meta['optics_from']}: a hint of {fov:.1f} deg for the field-of-view search")
    nominal = camera_for_fov(width, height, UNKNOWN_OPTICS_NOMINAL_FOV_DEG)
    del nominal["focal_length_tolerance"]
    return {**nominal, "focal_length_unknown": True}, "unknown optics (field of view searched)"


def _check_camera_object(camera: dict, width: int, height: int) -> None:
    """A sidecar camera block's width and height, when given, must be the frames': its focal length and
    principal point are in its pixels, so on frames of another size every position would be wrong."""
    problems = ProblemCollector()
    for key, size in (("width", width), ("height", height)):
        if key in camera and camera[key] != size:
            problems.add(f"sidecar.camera.{key}", f"{camera[key]!r}, but the frames are {width} x {height}")
    problems.raise_if_any(error=ImageError)


def _check_named_camera(name: str, width: int, height: int) -> None:
    """A built-in camera named by the sidecar must have the frames' size, for the same reason as a camera
    block: otherwise a larger camera is stored with the wrong geometry, and a smaller one is refused at
    detected blobs "outside the sensor", which the user never wrote.  An unknown name is left to the
    document's validation, which lists the known cameras (located at ``sidecar.camera`` too)."""
    camera = CAMERAS.get(name)
    if camera is not None and (camera.width, camera.height) != (width, height):
        raise ImageError.at("sidecar.camera", f"{name} is {camera.width} x {camera.height}, "
                                                  f"but the frames are {width} x {height}")


def _relocated(exc: TelemetryError, camera_from_sidecar: bool) -> ImageError:
    """Problems of the generated document located where the user can fix them (the sidecar's camera)."""
    problems = []
    for p in exc.problems:
        location = p.location
        if camera_from_sidecar and location.startswith("camera"):
            location = "sidecar." + location
        problems.append(Problem(location, p.message))
    return ImageError(problems, truncated=exc.truncated)
