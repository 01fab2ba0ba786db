"""The archive workflow: uploads, sequences and the operator's pattern versions.

Invariants kept here (the storage module keeps the rest):

* An upload is parsed, extracted once, and stored with its extraction
  (:class:`ExtractionDocument`).  The stored extraction is authoritative:
  pattern versions refer to its track ids, so loading a sequence reads it
  back (:func:`loaded`) instead of running extraction again, and a change to
  extraction can never re-number the tracks of archived sequences.
* Uploads stored before extraction documents were complete (no
  ``version``) are extracted again on load, and used only when the new
  extraction numbers every source exactly as the stored one did; otherwise
  the sequence is refused with a message (:class:`Conflict`).
* A pattern version is stored only after its definition was built into a
  pattern successfully.
* A spot-list upload of a spacecraft whose camera (same sensor size) has a
  hot-pixel map (built from uploads of its frames, :mod:`app.frames.hotpixels`)
  is extracted with the sources on the map's hot pixels given as known hot
  pixels (:func:`hot_pixel_sources`): they keep their place in the file's
  numbering but get the ``hot_pixel`` verdict, so they are never tracks or
  pattern points.  The map's version is recorded in the stored extraction
  (``hot_pixel_map``); a map made later never changes a stored sequence.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from app.camera import CAMERAS, Camera
from app.extraction import Pattern, PatternError, build_pattern, describe_track_ids, extract, unknown_tracks
from app.frames.hotpixels import HotPixelMap, near_hot_pixel
from app.storage import PatternVersion, SequenceRow, content_sha256
from app.telemetry import Sequence, parse_telemetry
from app.timefmt import utc_text
from app.workflow.compute import BULK, INTERACTIVE
from app.workflow.context import AppContext, LoadedSequence
from app.workflow.documents import (AttitudeDocument, ExtractionDocument, PatternDefinition, PatternDocument, PatternPoint,
                                    SearchDocument, SequenceDetail, SequencePage, SequenceSummary, UploadDocument)
from app.workflow.errors import Conflict, Invalid, NotFound
from app.workflow.text import require_audit_text


def automatic_definition() -> PatternDefinition:
    """Every track, nothing picked by hand: the pattern extraction proposes."""
    return PatternDefinition()


def clean_filename(name: str | None) -> str | None:
    """A client's file name reduced to a label: last path part, printable, at most 200 characters.

    The server never opens it; it only names the upload in messages and
    supplies a missing ``sequence_id`` (its stem).
    """
    if not name:
        return None
    base = re.split(r"[\\/]", name)[-1]
    base = "".join(ch for ch in base if ch.isprintable()).strip()[:200]
    return base or None


# ---------------------------------------------------------------------------
# Loading stored sequences
# ---------------------------------------------------------------------------

def require_sequence(ctx: AppContext, seq_id: int) -> SequenceRow:
    row = ctx.storage.get_sequence(seq_id)
    if row is None:
        raise NotFound(f"no sequence with id {seq_id}")
    return row


def loaded(ctx: AppContext, row: SequenceRow) -> LoadedSequence:
    """The stored upload parsed again, with its stored extraction (cached by id: uploads never change)."""
    item = ctx.cache.get(row.id)
    if item is None:
        sequence = stored_telemetry(row)
        item = LoadedSequence(sequence, stored_extraction(row, sequence))
        ctx.cache.put(row.id, item)
    return item


def stored_telemetry(row: SequenceRow) -> Sequence:
    """The stored upload's telemetry parsed again (``row.raw_text`` must be read)."""
    # Stored text passed validation once; the size limit and the camera's physical bounds may
    # have tightened since, so neither applies here: what was accepted stays readable.
    # A file without a camera block gets the camera it was given at upload (the default then, or
    # the spacecraft's calibration then), whatever the defaults and calibrations are now.
    return parse_telemetry(row.raw_text, filename=row.filename, default_camera=Camera(**row.camera) if row.camera else None,
                           max_bytes=len(row.raw_text.encode("utf-8")), physical_bounds=False)


def stored_extraction(row: SequenceRow, sequence: Sequence):
    """The extraction stored with ``row`` (see the module's invariants)."""
    document = ExtractionDocument.model_validate(row.extraction)
    if document.complete:
        return document.to_extraction(sequence)
    again = extract(sequence)
    if ExtractionDocument.of(again).sources != document.sources:
        raise Conflict(f"sequence {row.id} was extracted by an older version whose track numbers this "
                       "version does not reproduce; its pattern versions cannot be applied safely. "
                       "Re-upload the telemetry under a new sequence_id to process it again.")
    return again


