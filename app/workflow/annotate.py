"""Annotated frames: a solved frame with its stars named, the constellation figures, the
unmatched sources and an RA/Dec grid (drawn by :mod:`app.frames.annotate`), assembled here from a solve.

* ``python -m app solve IMAGE --annotate OUT.png`` (:func:`annotate_solve`): the frame read again from
  its file at full size, stretched to 8 bits as the stored previews are
  (:func:`app.workflow.frames.stretch_to_8bit`), with the first candidate's attitude (a spot list,
  which has no image, is drawn on black);
* ``GET /api/sequences/{id}/frames/{snapshot}/annotated.png?rank=N`` (:func:`annotated_frame_png`):
  the stored preview (the images are not kept), enlarged back towards the frame's size, with the
  latest search's candidate of that rank, its attitude carried from the reference snapshot to the
  one shown by the extraction's motion (``R_i = M_i^T R_ref``, where ``v_ref = M_i v_i``), else by
  the fitted body rate.

Stars and figure vertices are drawn at their apparent places at the snapshot's time (proper motion
and aberration, :meth:`app.catalogue.Catalogue.apparent_vectors`), through the candidate's camera
(the declared one, or the optics fitted with the candidate where it adopted them).
"""

from __future__ import annotations

import csv
import functools
import io
from datetime import datetime
from importlib import resources
from pathlib import Path

import numpy as np

from app.attitude.rotations import propagate
from app.camera import Camera
from app.catalogue import Catalogue, load_catalogue, radec_to_vectors
from app.frames import FrameLimits, read_frames
from app.frames.annotate import Annotation, Figure, SkyLabel, annotate
from app.telemetry import Sequence
from app.workflow import archive
from app.workflow.context import AppContext
from app.workflow.documents import CandidateDocument, SolveDocument
from app.workflow.errors import NotFound
from app.workflow.frames import encode_png, frame_preview_row, is_frames_path, stretch_to_8bit
from app.workflow.search import candidate_of, latest_search

#: The constellation stick figures (app/data; source and licence in its header).
FIGURES_FILE = "constellation_lines.csv"

#: A figure vertex: a Hipparcos number, or (RA, Dec) J2000 degrees for a star Hipparcos-2 lacks.
Vertex = int | tuple[float, float]


@functools.lru_cache(maxsize=1)
def figure_table() -> tuple[tuple[str, str, tuple[tuple[Vertex, ...], ...]], ...]:
    """``(abbreviation, name, polylines)`` of every constellation, in the file's order."""
    text = resources.files("app.data").joinpath(FIGURES_FILE).read_text(encoding="utf-8")
    rows = csv.DictReader(line for line in text.splitlines() if not line.startswith("#"))
    figures: dict[str, tuple[str, list]] = {}
    for row in rows:
        vertices = tuple(tuple(float(v) for v in token.split("/")) if "/" in token else int(token)
                         for token in row["vertices"].split())
        figures.setdefault(row["constellation"], (row["name"], []))[1].append(vertices)
    return tuple((abbrev, name, tuple(lines)) for abbrev, (name, lines) in figures.items())


def constellation_figures(catalogue: Catalogue, t: datetime, velocity_km_s=None) -> tuple[Figure, ...]:
    """Every stick figure with its stars at their apparent places at ``t``.  A vertex whose star is not in
    ``catalogue`` breaks its polyline there; one given by RA/Dec is its J2000 direction."""
    table = figure_table()
    row_of_hip = catalogue.index_of_hip()
    hips = sorted({v for _, _, lines in table for line in lines for v in line
                   if isinstance(v, int) and v in row_of_hip})
    rows = np.array([row_of_hip[h] for h in hips], dtype=int)
    vectors = dict(zip(hips, catalogue.subset(rows).apparent_vectors(t, velocity_km_s)))
    figures = []
    for abbrev, name, lines in table:
        polylines = []
        for line in lines:
            run: list[np.ndarray] = []
            for vertex in line + (None,):
                if isinstance(vertex, tuple):
                    v = radec_to_vectors(np.radians([vertex[0]]), np.radians([vertex[1]]))[0]
                else:
                    v = vectors.get(vertex)
                if v is None:
                    if len(run) >= 2:
                        polylines.append(np.array(run))
                    run = []
                else:
                    run.append(v)
        figures.append(Figure(abbreviation=abbrev, name=name, polylines=tuple(polylines)))
    return tuple(figures)


def frame_annotation(*, camera: Camera, status: str, candidate: CandidateDocument | None,
                     rotation: np.ndarray | None, t: datetime, velocity_km_s, source_xy: np.ndarray,
                     source_tracks: list[int | None]) -> Annotation:
    """What to draw over one snapshot: the candidate's stars and planets named, the snapshot's sources
    whose track no star or planet of the candidate explains as unmatched, the figures."""
    if candidate is None or rotation is None:
        return Annotation(camera=camera, status=status, unmatched_xy=np.asarray(source_xy, float).reshape(-1, 2))
    from app.planets import planet_vectors

    catalogue = load_catalogue()
    row_of_hip = catalogue.index_of_hip()
    matches = [m for m in candidate.matches if m.hip in row_of_hip]
    star_vectors = catalogue.subset(np.array([row_of_hip[m.hip] for m in matches], dtype=int)) \
        .apparent_vectors(t, velocity_km_s) if matches else np.zeros((0, 3))
    labels = [SkyLabel(text=m.name or f"HIP {m.hip}", vector=v) for m, v in zip(matches, star_vectors)]
    if candidate.planets:
        planets = planet_vectors(t)
        labels += [SkyLabel(text=p.name, vector=planets[p.name], planet=True)
                   for p in candidate.planets if p.name in planets]
    explained = {m.track for m in candidate.matches} | {p.track for p in candidate.planets}
    explained.discard(None)
    unmatched = [j for j, track in enumerate(source_tracks) if track is None or track not in explained]
    return Annotation(camera=candidate.matched_camera(camera), status=status, rotation=rotation,
                      stars=tuple(labels), unmatched_xy=np.asarray(source_xy, float).reshape(-1, 2)[unmatched],
                      figures=constellation_figures(catalogue, t, velocity_km_s))


