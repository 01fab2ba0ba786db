"""Full-frame images in the workflow: uploads of a pass of frames, hot-pixel maps, image files
on the command line.

An upload of frames ends as an ordinary archived sequence: the frames are detected
(:func:`app.frames.frames_to_sequence`), extracted, and stored with
:func:`app.workflow.archive.store_upload` under the `tubsat-snapshots/1` text of the detected
sources (with the frames' content hash and detection report in its ``frames`` block), so the
archive stays text and everything downstream is unchanged.  The images themselves are not kept;
a preview of each is (:func:`frame_previews`: stretched to 8 bits, at most
:data:`PREVIEW_MAX_WIDTH` pixels wide, a PNG of at most 2 MiB, with the detections, rejected
blobs and hot pixels as an overlay), for the console (``GET /api/sequences/{id}/frames``).

Steps of ``POST /api/frames``: :func:`prepare_frames` (in a thread: the sidecar, the upload's
hash and whether the same frames were stored before, the spacecraft's hot-pixel map),
:func:`frames_job` (in the compute pool: reading, detection, extraction, the previews; errors
come back as values because a TelemetryError does not survive pickling), :func:`store_frames`
(in a thread: the upload, its previews, then the spacecraft's hot-pixel map as a new version).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import logging
import math
import os
import re
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from app.extraction import extract
from app.frames import (Detections, FrameLimits, FramePass, FramesTimeout, HotPixelMap, Sidecar,
                        drop_hot_pixel_sources, frames_content_sha256, frames_to_sequence, looks_like_image,
                        near_hot_pixel, parse_sidecar, peek_frame, read_frames)
from app.frames.detect import REJECTING_FLAGS, DetectionOptions
from app.filenames import FOLDER_SIDECAR, IMAGE_SUFFIXES, SIDECAR_SUFFIX, image_sidecar
from app.frames.binning import block_mean  # the frame averaged over blocks: what a preview shows
from app.frames.images import file_sha256
from app.storage import MAX_PREVIEW_PNG_BYTES, StaleHotPixelMap
from app.telemetry import Sequence
from app.telemetry.errors import ImageError, Problem, TelemetryError
from app.timefmt import utc_text
from app.workflow import archive
from app.workflow.context import AppContext
from app.workflow.documents import Document, FramePreviewInfo, FramePreviewsDocument, UploadDocument
from app.workflow.errors import Busy, NotFound

log = logging.getLogger(__name__)

#: Tries at storing a hot-pixel map when other uploads of the same camera store theirs at once.
MAP_STORE_TRIES = 5
#: Widest preview image, pixels: a wider frame is averaged over scale x scale blocks, the smallest
#: integer scale that brings it to this width or less.
PREVIEW_MAX_WIDTH = 1024
#: Most bytes of all the previews of one pass (64 frames of a busy 16 Mpx camera would be ~100 MiB);
#: frames after the budget is spent have no preview.  Each PNG is at most ``MAX_PREVIEW_PNG_BYTES``
#: (2 MiB): a PNG larger than that is made again at twice the scale, until it fits.
PREVIEW_PASS_BYTES = 32 * 1024 * 1024
#: Pixels this many noise sigmas above the background are white in a preview.
STRETCH_TOP_SIGMA = 50.0
#: Rejected blobs and hot pixels listed in one preview's overlay (the brightest blobs; the map's
#: first hot pixels); the overlay says how many there were in all.
OVERLAY_MAX_REJECTED = 200
OVERLAY_MAX_HOT_PIXELS = 2000
#: A reported source is the detection within this distance (pixels): the sources are the
#: detections' positions rounded to 3 decimals.
SOURCE_MATCH_PX = 0.01


# ---------------------------------------------------------------------------
# Documents
# ---------------------------------------------------------------------------

class HotPixelMapVersion(Document):
    version: int
    frames: int
    hot_pixels: int
    seq_id: int | None = None
    created_at: str


class HotPixelMapDocument(Document):
    """A camera's current hot-pixel map and its history (``GET /api/frames/hot-pixels``)."""

    spacecraft: str
    sensor: str
    version: int
    frames: int
    hot_pixels: list[tuple[int, int]]
    history: list[HotPixelMapVersion]