# ---------------------------------------------------------------------------
# Uploads
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class ParsedUpload:
    """A valid upload: the telemetry and the text as sent."""

    sequence: Sequence
    raw_text: str
    filename: str | None
    #: The spacecraft's calibration version whose camera the file was given (it had no camera block).
    camera_calibration: int | None = None
    #: The version of the camera's hot-pixel map applied (None: no map for this spacecraft and sensor size)...
    hot_pixel_map: int | None = None
    #: ...and per snapshot, a flag per source (file order) on one of its hot pixels (see hot_pixel_sources).
    known_hot: tuple[np.ndarray, ...] | None = None


def parse_upload(ctx: AppContext, data: bytes, filename: str | None) -> ParsedUpload:
    """Validate an upload; raises :class:`app.telemetry.TelemetryError` (located problems) when invalid.

    A file without a camera block is given its spacecraft's current camera
    calibration when there is one (else the configured default camera).
    """
    filename = clean_filename(filename)
    sequence, defaulted = telemetry_job(data, filename, ctx.settings.default_camera, ctx.settings.max_upload_bytes)
    return parsed_upload(ctx, data, filename, sequence, defaulted)


#: Uploads larger than this are parsed on the compute pool's bulk lane rather than in the server
#: (:func:`telemetry_job`): validating a file is Python work that holds the server's one interpreter
#: lock, ~50 ms for a worst-case file of 64 x 64 sources (200 kB), while a sample file of 16 snapshots
#: of 10 sources is 10 kB.  32 kB is about 500 sources of JSON, beyond :data:`LARGE_UPLOAD_SOURCES`, so
#: a file parsed there is also extracted there.
LARGE_UPLOAD_BYTES = 32 * 1024


def parse_lane(data: bytes) -> str | None:
    """Where an upload of ``data`` is parsed: :data:`BULK` for a large one, None in the server itself."""
    return BULK if len(data) > LARGE_UPLOAD_BYTES else None


def telemetry_job(data: bytes, filename: str | None, default_camera: str, max_bytes: int, *,
                  sky=None) -> tuple[Sequence, bool]:
    """An upload's telemetry and whether it was given the default camera ``default_camera`` (a name of
    :data:`app.camera.CAMERAS`) because the file has no camera block; a compute-pool job (it needs no
    catalogue), its answer completed by :func:`parsed_upload`.  Raises :class:`app.telemetry.TelemetryError`."""
    default = CAMERAS.get(default_camera)
    marker = None if default is None else dataclasses.replace(default)  # equal, but recognisable by identity
    sequence = parse_telemetry(data, filename=filename, default_camera=marker, max_bytes=max_bytes)
    return sequence, marker is not None and sequence.camera is marker


def parsed_upload(ctx: AppContext, data: bytes, filename: str | None, sequence: Sequence,
                  defaulted: bool) -> ParsedUpload:
    """The upload of ``data`` whose telemetry :func:`telemetry_job` read as ``sequence`` (``defaulted``: given
    the default camera), with its spacecraft's calibration and hot-pixel map from the archive."""
    calibration = None
    if defaulted:
        calibration = ctx.storage.current_calibration(sequence.spacecraft)
        if calibration is not None:
            sequence = dataclasses.replace(sequence, camera=Camera(**calibration.camera))
    hot_pixel_map, known_hot = hot_pixel_sources(ctx, sequence)
    # parse_telemetry accepted the bytes as UTF-8; keep the text as sent.
    return ParsedUpload(sequence=sequence, raw_text=bytes(data).decode("utf-8"), filename=filename,
                        camera_calibration=None if calibration is None else calibration.version,
                        hot_pixel_map=hot_pixel_map, known_hot=known_hot)


def hot_pixel_sources(ctx: AppContext, sequence: Sequence) -> tuple[int | None, tuple[np.ndarray, ...] | None]:
    """``(version, flags)``: the current hot-pixel map of the sequence's camera (its spacecraft and sensor
    size) and, per snapshot, which sources lie on one of its hot pixels (within
    :data:`app.frames.hotpixels.SPOT_RADIUS_PX`); ``(None, None)`` when there is no such map."""
    camera = sequence.camera
    row = ctx.storage.current_hot_pixel_map(sequence.spacecraft, f"{camera.width}x{camera.height}")
    if row is None:
        return None, None
    hot = HotPixelMap.from_json(row.map, version=row.version).hot
    return row.version, tuple(near_hot_pixel(snapshot.xy, hot) for snapshot in sequence.snapshots)


def stored_upload(ctx: AppContext, upload: ParsedUpload) -> UploadDocument | None:
    """The document of the stored sequence with the same content, if there is one."""
    row = ctx.storage.find_sequence(content_sha256(upload.raw_text))
    return None if row is None else upload_document(ctx, row, created=False)