# ---------------------------------------------------------------------------
# Command line: solve IMAGE --annotate OUT.png
# ---------------------------------------------------------------------------

def frame_pixels(path: str, sequence: Sequence, snapshot: int) -> tuple[np.ndarray, int] | None:
    """The pixels of a snapshot of the pass read from ``path`` (an image file or a folder of frames),
    read again from its file, and the side of the blocks they are the means of (1: the frame's own;
    more for a frame over the detection budget, :class:`app.frames.Frame`); None for a spot list."""
    if not is_frames_path(path):
        return None
    report = sequence.extra["frames"]["frames"][snapshot]
    source = Path(path)
    file = source / report["file"] if source.is_dir() else source
    for frame in read_frames(file.read_bytes(), report["file"], FrameLimits()):
        if frame.part == report.get("part"):
            return frame.pixels, frame.binned
    raise ValueError(f"{file}: no frame {report.get('part')} in the file any more")


def annotate_solve(path: str, sequence: Sequence, doc: SolveDocument) -> bytes:
    """The PNG of a solved input's reference snapshot, the frame's own size, with the first candidate
    (none for ``no_match``: its candidates are chance fits kept for an operator to look at, and a
    grid drawn from one would tell a reader of the picture alone where the camera did not point)."""
    snapshot = doc.reference_snapshot if doc.reference_snapshot is not None else 0
    camera = sequence.camera
    read = frame_pixels(path, sequence, snapshot)
    grey = np.zeros((camera.height, camera.width), np.uint8) if read is None else stretch_to_8bit(read[0])
    scale = 1 if read is None else read[1]
    candidate = doc.candidates[0] if doc.candidates and doc.status != "no_match" else None
    status = doc.status + (f" · candidate 1 of {len(doc.candidates)}" if candidate else "")
    shot = sequence.snapshots[snapshot]
    annotation = frame_annotation(camera=camera, status=status, candidate=candidate,
                                  rotation=None if candidate is None else candidate.rotation, t=shot.time,
                                  velocity_km_s=sequence.observer, source_xy=shot.xy,
                                  source_tracks=doc.sources[snapshot] if doc.sources else [])
    return encode_png(annotate(grey, scale, annotation))


# ---------------------------------------------------------------------------
# Console: GET /api/sequences/{id}/frames/{snapshot}/annotated.png?rank=N
# ---------------------------------------------------------------------------

def attitude_at(candidate: CandidateDocument, motion: np.ndarray, sequence: Sequence, reference: int,
                snapshot: int) -> np.ndarray | None:
    """The candidate's attitude (ICRS -> camera) at ``snapshot``: carried by the extraction's motion
    from the reference snapshot, else by the fitted body rate; None when neither is known."""
    R = candidate.rotation
    if snapshot == reference:
        return R
    M = np.asarray(motion[snapshot], dtype=float)
    if np.all(np.isfinite(M)):
        return M.T @ R
    if candidate.sequence_fit is not None:
        dt = (sequence.snapshots[snapshot].time - sequence.snapshots[reference].time).total_seconds()
        return propagate(R, candidate.sequence_fit.rate_rad_s, dt)
    return None


def annotated_frame_png(ctx: AppContext, seq_id: int, snapshot: int, rank: int) -> bytes:
    """The stored preview of a snapshot annotated with the latest search's candidate of ``rank``;
    NotFound when the sequence, its frame image of that snapshot, its search or that rank is missing."""
    from PIL import Image

    preview = frame_preview_row(ctx, seq_id, snapshot)
    row = archive.require_sequence(ctx, seq_id)
    search, result = latest_search(ctx, seq_id)
    candidate = candidate_of(search, result, rank)
    item = archive.loaded(ctx, row)
    sequence, extraction = item.sequence, item.extraction
    rotation = attitude_at(candidate, extraction.motion, sequence, result.reference_snapshot, snapshot)
    if rotation is None:
        raise NotFound(f"the attitude at snapshot {snapshot} of sequence {seq_id} is not known (its stars were "
                       f"not tracked to the reference snapshot {result.reference_snapshot}, and no body rate was "
                       "fitted): annotate the reference snapshot")
    status = f"{result.status} · candidate {rank} of {len(result.candidates)}"
    if row.status in ("confirmed", "rejected"):
        status += f" · sequence {row.status}"
    grey = np.asarray(Image.open(io.BytesIO(preview.png)).convert("L"))
    shot = sequence.snapshots[snapshot]
    annotation = frame_annotation(camera=sequence.camera, status=status, candidate=candidate, rotation=rotation,
                                  t=shot.time, velocity_km_s=sequence.observer, source_xy=shot.xy,
                                  source_tracks=[None if t < 0 else int(t) for t in extraction.track_of_source[snapshot]])
    return encode_png(annotate(grey, preview.scale, annotation))