# ---------------------------------------------------------------------------
# Uploads
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class FramesRequest:
    """A checked upload of frames, ready for the compute pool."""

    files: list[tuple[str, bytes]]
    sidecar: Sidecar | None
    sequence_id: str | None
    spacecraft: str | None
    fov_deg: float | None
    upload_sha256: str
    #: The spacecraft and sensor whose hot-pixel map applies (spacecraft None: no map kept).
    map_spacecraft: str | None
    hot_map: HotPixelMap | None
    limits: FrameLimits
    #: The caller's time of a pass of one frame (the ``time`` field), over the sidecar's and the file's.
    time: datetime | None = None


@dataclass(frozen=True, eq=False)
class FramesResult:
    """What :func:`frames_job` hands back: the pass and its extraction, or the problems."""

    frame_pass: FramePass | None = None
    extraction: object = None
    problems: list[dict] | None = None
    timeout: str | None = None
    #: A preview per frame (snapshot order; frames without one are left out).
    previews: list["FramePreview"] = dataclasses.field(default_factory=list)


def upload_sha256(files: list[tuple[str, bytes]], sidecar: bytes | None, sequence_id: str | None,
                  spacecraft: str | None, fov_deg: float | None, caller_time: datetime | None = None) -> str:
    """The hash that makes an upload of frames "the same": the frames' content, the sidecar, the fields
    and the detector's defaults (file names and order do not count)."""
    key = {"frames": frames_content_sha256([file_sha256(data) for _, data in files]),
           "sidecar": None if sidecar is None else hashlib.sha256(sidecar).hexdigest(),
           "names": sorted(archive.clean_filename(name) or "" for name, _ in files),
           "sequence_id": sequence_id, "spacecraft": spacecraft, "fov_deg": fov_deg,
           "detector": DetectionOptions().to_dict()}
    if caller_time is not None:  # absent otherwise: the uploads stored before the field keep their hash
        key["time"] = utc_text(caller_time)
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


def prepare_frames(ctx: AppContext, files: list[tuple[str, bytes]], sidecar: bytes | None,
                   sequence_id: str | None, spacecraft: str | None,
                   fov_deg: float | None, caller_time: datetime | None = None) -> FramesRequest | UploadDocument:
    """Check an upload of frames; the stored sequence's document when the same upload was stored before.

    Raises ImageError (located problems) for a bad sidecar or too many files or bytes.
    """
    limits = FrameLimits()
    files = [(archive.clean_filename(name) or f"frame-{i}", bytes(data)) for i, (name, data) in enumerate(files)]
    if not files:
        raise ImageError.at("body.files", "no image: send the frames as 'files' fields")
    if len(files) > limits.max_frames:
        raise ImageError.at("body.files", f"{len(files)} files; at most {limits.max_frames} frames per pass")
    parsed_sidecar = parse_sidecar(sidecar) if sidecar is not None else None
    key = upload_sha256(files, sidecar, sequence_id, spacecraft, fov_deg, caller_time)
    seq_id = ctx.storage.find_frame_upload(key)
    if seq_id is not None:
        return _stored_document(ctx, seq_id)
    peek = peek_frame(files[0][1], files[0][0])
    map_spacecraft = spacecraft or (parsed_sidecar.spacecraft if parsed_sidecar else None) \
        or (peek[2].get("spacecraft") if peek else None)
    hot_map = None
    if map_spacecraft and peek:
        hot_map = current_hot_pixel_map(ctx, map_spacecraft, peek[0], peek[1])
    return FramesRequest(files=files, sidecar=parsed_sidecar, sequence_id=sequence_id, spacecraft=spacecraft,
                         fov_deg=fov_deg, upload_sha256=key, map_spacecraft=map_spacecraft, hot_map=hot_map,
                         limits=limits, time=caller_time)


