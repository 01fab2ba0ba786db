"""The search workflow: prepare from the archive, compute in the pool, store; candidates and their sky view.

A search is split in three so that only the middle part occupies a worker:

1. :func:`prepare_search` gathers a picklable :class:`SearchJob` from the
   archive (the sequence, its stored extraction, the current pattern, the
   options, the prior of a tracking search);
2. :func:`compute_search` runs identification (in a worker process or
   thread: :mod:`app.workflow.compute`) and returns a typed
   :class:`SearchResult`;
3. :func:`store_search` archives it and sets the sequence's status.

:func:`reusable_search` answers a repeated request from the archive when
running it again would compute the same result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.attitude import rotation_from_radec_roll
from app.extraction import Extraction, Pattern
from app.frames.times import time_notes
from app.identification import METHODS, Prior, SearchOptions, solve_sequence
from app.storage import SearchRow
from app.telemetry import Sequence
from app.timefmt import utc_text
from app.workflow.archive import current_pattern_version, definition_of, loaded, pattern_from_definition, \
    require_sequence
from app.workflow.context import AppContext
from app.workflow.documents import (CandidateDocument, CandidateView, FocalLengthContradictionDocument, PatternPoint,
                                    SearchDocument, SearchResult)
from app.workflow.errors import Conflict, Invalid, NotFound

#: 1-sigma of a prior propagated from the spacecraft's last confirmation with its fitted rate, and
#: without one (then the attitude is only a rough guide), degrees.
PRIOR_SIGMA_WITH_RATE_DEG = 1.0
PRIOR_SIGMA_WITHOUT_RATE_DEG = 5.0


@dataclass(frozen=True)
class PriorRequest:
    """A prior attitude given with a tracking search: boresight RA/Dec, roll and 1-sigma, degrees."""

    ra_deg: float
    dec_deg: float
    roll_deg: float
    sigma_deg: float = 1.0


@dataclass(frozen=True, eq=False)
class SearchJob:
    """Everything one identification needs, gathered from the archive (picklable: it may run in a
    worker process)."""

    seq_id: int
    method: str
    camera_calibration: int | None  # the spacecraft's calibration version the sequence's camera came from
    sequence: Sequence
    extraction: Extraction
    pattern: Pattern
    pattern_version: int | None
    options: SearchOptions
    prior: Prior | None


def tracking_prior(ctx: AppContext, spacecraft: str | None, prior: PriorRequest | None) -> Prior:
    """The prior of a tracking search: the one given, else the newest current confirmation of the
    same spacecraft with its body rate (:class:`Invalid` when there is neither)."""
    if prior is not None:
        return Prior(rotation=rotation_from_radec_roll(prior.ra_deg, prior.dec_deg, prior.roll_deg),
                     sigma_deg=prior.sigma_deg)
    c = ctx.storage.latest_confirmation_of_spacecraft(spacecraft)
    if c is None:
        raise Invalid("tracking needs a prior attitude: give \"prior\" (ra_deg, dec_deg, roll_deg, sigma_deg) "
                      f"or confirm an attitude of spacecraft {spacecraft!r} first", location="body.prior")
    rate = None if c.rate_deg_s is None else np.radians(c.rate_deg_s)
    return Prior(rotation=np.array(c.rotation_matrix, dtype=float), time=c.epoch, rate_rad_s=rate,
                 sigma_deg=PRIOR_SIGMA_WITH_RATE_DEG if rate is not None else PRIOR_SIGMA_WITHOUT_RATE_DEG)


def search_options(ctx: AppContext, max_candidates: int | None) -> SearchOptions:
    """The identification options of a search request: the server's identification budget (a part of the
    time-out users see, leaving room for the queue, extraction and storage) and the client's count."""
    return SearchOptions(timeout_s=ctx.settings.search_budget_s,
                         **({} if max_candidates is None else {"max_candidates": max_candidates}))


def search_options_record(ctx: AppContext, options: SearchOptions, camera_calibration: int | None) -> dict:
    """What a stored search depended on besides its pattern and method: its options, the index searched
    and the camera calibration version its sequence was given (None: the file's own or the default camera)."""
    index = ctx.sky.index
    return {"max_candidates": options.max_candidates, "timeout_s": options.timeout_s,
            "index": {"stars": int(index.n_stars), "pairs": int(index.n_pairs),
                      "mag_limit": float(index.mag_limit)},
            "camera_calibration": camera_calibration}


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise Invalid(f"unknown method {method!r}; known: {', '.join(METHODS)}", location="body.method")


