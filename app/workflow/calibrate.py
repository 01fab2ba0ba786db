"""Calibration from the archive (or from files): one camera fitted over many identified sequences.

A ground station holds thousands of frames from the same camera, each with
stars identified; together they fix the optics far better than any single
frame (:func:`app.camera_fit.calibrate`).  The workflow:

1. choose the sequences: every sequence of the spacecraft with a current
   confirmation (its confirmed candidate), else whose latest search is
   ``identified`` (its first candidate), of the sensor size with the most of
   them (:func:`archive_sequences`); from files, every file that identifies;
2. turn each into observations (:func:`candidate_observations`): per
   snapshot, the pixels where the candidate's identified tracks were seen,
   the apparent places of their stars, and a starting attitude (the
   sequence fit's, propagated at its rate; else extraction's motion);
3. fit the camera, rejecting outliers (:func:`fit`);
4. associate every reported source again, through the fitted camera and
   attitudes, with the catalogue, and fit once more (:func:`reassociated`);
5. store the result as the spacecraft's next calibration version
   (append-only, with who, when and which sequences); later uploads of the
   spacecraft without a camera block are given that camera, and each search
   records which version it used.

Why step 4: the identified tracks are the ones identification kept, and its
final rejection (:data:`app.identification.verify.FINAL_REJECT_SIGMAS`)
judges them through the *declared* optics, which a calibration exists to
correct.  Near the edge of the field it drops the tracks whose noise points
away from where the declared optics put the star and keeps those whose noise
points towards it, so the kept sightings lean inwards: over 60 simulated
calibrations of 20 sequences each, the fitted k1 came out 0.7 sigma low and
the focal length 0.5 sigma long on average.  Re-associated through the
fitted camera, every source within a few pixels of a star takes part
whatever identification thought of it, and the fit's own outlier rejection,
in the fitted optics, decides.

Parameters fitted by default: focal length, principal point and k1.  ``k2``
on request only: over a 20 deg field it is nearly collinear with k1 and the
focal length, and fitting it quadruples k1's uncertainty
(:mod:`app.camera_fit`).
"""

from __future__ import annotations

import hashlib
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from app.camera import Camera
from app.camera_fit import Calibration, Observation, calibrate as fit_camera, parameter_names, residual_vectors
from app.extraction import Extraction
from app.identification.sightings import (MIN_SIGHTINGS, claimed_once, identified_sightings, observations,
                                          source_match_tolerance_rad, sources_field, stars_at)
from app.telemetry import Sequence
from app.workflow.archive import loaded, require_sequence
from app.workflow.context import AppContext
from app.workflow.documents import (CalibrationDocument, CandidateDocument, ResidualCell, ResidualMap,
                                    StoredCalibration)
from app.workflow.errors import Invalid, NotFound
from app.workflow.text import require_audit_text

#: What a calibration fits unless asked otherwise (see the module doc).
DEFAULT_PARAMETERS = ("focal_length_px", "cx", "cy", "k1")
#: Fewest sequences a calibration is made from.
MIN_SEQUENCES = 3
#: A calibration from the archive uses the spacecraft's newest sequences, at most this many: 200
#: already fix the focal length to ~0.002 % and k1 to ~0.5 % (app.camera_fit), and the bound keeps
#: the request to a few seconds.
MAX_SEQUENCES = 300


@dataclass(frozen=True, eq=False)
class IdentifiedSequence:
    """A sequence a calibration is made from: what was reported and tracked, and the observations of its
    identified candidate (:func:`candidate_observations`, made once)."""

    label: str  # how the calibration names it (archive id or file path)
    sequence: Sequence
    extraction: Extraction
    observations: list[Observation]

    @classmethod
    def of(cls, label: str, sequence, extraction, candidate: CandidateDocument, sky) -> IdentifiedSequence:
        return cls(label, sequence, extraction, candidate_observations(sequence, extraction, candidate, sky, label))

    @classmethod
    def from_solved(cls, label: str, solved, sky) -> IdentifiedSequence:
        """Of a solved sequence's best candidate (with its sequence fit)."""
        best = solved.solution.candidates[0]
        return cls.of(label, solved.sequence, solved.extraction,
                      CandidateDocument.of(best, solved.sequence_fits.get(best.rank)), sky)