def extraction_job(sequence: Sequence, known_hot=None, *, sky=None):
    """Extraction as a compute-pool job (it needs no catalogue); ``known_hot``: an upload's
    :attr:`ParsedUpload.known_hot` (else :func:`store_upload` extracts again with it)."""
    return extract(sequence) if known_hot is None else extract(sequence, known_hot=known_hot)


def upload_extraction(upload: ParsedUpload, extraction):
    """The extraction to store for ``upload``: ``extraction`` when it was made with the upload's known hot
    pixels (or neither has any), else the upload extracted again with them."""
    wanted = upload.known_hot if upload.known_hot is not None and any(f.any() for f in upload.known_hot) else None
    given = extraction.known_hot
    if given is not None and not any(f.any() for f in given):
        given = None
    if wanted is None and given is None:
        return extraction
    if wanted is not None and given is not None and len(wanted) == len(given) \
            and all(np.array_equal(a, b) for a, b in zip(wanted, given)):
        return extraction
    return extraction_job(upload.sequence, wanted)


#: Uploads with more sources than this (16 snapshots of 16) are extracted on the compute pool's bulk
#: lane: extraction's work is capped per snapshot link (app.extraction.motion), but the cap is
#: reached only by files far denser than a star sensor's ~10 sources per snapshot, which then take
#: 0.1-0.4 s, too long to share the workers that answer searches in tens of milliseconds.
LARGE_UPLOAD_SOURCES = 256


def extraction_lane(sequence: Sequence) -> str:
    """The compute-pool lane that extracts ``sequence`` (see :data:`LARGE_UPLOAD_SOURCES`)."""
    sources = sum(snapshot.n_sources for snapshot in sequence.snapshots)
    return BULK if sources > LARGE_UPLOAD_SOURCES else INTERACTIVE


def store_upload(ctx: AppContext, upload: ParsedUpload, extraction) -> UploadDocument:
    """Store a parsed and extracted upload (``created`` False: the same content was stored meanwhile).

    An extraction made without the upload's known hot pixels is made again with them (see
    :func:`upload_extraction`): callers that pass ``upload.known_hot`` to :func:`extraction_job`
    save that second run.
    """
    sequence = upload.sequence
    extraction = upload_extraction(upload, extraction)
    row, created = ctx.storage.add_sequence(
        raw_text=upload.raw_text, filename=upload.filename, sequence_id=sequence.sequence_id,
        spacecraft=sequence.spacecraft, camera=sequence.camera.to_dict(),
        # An assumed time (frames that carried none) is no time to list or sort a pass by.
        first_time=sequence.snapshots[0].time if sequence.snapshots and not sequence.time_assumed else None,
        n_snapshots=len(sequence.snapshots), camera_calibration=upload.camera_calibration,
        extraction=ExtractionDocument.of(extraction, hot_pixel_map=upload.hot_pixel_map).model_dump(mode="json"))
    if created:
        ctx.cache.put(row.id, LoadedSequence(sequence, extraction))
        ctx.storage.add_pattern_version(row.id, automatic_definition().model_dump(), kind="automatic")
    return upload_document(ctx, row, created)


def upload_document(ctx: AppContext, row: SequenceRow, created: bool) -> UploadDocument:
    """The answer to an upload stored as ``row``, naming the other uploads of its spacecraft and sequence id."""
    item = loaded(ctx, row)
    same = ctx.storage.same_sequence_uploads(row.spacecraft, row.sequence_id, other_than=row.id)
    return UploadDocument(id=row.id, created=created, sequence=SequenceSummary.of(row),
                          extraction=ExtractionDocument.model_validate(row.extraction),
                          pattern=pattern_document(item, ctx.storage.current_pattern(row.id)),
                          same_sequence_id_as=[i for i, _ in same], note=same_sequence_note(same))


def same_sequence_note(uploads: list[tuple[int, str | None]]) -> str | None:
    """The operator's sentence about other stored uploads (id, file name) of the same spacecraft and sequence
    id (None: none).

    Uploads are deduplicated by their exact bytes only: telemetry read the same but sent with other line
    endings or a byte-order mark is a second sequence, and the work queue shows both.
    """
    if not uploads:
        return None
    listed = ", ".join(f"#{i}" + (f' "{name}"' if name else "") for i, name in uploads)
    others, have, its = ("another stored upload", "has", "its") if len(uploads) == 1 else \
        ("other stored uploads", "have", "their")
    return (f"{others} ({listed}) {have} the same spacecraft and sequence id; {its} telemetry differs in bytes "
            "(line endings, byte-order mark or content)")


# ---------------------------------------------------------------------------
# Sequences
# ---------------------------------------------------------------------------