def prepare_search(ctx: AppContext, seq_id: int, method: str, max_candidates: int | None,
                   prior: PriorRequest | None = None) -> SearchJob:
    """The job of a search on the current pattern (NotFound, or Invalid for an unknown method or no prior)."""
    _check_method(method)
    row = require_sequence(ctx, seq_id)
    item = loaded(ctx, row)
    version = ctx.storage.current_pattern(seq_id)
    return SearchJob(seq_id=seq_id, method=method, camera_calibration=row.camera_calibration,
                     sequence=item.sequence, extraction=item.extraction,
                     pattern=pattern_from_definition(item, definition_of(version)),
                     pattern_version=version.version if version else None,
                     options=search_options(ctx, max_candidates),
                     prior=tracking_prior(ctx, row.spacecraft, prior) if METHODS[method].needs_prior else None)


def search_result(solved, method: str, pattern_version: int | None) -> SearchResult:
    """The document of an identification run (:class:`app.identification.SolvedSequence`)."""
    solution = solved.solution
    return SearchResult(status=solution.status, method=method,
                        reference_snapshot=int(solved.extraction.reference),
                        reference_time=utc_text(solved.reference_time), pattern_version=pattern_version,
                        pattern=PatternPoint.rows(solved.pattern),
                        candidates=[CandidateDocument.of(c, solved.sequence_fits.get(c.rank))
                                    for c in solution.candidates],
                        notes=list(solved.extraction.notes) + list(solution.notes) + time_notes(solved.sequence),
                        elapsed_ms=round(solution.elapsed_s * 1000, 2),
                        focal_length_contradiction=FocalLengthContradictionDocument.of(
                            solution.focal_length_contradiction))


def compute_search(job: SearchJob, *, sky) -> SearchResult:
    """Identify the job's pattern (a compute-pool job)."""
    solved = solve_sequence(job.sequence, sky, options=job.options, extraction=job.extraction,
                            pattern=job.pattern, prior=job.prior, method=job.method)
    return search_result(solved, job.method, job.pattern_version)


def store_search(ctx: AppContext, job: SearchJob, result: SearchResult) -> SearchDocument:
    """Archive a computed search and, in the same write, set the sequence's status from it (a confirmed or
    rejected sequence keeps its verdict until an operator supersedes it)."""
    search = ctx.storage.add_search(job.seq_id, pattern_version=job.pattern_version, method=job.method,
                                    options=search_options_record(ctx, job.options, job.camera_calibration),
                                    result=result.model_dump(mode="json"), status=result.status,
                                    elapsed_s=result.elapsed_ms / 1000)
    return SearchDocument.of(search)


def reusable_search(ctx: AppContext, seq_id: int, method: str, max_candidates: int | None) -> SearchDocument | None:
    """The latest stored search if running the search again would compute the same result, else None.

    Identification is a deterministic function of the pattern, the method,
    the options and the catalogue index, so a new request on an unchanged
    pattern version with equal options and the same index is answered from
    the archive (same ``search_id``, ``"reused": true``) instead of queueing
    for a search worker.  A search that ran into its time-out is never
    reused: it may have stopped early, and a rerun may find more.  Anything
    unusual (unknown method or sequence) returns None so that
    :func:`prepare_search` produces the proper error.
    """
    if method not in METHODS or METHODS[method].needs_prior:  # a tracking search depends on its prior too
        return None
    row = ctx.storage.get_sequence(seq_id)
    search = ctx.storage.latest_search(seq_id) if row is not None else None
    if search is None:
        return None
    options = search_options(ctx, max_candidates)
    timed_out = search.elapsed_s is None or search.elapsed_s >= options.timeout_s
    if (timed_out or search.method != method or search.pattern_version != current_pattern_version(ctx, seq_id)
            or search.options != search_options_record(ctx, options, row.camera_calibration)):
        return None
    if row.status not in ("confirmed", "rejected") and row.status != search.status:
        ctx.storage.set_search_status(seq_id, search.status)
    return SearchDocument.of(search, reused=True)


def latest_search(ctx: AppContext, seq_id: int, missing: type[NotFound] | type[Conflict] = NotFound
                  ) -> tuple[SearchRow, SearchResult]:
    """The sequence's latest search, parsed; ``missing`` is raised when it has none."""
    search = ctx.storage.latest_search(seq_id)
    if search is None:
        raise missing(f"sequence {seq_id} has not been searched yet; POST /api/sequences/{seq_id}/search first")
    return search, SearchResult.model_validate(search.result)