def candidate_observations(sequence, extraction, candidate: CandidateDocument, sky, label: str) -> list[Observation]:
    """The observations (one per snapshot with 3 or more identified sightings) of a candidate document.

    Pixels are the raw sightings (:mod:`app.identification.sightings`: no
    camera model involved), so the calibration sees the optics as they are;
    each snapshot starts from the candidate's attitude propagated at its
    fitted rate (else carried by extraction's motion).
    """
    star_of_track = {m.track: m.hip for m in candidate.matches if m.track is not None}
    rate = candidate.sequence_fit.rate_rad_s if candidate.sequence_fit is not None else None
    return observations(identified_sightings(sequence, extraction, star_of_track, sky), extraction,
                        candidate.rotation, rate, label)


#: The residual map's grid over the sensor (columns, rows).
RESIDUAL_GRID = (8, 6)


def residual_map(observations: list[Observation], result: Calibration, camera: Camera) -> ResidualMap:
    """Mean residual vector (measured minus predicted, px) of the inlier stars in each cell of a grid over the
    sensor, with the declared camera (attitudes refitted for it) and with the fitted one: what the console
    draws to show what the calibration corrected."""
    nx, ny = RESIDUAL_GRID
    sums = np.zeros((ny, nx, 4))
    counts = np.zeros((ny, nx), dtype=int)
    for obs, before, after, inlier in zip(observations, result.rotations_before, result.rotations, result.inliers):
        if before is None or after is None or not np.any(inlier):
            continue
        xy = np.asarray(obs.xy)[inlier]
        kept = Observation(xy=xy, star_vectors=np.asarray(obs.star_vectors)[inlier], rotation=after,
                           sigma_px=obs.sigma_px)
        both = np.hstack([residual_vectors(kept, before, camera), residual_vectors(kept, after, result.camera)])
        col = np.clip(((xy[:, 0] + 0.5) * nx / camera.width).astype(int), 0, nx - 1)
        row = np.clip(((xy[:, 1] + 0.5) * ny / camera.height).astype(int), 0, ny - 1)
        np.add.at(sums, (row, col), both)
        np.add.at(counts, (row, col), 1)
    cells = []
    for r in range(ny):
        for c in range(nx):
            if counts[r, c]:
                mean = sums[r, c] / counts[r, c]
                cells.append(ResidualCell(x=(c + 0.5) * camera.width / nx - 0.5, y=(r + 0.5) * camera.height / ny - 0.5,
                                          n=int(counts[r, c]), dx_before=round(mean[0], 3), dy_before=round(mean[1], 3),
                                          dx_after=round(mean[2], 3), dy_after=round(mean[3], 3)))
    return ResidualMap(columns=nx, rows=ny, width=camera.width, height=camera.height, cells=cells)