def frames_job(request: FramesRequest, *, sky=None) -> FramesResult:
    """Read, detect and extract one pass (a compute-pool job; needs no catalogue)."""
    deadline = time.monotonic() + request.limits.timeout_s
    try:
        frame_pass = frames_to_sequence(request.files, sidecar=request.sidecar, sequence_id=request.sequence_id,
                                        spacecraft=request.spacecraft, fov_deg=request.fov_deg,
                                        hot_map=request.hot_map, limits=request.limits, deadline=deadline,
                                        caller_time=request.time)
    except TelemetryError as exc:
        return FramesResult(problems=[p.to_dict() for p in exc.problems])
    except FramesTimeout as exc:
        return FramesResult(timeout=str(exc))
    except Exception as exc:  # noqa: BLE001 - an image library failing on odd input: the upload's fault, said so
        log.warning("frames could not be processed", exc_info=True)
        return FramesResult(problems=[{"location": "files", "message": "the images could not be processed "
                                       f"({type(exc).__name__}: {str(exc)[:160]})"}])
    extraction = extract(frame_pass.sequence)
    try:
        previews = frame_previews(request.files, frame_pass, request.limits, deadline=deadline)
    except Exception:  # noqa: BLE001 - the previews are a convenience: never the reason an upload fails
        log.warning("no previews of the frames", exc_info=True)
        previews = []
    return FramesResult(frame_pass=frame_pass, extraction=extraction, previews=previews)


def store_frames(ctx: AppContext, request: FramesRequest, result: FramesResult) -> UploadDocument:
    """Store the pass as an ordinary upload, record its upload hash, and add its frames to the camera's
    hot-pixel map (a new version; only for a new upload of a named spacecraft)."""
    if result.timeout is not None:
        raise Busy(result.timeout)
    if result.problems is not None:
        raise ImageError([Problem(p["location"], p["message"]) for p in result.problems])
    frame_pass = result.frame_pass
    names = [name for name, _ in request.files]
    label = names[0] if len(names) == 1 else f"{names[0]} (+{len(names) - 1} frames)"
    upload = archive.ParsedUpload(sequence=frame_pass.sequence, raw_text=frame_pass.raw_text, filename=label[:200])
    doc = archive.store_upload(ctx, upload, result.extraction)
    recorded = ctx.storage.add_frame_upload(request.upload_sha256, doc.id)
    if recorded != doc.id:
        return _stored_document(ctx, recorded)
    if result.previews:
        # Append-only: a sequence that has previews keeps them (the same detections from other frames).
        ctx.storage.add_frame_previews(doc.id, [p.to_storage() for p in result.previews])
    spacecraft = frame_pass.sequence.spacecraft or request.map_spacecraft
    if doc.created and spacecraft:
        add_frames_to_map(ctx, spacecraft, frame_pass, doc.id)
    return doc


def add_frames_to_map(ctx: AppContext, spacecraft: str, frame_pass: FramePass, seq_id: int | None) -> HotPixelMap:
    """The pass's hot-pixel candidates added to the spacecraft's stored map, as a new version."""
    camera = frame_pass.sequence.camera
    candidates = frame_pass.candidates
    for _ in range(MAP_STORE_TRIES):
        current = current_hot_pixel_map(ctx, spacecraft, camera.width, camera.height)
        base = current or HotPixelMap.empty(camera.width, camera.height)
        merged = base.with_frames(candidates)
        try:
            row = ctx.storage.add_hot_pixel_map(spacecraft, merged.sensor, map_doc=merged.to_json(),
                                                frames=merged.frames, hot_pixels=len(merged.hot),
                                                based_on=None if current is None else current.version, seq_id=seq_id)
        except StaleHotPixelMap:
            continue  # another upload of this camera stored its map meanwhile: merge again
        return HotPixelMap.from_json(row.map, version=row.version)
    raise Busy(f"the hot-pixel map of {spacecraft} changed {MAP_STORE_TRIES} times while this upload was "
               "stored; the upload itself is stored")