def require_search_of(ctx: AppContext, seq_id: int, search_id: int) -> SearchRow:
    """Search ``search_id`` when it is one of sequence ``seq_id``'s searches; :class:`Invalid` (at
    ``body.search_id``) when it is another sequence's or does not exist.

    A confirmation names the search its operator looked at, and the guard
    rail refuses one that a newer search of the sequence replaced.  An id
    that was never a search of this sequence is another case: nothing
    replaced it, so saying so would send the operator looking for new
    candidates that do not exist.  It is a wrong value in the request (422,
    located, like an unknown track of a pattern edit), not a change of the
    archive's state (409): no reload makes it right.
    """
    require_sequence(ctx, seq_id)  # 404 for an unknown sequence, as before
    search = ctx.storage.get_search(search_id)
    if search is not None and search.seq_id == seq_id:
        return search
    latest = ctx.storage.latest_search(seq_id)
    known = f"its latest is {latest.id}" if latest is not None else "it has not been searched yet"
    message = f"search {search_id} is not a search of sequence {seq_id} ({known})"
    raise Invalid(message, location="body.search_id", message=message)


def candidate_of(search: SearchRow, result: SearchResult, rank: int,
                 missing: type[NotFound] | type[Conflict] = NotFound) -> CandidateDocument:
    candidate = result.candidate(rank)
    if candidate is None:
        raise missing(f"the latest search of sequence {search.seq_id} has no candidate of rank {rank} "
                      f"(it has {len(result.candidates)})")
    return candidate


@dataclass(frozen=True, eq=False)
class CandidateViewJob:
    """What one candidate view needs, read from the archive (picklable: the sky section is computed in
    the compute pool, as searches are, so that it does not hold the server's request threads)."""

    seq_id: int
    search_id: int
    rank: int
    mag: float
    result: SearchResult
    candidate: CandidateDocument
    camera: object
    time: object
    velocity_km_s: object  # the sequence's observer (app.telemetry.Sequence.observer)
    time_assumed: bool = False  # no planets are drawn at an assumed time


def prepare_candidate_view(ctx: AppContext, seq_id: int, rank: int, mag: float) -> CandidateViewJob:
    """The job of one candidate view (NotFound for an unknown sequence, search or rank)."""
    row = require_sequence(ctx, seq_id)
    search, result = latest_search(ctx, seq_id)
    candidate = candidate_of(search, result, rank)
    sequence = loaded(ctx, row).sequence
    return CandidateViewJob(seq_id=seq_id, search_id=search.id, rank=rank, mag=mag, result=result,
                            candidate=candidate, camera=candidate.matched_camera(sequence.camera),
                            time=sequence.snapshots[result.reference_snapshot].time,
                            velocity_km_s=sequence.observer, time_assumed=sequence.time_assumed)


def candidate_view_job(job: CandidateViewJob, *, sky=None) -> CandidateView:
    """One candidate of the latest search with its sky section (see :mod:`app.workflow.skyview`); a
    compute-pool job (~8 ms of CPU: stars, names, constellations and planets of the section)."""
    from app.catalogue import load_catalogue, star_names
    from app.planets import planet_vectors
    from app.workflow.skyview import sky_section

    result = job.result
    section = sky_section(rotation=job.candidate.rotation, camera=job.camera, t=job.time,
                          catalogue=load_catalogue(), names=star_names(), mag_limit=job.mag,
                          pattern=result.pattern, candidate=job.candidate,
                          planets=None if job.time_assumed else planet_vectors(job.time),
                          velocity_km_s=job.velocity_km_s)
    return CandidateView(sequence=job.seq_id, search_id=job.search_id, status=result.status, rank=job.rank,
                         n_candidates=len(result.candidates), reference_snapshot=result.reference_snapshot,
                         reference_time=result.reference_time, candidate=job.candidate, sky=section)


def candidate_view(ctx: AppContext, seq_id: int, rank: int, mag: float) -> CandidateView:
    """One candidate of the latest search with its sky section, computed here (the API computes it in the
    compute pool: :func:`prepare_candidate_view`, then :func:`candidate_view_job`)."""
    return candidate_view_job(prepare_candidate_view(ctx, seq_id, rank, mag))