def reassociated(identified: list[IdentifiedSequence], first: list[Observation], result: Calibration,
                 sky) -> list[Observation]:
    """Every reported source of each snapshot that took part in ``result``, associated with the catalogue
    through the fitted camera and that snapshot's fitted attitude (module doc, step 4).

    A source is a star's when it lies within the tolerance of
    :func:`app.identification.sightings.source_match_tolerance_rad` of it
    (2 px, or 5 sigma of the sighting noise) and no other source of the
    snapshot is that star's too; snapshots left with fewer than
    :data:`MIN_SIGHTINGS` such sources are left out.  The stars are the ones
    down to the camera's limiting magnitude plus the search's margin, at the
    sequence's reference time (as :func:`candidate_observations`).
    """
    at = {(o.sequence, o.snapshot): (o, rotation) for o, rotation in zip(first, result.rotations)
          if rotation is not None}  # the snapshots that took part, with their fitted attitudes
    out = []
    for item in identified:
        sequence, extraction = item.sequence, item.extraction
        taking_part = [at[item.label, position] for position in range(len(sequence.snapshots))
                       if (item.label, position) in at]
        if not taking_part:
            continue
        field = sources_field(sky, sequence, sequence.snapshots[extraction.reference].time, sequence.camera)
        # All the sequence's sources at once (one query, one pass through the optics), each with the
        # attitude of its snapshot.
        xy = [sequence.snapshots[o.snapshot].xy for o, _ in taking_part]
        owner = np.repeat(np.arange(len(xy)), [len(a) for a in xy])
        rotations = np.array([rotation for _, rotation in taking_part])
        all_xy = np.concatenate(xy)
        stars = stars_at(all_xy, result.camera, rotations[owner], field,
                         source_match_tolerance_rad(result.camera, extraction))
        kept = claimed_once(stars, owner)
        for k, (observation, rotation) in enumerate(taking_part):
            mine = kept & (owner == k)
            if mine.sum() >= MIN_SIGHTINGS:
                out.append(Observation(xy=all_xy[mine], star_vectors=field.vectors[stars[mine]], rotation=rotation,
                                       sigma_px=observation.sigma_px, sequence=observation.sequence,
                                       snapshot=observation.snapshot))
    return out


@dataclass(frozen=True, eq=False)
class Fitted:
    """What :func:`fit` made: the calibration, the observations of its final fit, and the first fit (the
    identified tracks alone, before the re-association: what ``bench --suite calibration`` compares)."""

    calibration: Calibration
    observations: list[Observation]
    first: Calibration


def fit(identified: list[IdentifiedSequence], camera: Camera, sky,
        parameters: Iterable[str] | None = None) -> Fitted:
    """The camera fitted over the identified sequences (module doc, steps 2-4; Invalid when they cannot
    fix it)."""
    names = parameter_names(parameters or DEFAULT_PARAMETERS)
    first = [o for item in identified for o in item.observations]
    n_sequences = len({o.sequence for o in first})
    if n_sequences < MIN_SEQUENCES:
        raise Invalid(f"a calibration needs identified stars from at least {MIN_SEQUENCES} sequences; "
                      f"{n_sequences} usable", location="sequences")
    try:
        result = fit_camera(first, camera, parameters=names)
        again = reassociated(identified, first, result, sky)
        if len({o.sequence for o in again}) < MIN_SEQUENCES:
            return Fitted(result, first, result)
        return Fitted(fit_camera(again, camera, parameters=names), again, result)
    except ValueError as exc:
        raise Invalid(f"the camera cannot be calibrated from these sequences: {exc}", location="sequences") from None


def calibrate_files(files: Iterable[tuple[str, object]], sky, options,
                    parameters: Iterable[str] | None = None) -> tuple[CalibrationDocument, list[tuple[str, str]]]:
    """Solve every ``(path, sequence)`` and fit one camera over those that identify.

    Returns the calibration and ``(path, what happened)`` per file: the
    status, and why a file was left out.  A calibration is of one camera:
    the files of the sensor size most of them have (the first file's on a
    tie) take part, with the first such file's camera as the declared one.
    """
    from app.identification import IDENTIFIED, solve_sequence

    files = list(files)
    if not files:
        raise Invalid("no telemetry file to calibrate from", location="files")
    sizes = Counter((sequence.camera.width, sequence.camera.height) for _, sequence in files)
    chosen = max(sizes, key=sizes.__getitem__)  # a Counter keeps the files' order: the first file's on a tie
    camera = next(sequence.camera for _, sequence in files
                  if (sequence.camera.width, sequence.camera.height) == chosen)
    identified, report = [], []
    for path, sequence in files:
        size = (sequence.camera.width, sequence.camera.height)
        if size != chosen:
            report.append((path, f"left out: another sensor size ({size[0]}x{size[1]}) than most files' "
                                 f"({chosen[0]}x{chosen[1]})"))
            continue
        solved = solve_sequence(sequence, sky, options=options)
        if solved.solution.status != IDENTIFIED:
            report.append((path, f"left out: {solved.solution.status}"))
            continue
        item = IdentifiedSequence.from_solved(path, solved, sky)
        report.append((path, f"identified, {len(item.observations)} snapshot(s) with 3 or more "
                             "identified stars"))
        identified.append(item)
    fitted = fit(identified, camera, sky, parameters)
    result = fitted.calibration
    return CalibrationDocument.of(result, residual_map(fitted.observations, result, camera)), report