def sequence_detail(ctx: AppContext, seq_id: int) -> SequenceDetail:
    row = require_sequence(ctx, seq_id)
    item = loaded(ctx, row)
    search = ctx.storage.latest_search(seq_id)
    confirmation = ctx.storage.current_confirmation(seq_id)
    return SequenceDetail(**SequenceSummary.of(row).model_dump(), telemetry=item.sequence.to_json_dict(),
                          extraction=ExtractionDocument.model_validate(row.extraction),
                          pattern=pattern_document(item, ctx.storage.current_pattern(seq_id)),
                          search=None if search is None else SearchDocument.of(search),
                          confirmation=None if confirmation is None else AttitudeDocument.of(confirmation, row))


def list_sequences(ctx: AppContext, offset: int, limit: int, spacecraft: str | None,
                   status: str | None) -> SequencePage:
    rows, total = ctx.storage.list_sequences(offset, limit, spacecraft=spacecraft, status=status)
    return SequencePage(items=[SequenceSummary.of(r) for r in rows], total=total, offset=offset, limit=limit)


# ---------------------------------------------------------------------------
# Patterns
# ---------------------------------------------------------------------------

def definition_of(version: PatternVersion | None) -> PatternDefinition:
    return automatic_definition() if version is None else PatternDefinition.model_validate(version.pattern)


def pattern_from_definition(item: LoadedSequence, definition: PatternDefinition) -> Pattern:
    """The pattern an operator's definition describes; ValueError with the reason if it cannot be built."""
    manual = [(p.snapshot, p.x, p.y) for p in definition.manual_points]
    return build_pattern(item.sequence, item.extraction, exclude_tracks=definition.exclude_tracks,
                         include_tracks=definition.include_tracks, manual_points=manual)


def pattern_document(item: LoadedSequence, version: PatternVersion | None) -> PatternDocument:
    definition = definition_of(version)
    try:
        points = PatternPoint.rows(pattern_from_definition(item, definition))
    except ValueError:  # stored definitions were checked when stored; be safe anyway
        points = PatternPoint.rows(item.extraction.pattern)
    return PatternDocument(version=version.version if version else None,
                           kind=version.kind if version else "automatic",
                           operator=version.operator if version else None,
                           created_at=utc_text(version.created_at) if version else None,
                           definition=definition, points=points, reference_snapshot=int(item.extraction.reference))


def current_pattern_version(ctx: AppContext, seq_id: int) -> int | None:
    version = ctx.storage.current_pattern(seq_id)
    return None if version is None else version.version


def current_pattern(ctx: AppContext, seq_id: int) -> PatternDocument:
    row = require_sequence(ctx, seq_id)
    return pattern_document(loaded(ctx, row), ctx.storage.current_pattern(seq_id))


def set_pattern(ctx: AppContext, seq_id: int, definition: PatternDefinition, operator: str | None,
                locate: Callable[[str, int], str] | None = None) -> PatternDocument:
    """Store the operator's pattern as a new version after checking it can be built.

    Every track it names, excluded or included, must exist: an unknown id is
    a mistake either way, and is refused at its location.  ``locate(field,
    key)`` gives that location for a track id or a manual point's position
    (default: ``body.<field>``).
    """
    where = locate or (lambda field, key: f"body.{field}")
    require_audit_text(operator=operator)
    row = require_sequence(ctx, seq_id)
    item = loaded(ctx, row)
    known = describe_track_ids(t.id for t in item.extraction.tracks)
    problems = [{"location": where(field, track), "message": f"track {track} does not exist ({known})"}
                for field, ids in (("exclude_tracks", definition.exclude_tracks),
                                   ("include_tracks", definition.include_tracks or ()))
                for track in unknown_tracks(item.extraction, ids)]
    if problems:
        raise Invalid("the pattern names tracks this sequence does not have: "
                      + "; ".join(f"{p['location']}: {p['message']}" for p in problems[:5]), problems=problems)
    try:
        pattern_from_definition(item, definition)
    except PatternError as exc:
        raise Invalid(f"the pattern cannot be built: {exc}", location=where(exc.field, exc.key),
                      message=str(exc)) from None
    except ValueError as exc:
        raise Invalid(f"the pattern cannot be built: {exc}", message=str(exc)) from None
    version = ctx.storage.add_pattern_version(seq_id, definition.model_dump(), kind="edit", operator=operator)
    return pattern_document(item, version)


def reset_pattern(ctx: AppContext, seq_id: int, operator: str | None) -> PatternDocument:
    require_audit_text(operator=operator)
    row = require_sequence(ctx, seq_id)
    version = ctx.storage.add_pattern_version(seq_id, automatic_definition().model_dump(), kind="reset",
                                              operator=operator)
    return pattern_document(loaded(ctx, row), version)
