"""The pipeline on telemetry files, without an archive: what ``python -m app solve`` and ``extract`` print.

Each file gives one document (:class:`SolveDocument`, :class:`ExtractDocument`),
the same candidate and extraction documents the API returns; a file that
does not parse gives a document with status ``invalid`` and its located
error, and the batch goes on.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

from app.attitude import rotation_angle_between
from app.extraction import extract
from app.filenames import (FOLDER_SIDECAR, SPOT_LIST_SUFFIXES, TRUTH_SUFFIX, image_sidecar, image_sidecars,
                           passes_of_folder, special_file)
from app.frames.times import time_notes
from app.identification import NO_MATCH, Prior, SearchOptions, Sky, solve_sequence, source_stars
from app.telemetry import Sequence
from app.telemetry.errors import TelemetryError
from app.telemetry.formats import load_telemetry_file
from app.workflow.documents import (CandidateDocument, ExtractDocument, ExtractionDocument,
                                    FocalLengthContradictionDocument, SolveDocument)

#: Two first candidates closer than this (rotation angle) are the same attitude.
AGREE_DEG = 0.1

#: A folder with nothing to read.
EMPTY_FOLDER = "the folder holds no telemetry (.json, .csv) and no frames (FITS, PNG, JPEG, TIFF)"


def input_files(paths: list[str]) -> tuple[list[str], list[str]]:
    """``(inputs, truth files left out)`` of the command line's files and folders, in order.

    A file is an input as given; a folder holding images gives its passes of frames
    (:func:`app.filenames.passes_of_folder`: the folder as one pass, read with its ``frames.json``, or each
    photograph alone), then its spot-list files in name order; ``*.truth.json`` files are left out (a shell
    glob such as ``sample_telemetry/*.json`` takes them in), and so are the sidecars read with the frames.  A
    folder with nothing to read stays an input, so that it is reported (:data:`EMPTY_FOLDER`).
    """
    inputs, truth = [], []
    for raw in paths:
        folder = Path(raw)
        if not folder.is_dir():
            (truth if raw.lower().endswith(TRUTH_SUFFIX) else inputs).append(raw)
            continue
        try:
            entries = sorted(p for p in folder.iterdir() if p.is_file())
        except OSError:
            inputs.append(raw)  # reported when read
            continue
        passes, sidecars = passes_of_folder(entries), image_sidecars(entries)
        spot_lists = [p for p in entries if p.suffix.lower() in SPOT_LIST_SUFFIXES
                      and not (passes and p.name == FOLDER_SIDECAR) and p not in sidecars]
        truth += [str(p) for p in spot_lists if p.name.lower().endswith(TRUTH_SUFFIX)]
        frames = [raw] if len(passes) == 1 else [str(image) for (image,) in passes]  # the folder, or each photograph
        found = frames + [str(p) for p in spot_lists if not p.name.lower().endswith(TRUTH_SUFFIX)]
        inputs += found or [raw]
    return inputs, truth


def telemetry_files(paths: list[str], *, fov_deg: float | None = None, time: datetime | None = None
                    ) -> Iterator[tuple[str, Sequence | None, TelemetryError | None]]:
    """``(path, sequence, None)`` for each input that parses, ``(path, None, error)`` for each that does not.

    ``paths`` are inputs as :func:`input_files` gives them.  An image file or a folder of frames is
    one pass (see :func:`_load`); ``fov_deg`` (the horizontal field of view in degrees, known to
    +-5 %) gives its optics, over a sidecar's and the FITS header's; ``time`` the time of a pass of one
    frame, over the sidecar's and the file's own.  A spot-list file carries its own camera and times, so
    with ``fov_deg`` or ``time`` it is refused (:data:`FOV_SPOT_LIST`, :data:`TIME_SPOT_LIST`).
    """
    for path in paths:
        try:
            yield path, _load(path, fov_deg, time), None
        except TelemetryError as exc:
            yield path, None, exc


# --- image files and folders of frames ------------------------------------------------

#: Why ``fov_deg`` is refused for a spot-list file: its camera block (or the default camera, which the
#: operator can see and change in the file) is the camera, and a field of view given for a batch of
#: images silently replacing it would change the optics of every spot list in the batch.
FOV_SPOT_LIST = ("applies to image files and folders of frames only; a spot list carries its own camera "
                 "(its camera block, else the default camera): leave --fov-deg out for it, or give it a camera block")


#: Why ``time`` is refused for a spot-list file: every snapshot has its own time there.
TIME_SPOT_LIST = ("applies to image files and folders of frames only; a spot list carries its own times: leave "
                  "--time out for it")


def _load(path: str, fov_deg: float | None, time: datetime | None = None) -> Sequence:
    """Spot-list telemetry, or (an image file, a folder of images) the pass of frames it holds."""
    from app.workflow.frames import frames_sequence_from_path, is_frames_path

    kind = special_file(path)
    if kind is not None:  # before anything opens it (is_frames_path reads its first bytes)
        raise TelemetryError.at("file", f"not a regular file ({kind})", filename=path)
    if not is_frames_path(path):
        if Path(path).is_dir():
            raise TelemetryError.at("folder", EMPTY_FOLDER, filename=path)
        if fov_deg is not None:
            raise TelemetryError.at("--fov-deg", FOV_SPOT_LIST, filename=path)
        if time is not None:
            raise TelemetryError.at("--time", TIME_SPOT_LIST, filename=path)
        return load_telemetry_file(path)
    try:
        return frames_sequence_from_path(path, fov_deg=fov_deg, caller_time=time)
    except TelemetryError as exc:
        if exc.filename is not None:
            raise
        raise type(exc)(exc.problems, filename=path, truncated=exc.truncated) from None


def input_sha256(path: str) -> str | None:
    """SHA-256 of everything an input may be read from, to tell a changed input from one answered before:
    a file's bytes (an image's with the sidecars it may take, ``<stem>.frames.json`` and its folder's
    ``frames.json``); a folder's files, each by name and bytes, in name order.  Taking in a file the input
    may not need only makes a re-run redo it; None when it cannot be read, or is a device, FIFO or socket
    (:func:`special_file`: hashing it would never end); it is reported when processed.
    """
    from app.workflow.frames import is_frames_path

    if special_file(path) is not None:
        return None
    source = Path(path)
    try:
        if source.is_dir():
            members = sorted(p for p in source.iterdir() if p.is_file())
        else:
            members = [source]
            if is_frames_path(path):
                members += [p for p in (image_sidecar(source), source.with_name(FOLDER_SIDECAR)) if p.is_file()]
        digest = hashlib.sha256()
        for member in members:
            digest.update(member.name.encode() + b"\0")
            with member.open("rb") as stream:
                for chunk in iter(lambda: stream.read(1 << 20), b""):
                    digest.update(chunk)
        return digest.hexdigest()
    except OSError:
        return None


def invalid_solve_document(path: str, message: str, digest: str | None = None) -> SolveDocument:
    """The ``solve --json`` line of an input that cannot be identified (``digest``: its
    :func:`input_sha256`, taken here when not given)."""
    return SolveDocument(file=path, sequence_id=None, status="invalid", error=message,
                         input_sha256=digest if digest is not None else input_sha256(path))


def extract_document(path: str, sequence: Sequence) -> ExtractDocument:
    extraction = ExtractionDocument.of(extract(sequence))
    doc = ExtractDocument(file=path, sequence_id=sequence.sequence_id, status="ok",
                          **extraction.model_dump(include=set(ExtractDocument.model_fields) - {"file"}))
    doc.notes = list(doc.notes or []) + time_notes(sequence)
    return doc


def solve_document(path: str, sequence: Sequence, sky: Sky, *, options: SearchOptions,
                   method: str = "bright_pair", prior: Prior | None = None, compare_tf: bool = False,
                   digest: str | None = None) -> SolveDocument:
    """Identify one file's sequence; with ``compare_tf`` also by triangle features, and say whether they agree.

    ``source_stars`` gives, per snapshot and source in input order, the HIP
    number the first candidate's attitude assigns it (null: no star there,
    or none certainly: a note counts those), or is null when that candidate
    is not credible.  ``digest``: the input's
    :func:`input_sha256` (taken here from ``path`` when not given).
    """
    solved = solve_sequence(sequence, sky, options=options, method=method, prior=prior)
    s = solved.solution
    names = source_stars(solved, sky)
    doc = SolveDocument(
        file=path, sequence_id=sequence.sequence_id, status=s.status,
        input_sha256=digest if digest is not None else input_sha256(path),
        reference_snapshot=int(solved.extraction.reference),
        sources=[[int(t) if t >= 0 else None for t in per] for per in solved.extraction.track_of_source],
        source_stars=names.names if names else None,
        candidates=[CandidateDocument.of(c, solved.sequence_fits.get(c.rank)) for c in s.candidates],
        elapsed_ms=round(s.elapsed_s * 1000, 2),
        notes=(list(solved.extraction.notes) + list(s.notes) + time_notes(sequence)
               + ([names.note] if names and names.note else [])),
        focal_length_contradiction=FocalLengthContradictionDocument.of(s.focal_length_contradiction))
    if compare_tf and prior is None:
        tf = solve_sequence(sequence, sky, options=options, extraction=solved.extraction, pattern=solved.pattern,
                            method="tf").solution
        doc.tf_status = tf.status
        doc.tf_candidates = [CandidateDocument.of(c) for c in tf.candidates]
        doc.methods_agree = methods_agree(s, tf)
    return doc


def methods_agree(a, b, tolerance_deg: float = AGREE_DEG) -> bool:
    """True when both solutions find no match, or both find one and their first candidates are one attitude.

    Two answers of "no match" agree whatever chance fits either kept as
    candidates (the bright-pair method keeps its best few for the operator).
    """
    if NO_MATCH in (a.status, b.status):
        return a.status == b.status
    angle = rotation_angle_between(a.candidates[0].rotation_matrix, b.candidates[0].rotation_matrix)
    return math.degrees(angle) <= tolerance_deg