# ---------------------------------------------------------------------------
# From the archive
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class ArchiveSelection:
    """What :func:`archive_sequences` took from a spacecraft's archive, and what it left out and why."""

    sequences: list[IdentifiedSequence]  # usable, of the chosen sensor, newest first
    camera: Camera | None  # the chosen sensor's newest declared camera (None: nothing usable at all)
    other_sensors: dict[str, int]  # "WxH" -> usable sequences of that sensor size, left out
    repeated: int  # uploads left out as another upload of a sequence taken already (its id or its snapshots)


def snapshots_digest(sequence: Sequence) -> str:
    """What makes two uploads the same telemetry whatever their bytes and names: every snapshot's time and
    its sources' positions and brightnesses, in order (SHA-256 of their exact values)."""
    h = hashlib.sha256()
    for snapshot in sequence.snapshots:
        h.update(snapshot.time.isoformat().encode())
        h.update(np.ascontiguousarray(snapshot.xy, dtype=float).tobytes())
        h.update(np.ascontiguousarray(snapshot.brightness, dtype=float).tobytes())
    return h.hexdigest()


def archive_sequences(ctx: AppContext, spacecraft: str) -> ArchiveSelection:
    """The usable sequences of ``spacecraft`` for one camera, newest first, with what was left out.

    Usable: confirmed (the confirmed candidate) or identified (the first
    candidate) and not given "no valid attitude" by an operator, with 3 or
    more identified stars in some snapshot.  One upload per sequence: the
    same telemetry sent again in other bytes (CRLF line endings, a byte-order
    mark) or under another sequence id is a second upload of the same stars,
    and counting it twice would make the calibration's uncertainties too
    small.  Uploads are the same sequence when they share their sequence id
    or their snapshots (:func:`snapshots_digest`); the confirmed upload is
    taken, else the newest.  A spacecraft name may cover several sensors (a
    second camera, a renamed test article); a calibration is of one, the
    sensor with the most usable sequences (on a tie, the newest sequence's),
    and uses at most :data:`MAX_SEQUENCES` of them.
    """
    from app.workflow.documents import SearchResult

    by_sensor: dict[tuple[int, int], list[IdentifiedSequence]] = {}
    cameras: dict[tuple[int, int], Camera] = {}  # each sensor's newest declared camera, newest sensor first
    # (sensor, "id", sequence id) and (sensor, "snapshots", their digest) -> (position, confirmed)
    taken: dict[tuple, tuple[int, bool]] = {}
    repeated = 0
    offset = 0
    while all(len(found) < MAX_SEQUENCES for found in by_sensor.values()):
        rows, total = ctx.storage.list_sequences(offset, 200, spacecraft=spacecraft)
        for light in rows:
            if light.status == "rejected":  # an operator's "no valid attitude" stands over any search
                continue
            candidate = None
            confirmation = ctx.storage.current_confirmation(light.id)
            if confirmation is not None:
                candidate = CandidateDocument.model_validate(confirmation.candidate)
            else:
                search = ctx.storage.latest_search(light.id)
                if search is not None and search.status == "identified":
                    candidate = SearchResult.model_validate(search.result).candidate(1)
            if candidate is None:
                continue
            item = loaded(ctx, require_sequence(ctx, light.id))
            sensor = (item.sequence.camera.width, item.sequence.camera.height)
            cameras.setdefault(sensor, item.sequence.camera)
            found = by_sensor.setdefault(sensor, [])
            keys = [(sensor, "snapshots", snapshots_digest(item.sequence))]
            if light.sequence_id is not None:
                keys.append((sensor, "id", light.sequence_id))
            confirmed = confirmation is not None
            earlier = next((taken[key] for key in keys if key in taken), None)
            if earlier is not None and (earlier[1] or not confirmed):
                repeated += 1  # a newer (or as well confirmed) upload of this sequence is taken already
                continue
            if earlier is None and len(found) >= MAX_SEQUENCES:
                continue
            usable = IdentifiedSequence.of(str(light.id), item.sequence, item.extraction, candidate, ctx.sky)
            if not usable.observations:
                continue
            if earlier is None:
                position = len(found)
                found.append(usable)
            else:  # this older upload is the confirmed one: it takes the newer one's place
                position = earlier[0]
                found[position] = usable
                repeated += 1
            for key in keys:
                taken[key] = (position, confirmed)
        offset += len(rows)
        if not rows or offset >= total:
            break
    if not cameras:
        return ArchiveSelection([], None, {}, repeated)
    chosen = max(cameras, key=lambda sensor: len(by_sensor[sensor]))  # max keeps the first (newest) on a tie
    others = {f"{w}x{h}": len(found) for (w, h), found in by_sensor.items() if (w, h) != chosen and found}
    return ArchiveSelection(by_sensor[chosen], cameras[chosen], others, repeated)