def current_hot_pixel_map(ctx: AppContext, spacecraft: str | None, width: int, height: int) -> HotPixelMap | None:
    """The stored map of this spacecraft's camera of this sensor size, if any."""
    row = ctx.storage.current_hot_pixel_map(spacecraft, f"{width}x{height}")
    return None if row is None else HotPixelMap.from_json(row.map, version=row.version)


def hot_pixel_map_document(ctx: AppContext, spacecraft: str, sensor: str) -> HotPixelMapDocument:
    rows = ctx.storage.hot_pixel_map_history(spacecraft, sensor)
    if not rows:
        raise NotFound(f"no hot-pixel map of {spacecraft}'s {sensor} camera")
    last = rows[-1]
    current = HotPixelMap.from_json(last.map, version=last.version)
    return HotPixelMapDocument(spacecraft=spacecraft, sensor=sensor, version=last.version, frames=last.frames,
                               hot_pixels=current.hot,
                               history=[HotPixelMapVersion(version=r.version, frames=r.frames,
                                                           hot_pixels=r.hot_pixels, seq_id=r.seq_id,
                                                           created_at=r.created_at.isoformat()) for r in rows])


def without_hot_pixels(ctx: AppContext, sequence: Sequence) -> tuple[Sequence, list[list[int]]]:
    """Spot-list telemetry without its sources on the spacecraft's mapped hot pixels (same sensor size).

    ``(sequence, dropped)``: ``dropped[i]`` are the file-order positions removed from snapshot i.
    Not what the archive does with a spot-list upload: removing sources renumbers the rest, and the
    stored extraction's numbering is authoritative, so :func:`app.workflow.archive.parse_upload` flags
    them instead (:func:`app.workflow.archive.hot_pixel_sources`) and extraction gives them the
    ``hot_pixel`` verdict in place.  This is for a caller that wants the filtered telemetry itself.
    """
    hot_map = current_hot_pixel_map(ctx, sequence.spacecraft, sequence.camera.width, sequence.camera.height)
    if hot_map is None:
        return sequence, [[] for _ in sequence.snapshots]
    return drop_hot_pixel_sources(sequence, hot_map.hot)


# ---------------------------------------------------------------------------
# Previews: what the console shows of each frame
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class FramePreview:
    """One frame as the console shows it: an 8-bit PNG of ``image_width`` x ``image_height`` pixels, each
    the mean of ``scale`` x ``scale`` pixels of the ``width`` x ``height`` frame, and its overlay."""

    snapshot: int
    width: int
    height: int
    scale: int
    image_width: int
    image_height: int
    png: bytes
    overlay: dict

    def to_storage(self) -> dict:
        return dataclasses.asdict(self)


def preview_scale(width: int) -> int:
    """The smallest integer scale that makes a frame ``width`` pixels wide at most :data:`PREVIEW_MAX_WIDTH`."""
    return max(1, math.ceil(width / PREVIEW_MAX_WIDTH))


def stretch_to_8bit(image: np.ndarray) -> np.ndarray:
    """A frame as 8-bit grey an operator can read: the background (median) nearly black with its noise
    (MAD) just visible, stars a few sigma high clear of it, bright ones not all white: an asinh stretch
    from the background (black) to :data:`STRETCH_TOP_SIGMA` sigma above it (white), about linear
    for the first 2 sigma.  Relative to the noise, so hot pixels and saturated stars do not darken
    the rest."""
    data = np.asarray(image, dtype=np.float64)
    finite = np.isfinite(data)
    if not finite.all():
        data = np.where(finite, data, np.median(data[finite]) if finite.any() else 0.0)
    step = max(1, int(math.sqrt(data.size / 250_000)))
    sample = data[::step, ::step]
    median = float(np.median(sample))
    sigma = 1.4826 * float(np.median(np.abs(sample - median)))
    if not sigma > 0:
        sigma = float(np.std(sample)) or 1.0
    low = median
    high = median + STRETCH_TOP_SIGMA * sigma
    soft = 2.0 * sigma
    scaled = np.arcsinh(np.clip(data - low, 0.0, None) / soft) / math.asinh((high - low) / soft)
    return np.clip(np.round(scaled * 255.0), 0, 255).astype(np.uint8)