def calibrate_spacecraft(ctx: AppContext, spacecraft: str, operator: str | None = None,
                         parameters: Iterable[str] | None = None) -> StoredCalibration:
    """Fit the camera of ``spacecraft`` from its archive and store it as the next calibration version."""
    require_audit_text(operator=operator)
    selection = archive_sequences(ctx, spacecraft)
    identified, camera, other_sensors = selection.sequences, selection.camera, selection.other_sensors
    if camera is None:
        raise NotFound(f"no identified or confirmed sequence of spacecraft {spacecraft!r} to calibrate from")
    left_out = [f"{n} usable sequence{'s' * (n != 1)} of another sensor size ({sensor})"
                for sensor, n in sorted(other_sensors.items())]
    tie = any(n == len(identified) for n in other_sensors.values())
    why = (f"left out: a calibration is of one camera, the {camera.width}x{camera.height} sensor, which has "
           + ("as many usable sequences as any and the newest" if tie else "the most usable sequences"))
    notes = [f"{entry} {why}" for entry in left_out]
    if selection.repeated:
        notes.append(f"{selection.repeated} upload{'s' * (selection.repeated != 1)} of a sequence already "
                     "used left out (the same telemetry sent again, under its sequence id or another, counts once: "
                     "the confirmed upload, else the newest)")
    try:
        fitted = fit(identified, camera, ctx.sky, parameters)
    except Invalid as exc:
        if not notes:
            raise
        raise Invalid(f"{exc.detail} ({'; '.join(notes)})", location="sequences") from None
    result, observations = fitted.calibration, fitted.observations
    document = CalibrationDocument.of(result, residual_map(observations, result, camera), notes=notes)
    used_ids = sorted({int(o.sequence) for o, inlier in zip(observations, result.inliers) if np.any(inlier)})
    row = ctx.storage.add_calibration(spacecraft, camera=document.camera, result=document.model_dump(mode="json"),
                                      sequences=used_ids, operator=operator)
    return StoredCalibration.of(row)


def current_camera(ctx: AppContext, spacecraft: str) -> StoredCalibration:
    row = ctx.storage.current_calibration(spacecraft)
    if row is None:
        raise NotFound(f"spacecraft {spacecraft!r} has no camera calibration yet; "
                       f"POST /api/spacecraft/{spacecraft}/calibrate makes one")
    return StoredCalibration.of(row)


def calibration_history(ctx: AppContext, spacecraft: str) -> list[StoredCalibration]:
    return [StoredCalibration.of(row) for row in ctx.storage.calibration_history(spacecraft)]