def encode_png(image: np.ndarray) -> bytes:
    """A PNG of 8-bit grey (H, W) or colour (H, W, 3) pixels."""
    from PIL import Image

    stream = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8)).save(stream, format="PNG")
    return stream.getvalue()


def render_preview(pixels: np.ndarray, snapshot: int, overlay: dict, *, binned: int = 1,
                   size: tuple[int, int] | None = None) -> FramePreview | None:
    """The preview of one frame; at twice the scale while its PNG exceeds ``MAX_PREVIEW_PNG_BYTES``
    (None when even a 16-pixel-wide image would: not a frame to preview).

    ``pixels`` may be the means of ``binned`` x ``binned`` blocks covering a frame of ``size`` (width,
    height) pixels (:class:`app.frames.Frame` over the detection budget).  Averaged again over ``step`` x
    ``step`` of them, a preview pixel stands for ``binned * step`` square frame pixels (the cut blocks at
    the right and bottom weighted as whole ones: a preview's liberty), so the preview's scale is
    ``binned * step`` and its size ``ceil(size / scale)``, what the overlay (in the frame's own pixels) and
    the annotated frame (:mod:`app.workflow.annotate`) expect."""
    height, width = pixels.shape
    frame_width, frame_height = size or (width, height)
    step = preview_scale(width)
    while True:
        png = encode_png(stretch_to_8bit(block_mean(pixels, step)))
        if len(png) <= MAX_PREVIEW_PNG_BYTES:
            scale = binned * step
            return FramePreview(snapshot=snapshot, width=frame_width, height=frame_height, scale=scale,
                                image_width=-(-frame_width // scale), image_height=-(-frame_height // scale),
                                png=png, overlay=overlay)
        step *= 2
        if -(-width // step) < 16:
            return None


def frame_overlay(detections: Detections, snapshot, hot: list[tuple[int, int]]) -> dict:
    """What the console draws over one frame, in full-resolution pixels (0, 0 = centre of the top-left pixel).

    * ``detections``: the snapshot's sources in file order (``source`` = the index the extraction's
      tracks refer to), with the detector's flags (``saturated``, ``edge``);
    * ``rejected``: every other blob, brightest first, with why it is no source: ``hot_pixel``
      (one sharp pixel), ``mapped_hot_pixel`` (on a hot pixel of the camera's map), ``elongated``
      (a trail), ``extended`` (glare, the Moon), ``not_brightest`` (a star beyond the ``max_sources``
      brightest reported), plus its other flags;
    * ``hot_pixels``: the hot pixels of the camera's map applied to the pass.
    """
    xy = detections.xy
    used: set[int] = set()
    rows = []
    for j in range(snapshot.n_sources):
        x, y = float(snapshot.xy[j, 0]), float(snapshot.xy[j, 1])
        flags: list[str] = []
        if len(detections):
            distance = np.hypot(xy[:, 0] - x, xy[:, 1] - y)
            k = int(np.argmin(distance))
            if distance[k] <= SOURCE_MATCH_PX and k not in used:
                used.add(k)
                flags = list(detections.flags[k])
        rows.append({"source": j, "x": round(x, 3), "y": round(y, 3),
                     "brightness": round(float(snapshot.brightness[j]), 2), "flags": flags})
    on_hot = near_hot_pixel(detections.peak_pixel, hot, radius_px=1.0) if len(detections) \
        else np.zeros(0, dtype=bool)
    rejected = []
    total = 0
    for k in range(len(detections)):
        if k in used:
            continue
        total += 1
        if len(rejected) >= OVERLAY_MAX_REJECTED:
            continue
        flags = detections.flags[k]
        reasons = [f for f in flags if f in REJECTING_FLAGS]
        if on_hot[k] and "hot_pixel" not in reasons:
            reasons.append("mapped_hot_pixel")
        if not reasons:
            reasons.append("not_brightest")
        reasons += [f for f in flags if f not in REJECTING_FLAGS]
        rejected.append({"x": round(float(xy[k, 0]), 2), "y": round(float(xy[k, 1]), 2), "reason": "+".join(reasons)})
    return {"detections": rows, "rejected": rejected, "rejected_total": total,
            "hot_pixels": [[int(x), int(y)] for x, y in hot[:OVERLAY_MAX_HOT_PIXELS]], "hot_pixels_total": len(hot)}


def frame_previews(files: list[tuple[str, bytes]], frame_pass: FramePass, limits: FrameLimits, *,
                   deadline: float | None = None) -> list[FramePreview]:
    """A preview of each frame of the pass, in snapshot order (the frames are read again, one file at a
    time: the pass keeps only its detections).  Frames past the deadline or the pass's byte budget
    (:data:`PREVIEW_PASS_BYTES`) get none."""
    reports = (frame_pass.sequence.extra.get("frames") or {}).get("frames") or []
    snapshot_of = {(report.get("file"), report.get("part")): i for i, report in enumerate(reports)}
    hot = frame_pass.hot_map.hot
    previews: dict[int, FramePreview] = {}
    spent = 0
    for name, data in files:
        for frame in read_frames(data, re.split(r"[\\/]", name)[-1], limits):
            i = snapshot_of.get((frame.file, frame.part))
            if i is None or i in previews or i >= len(frame_pass.detections):
                continue
            if (deadline is not None and time.monotonic() > deadline) or spent >= PREVIEW_PASS_BYTES:
                return [previews[k] for k in sorted(previews)]
            overlay = frame_overlay(frame_pass.detections[i], frame_pass.sequence.snapshots[i], hot)
            preview = render_preview(frame.pixels, i, overlay, binned=frame.binned,
                                     size=(frame.width, frame.height))
            if preview is not None and spent + len(preview.png) <= PREVIEW_PASS_BYTES:
                previews[i] = preview
                spent += len(preview.png)
    return [previews[k] for k in sorted(previews)]


def frame_previews_document(ctx: AppContext, seq_id: int) -> FramePreviewsDocument:
    """The previews kept of a sequence's frames (an empty list for spot-list uploads and frames uploaded
    before previews were kept); NotFound for an unknown sequence."""
    archive.require_sequence(ctx, seq_id)
    rows = ctx.storage.frame_previews(seq_id)
    return FramePreviewsDocument(sequence=seq_id, max_png_bytes=MAX_PREVIEW_PNG_BYTES,
                                 frames=[FramePreviewInfo.of(seq_id, row) for row in rows])


def frame_preview_png(ctx: AppContext, seq_id: int, snapshot: int) -> bytes:
    """The PNG of one snapshot's preview; NotFound (saying why) when there is none."""
    return frame_preview_row(ctx, seq_id, snapshot).png


def frame_preview_row(ctx: AppContext, seq_id: int, snapshot: int):
    """One snapshot's stored preview (:class:`app.storage.FramePreviewRow`, with its PNG); NotFound (saying
    why) when there is none."""
    row = ctx.storage.frame_preview(seq_id, snapshot)
    if row is not None:
        return row
    stored = archive.require_sequence(ctx, seq_id)
    if not ctx.storage.frame_previews(seq_id):
        raise NotFound(f"sequence {seq_id} has no frame images: it was uploaded as a spot list, or as frames "
                       "before their previews were kept")
    n = stored.n_snapshots
    raise NotFound(f"snapshot {snapshot} of sequence {seq_id} has no frame image"
                   + (f" (snapshots 0 to {n - 1})" if n and snapshot >= n else ""))


def _stored_document(ctx: AppContext, seq_id: int) -> UploadDocument:
    return archive.upload_document(ctx, archive.require_sequence(ctx, seq_id), created=False)


# ---------------------------------------------------------------------------
# Command line: image files and folders of frames
# ---------------------------------------------------------------------------

def is_frames_path(path: str) -> bool:
    """True for an image file, or a folder holding image files (what ``extract``/``solve`` read as frames)."""
    if os.path.isdir(path):
        try:
            return any(name.lower().endswith(IMAGE_SUFFIXES) for name in os.listdir(path))
        except OSError:
            return False
    if path.lower().endswith(IMAGE_SUFFIXES):
        return True
    try:
        with open(path, "rb") as stream:
            return looks_like_image(path, stream.read(16))
    except OSError:
        return False


def frames_sequence_from_path(path: str, *, fov_deg: float | None = None,
                              caller_time: datetime | None = None) -> Sequence:
    """One pass from an image file (with ``<stem>.frames.json`` beside it, if any) or a folder of frames
    (every image in it, in name order, with its ``frames.json``, if any; the folder's name is the default
    id).  ``caller_time``: the caller's time of a pass of one frame (over the sidecar's and the file's own).

    No archive here: the hot-pixel map is the pass's own.  Raises ImageError (located) for
    anything invalid, at ``file`` for files that cannot be read.
    """
    limits = FrameLimits()
    folder = Path(path)
    try:
        if folder.is_dir():
            images = sorted(p for p in folder.iterdir() if p.is_file() and p.name.lower().endswith(IMAGE_SUFFIXES))
            if not images:
                raise ImageError.at("file", "the folder holds no FITS, PNG, JPEG or TIFF file")
            sidecar_path = folder / FOLDER_SIDECAR
            default_id = folder.resolve().name
        else:
            images = [folder]
            sidecar_path = image_sidecar(folder)
            default_id = sidecar_path.name[: -len(SIDECAR_SUFFIX)]
        if len(images) > limits.max_frames:
            raise ImageError.at("file", f"{len(images)} images; at most {limits.max_frames} frames per pass")
        total = 0
        files = []
        for image in images:
            size = image.stat().st_size
            total += size
            if total > limits.max_bytes:
                raise ImageError.at(image.name, f"the frames exceed {limits.max_bytes} bytes in all "
                                                    "(STARID_FRAMES_MAX_BYTES)")
            files.append((image.name, image.read_bytes()))
        sidecar = None
        only = None
        if not sidecar_path.is_file() and not folder.is_dir():
            # A single frame of a folder: the folder's sidecar, for this file's entries.
            sidecar_path, only = folder.with_name(FOLDER_SIDECAR), folder.name
        if sidecar_path.is_file():
            if sidecar_path.stat().st_size > 1024 * 1024:
                raise ImageError.at("sidecar", "the sidecar is larger than 1 MiB")
            # Found beside the image, not given: its problems name it (a user who never wrote one asks "which?").
            sidecar = parse_sidecar(sidecar_path.read_bytes(), name=sidecar_path.name)
            if only is not None:
                sidecar = dataclasses.replace(sidecar, sequence_id=None,
                                              times={k: t for k, t in sidecar.times.items() if k[0] == only})
    except OSError as exc:
        raise ImageError.at("file", f"cannot read the file: {exc.strerror or type(exc).__name__}") from None
    try:
        return frames_to_sequence(files, sidecar=sidecar, fov_deg=fov_deg, default_id=default_id, limits=limits,
                                  deadline=time.monotonic() + limits.timeout_s, caller_time=caller_time).sequence
    except FramesTimeout as exc:
        raise ImageError.at("file", str(exc)) from None
