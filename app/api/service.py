"""What the endpoints do, as plain functions of the :class:`AppContext`.

Routes only translate HTTP to these calls; everything here takes and returns
Python values and raises :class:`ApiError` (with the HTTP status) or
:class:`TelemetryError` (422) for what a client did wrong.

Stored documents
----------------
* pattern version: the operator's *definition* ``{"exclude_tracks": [...],
  "include_tracks": null | [...], "manual_points": [{"snapshot", "x", "y"}]}``;
  the points are recomputed from it (extraction is deterministic).
* search result: ``{"status", "method", "reference_snapshot", "reference_time",
  "pattern_version", "pattern": [pattern rows], "candidates": [...], "notes",
  "elapsed_ms"}``; each candidate is :meth:`Candidate.to_json` plus
  ``pattern_index`` on its matches and planets (rows of ``pattern``), so the
  sky view and the confirmation need nothing but the stored record.
* confirmation: the candidate, the pattern used, and the APM and AEM texts
  rendered once (creation date = confirmation time) so exports never change.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

import numpy as np

from app.api.context import AppContext, LoadedSequence
from app.api.errors import ApiError
from app.attitude import quaternion_from_rotation
from app.extraction import Pattern, build_pattern, extract, extraction_to_json, pattern_to_json
from app.storage import ConfirmationRow, PatternVersion, SearchRow, SequenceRow, content_sha256
from app.telemetry import parse_telemetry
from app.telemetry.model import format_time

#: Identification methods of a search: the bright-pair index (default),
#: Liebe's triangle features, and tracking from a prior attitude.
METHODS = ("bright_pair", "tf", "tracking")
#: Originator written into the CCSDS messages.
ORIGINATOR = "STARID GROUND STATION"


def automatic_definition() -> dict:
    return {"exclude_tracks": [], "include_tracks": None, "manual_points": []}


def _time_text(t: datetime | None) -> str | None:
    return None if t is None else t.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


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
# Sequences
# ---------------------------------------------------------------------------

def sequence_summary(row: SequenceRow) -> dict:
    return {"id": row.id, "sequence_id": row.sequence_id, "spacecraft": row.spacecraft,
            "filename": row.filename, "camera": row.camera, "first_time": _time_text(row.first_time),
            "n_snapshots": row.n_snapshots, "uploaded_at": _time_text(row.uploaded_at),
            "status": row.status, "content_sha256": row.content_sha256}


def require_sequence(ctx: AppContext, seq_id: int) -> SequenceRow:
    row = ctx.storage.get_sequence(seq_id)
    if row is None:
        raise ApiError(404, f"no sequence with id {seq_id}")
    return row


def loaded(ctx: AppContext, row: SequenceRow) -> LoadedSequence:
    return ctx.load_sequence(row.id, row.raw_text, row.filename)


@dataclass(frozen=True, eq=False)
class ParsedUpload:
    """A valid upload: the telemetry and the text as sent."""

    sequence: Any  # app.telemetry.Sequence
    raw_text: str
    filename: str | None


def parse_upload(ctx: AppContext, data: bytes, filename: str | None) -> ParsedUpload:
    """Validate an upload; raises TelemetryError (422) for invalid telemetry."""
    filename = clean_filename(filename)
    sequence = parse_telemetry(data, filename=filename, max_bytes=ctx.settings.max_upload_bytes)
    # parse_telemetry accepted the bytes as UTF-8; keep the text as sent.
    return ParsedUpload(sequence=sequence, raw_text=bytes(data).decode("utf-8"), filename=filename)


def stored_upload(ctx: AppContext, upload: ParsedUpload) -> dict | None:
    """The document of the stored sequence with the same content, if there is one."""
    row = ctx.storage.find_sequence(content_sha256(upload.raw_text))
    return None if row is None else _upload_document(ctx, row, created=False)


def extraction_job(sequence, *, sky=None):
    """Extraction as a compute-pool job (it needs no catalogue)."""
    return extract(sequence)


def store_upload(ctx: AppContext, upload: ParsedUpload, extraction) -> tuple[dict, bool]:
    """Store a parsed and extracted upload; ``(document, created)`` (False: the same content was
    stored meanwhile)."""
    sequence = upload.sequence
    row, created = ctx.storage.add_sequence(
        raw_text=upload.raw_text, filename=upload.filename, sequence_id=sequence.sequence_id,
        spacecraft=sequence.spacecraft, camera=sequence.camera.to_dict(),
        first_time=sequence.snapshots[0].time if sequence.snapshots else None,
        n_snapshots=len(sequence.snapshots), extraction=extraction_to_json(extraction))
    if created:
        ctx.cache.put(row.id, LoadedSequence(sequence, extraction))
        ctx.storage.add_pattern_version(row.id, automatic_definition(), kind="automatic")
    return _upload_document(ctx, row, created), created


def _upload_document(ctx: AppContext, row: SequenceRow, created: bool) -> dict:
    item = loaded(ctx, row)
    return {"id": row.id, "created": created, "sequence": sequence_summary(row),
            "extraction": row.extraction,
            "pattern": pattern_document(item, current_pattern(ctx, row.id))}


def current_pattern(ctx: AppContext, seq_id: int) -> PatternVersion | None:
    return ctx.storage.current_pattern(seq_id)


def pattern_from_definition(item: LoadedSequence, definition: dict) -> Pattern:
    """The pattern an operator's definition describes; ValueError with the reason if it cannot be built."""
    manual = [(p["snapshot"], p["x"], p["y"]) for p in definition.get("manual_points") or []]
    return build_pattern(item.sequence, item.extraction, exclude_tracks=definition.get("exclude_tracks") or [],
                         include_tracks=definition.get("include_tracks"), manual_points=manual)


def pattern_document(item: LoadedSequence, version: PatternVersion | None) -> dict:
    definition = version.pattern if version is not None else automatic_definition()
    try:
        points = pattern_to_json(pattern_from_definition(item, definition))
    except ValueError:  # stored definitions were checked when stored; be safe anyway
        points = pattern_to_json(item.extraction.pattern)
    return {"version": version.version if version else None, "kind": version.kind if version else "automatic",
            "operator": version.operator if version else None,
            "created_at": _time_text(version.created_at) if version else None,
            "definition": definition, "points": points,
            "reference_snapshot": int(item.extraction.reference)}


def sequence_detail(ctx: AppContext, seq_id: int) -> dict:
    row = require_sequence(ctx, seq_id)
    item = loaded(ctx, row)
    search = ctx.storage.latest_search(seq_id)
    confirmation = ctx.storage.current_confirmation(seq_id)
    return {**sequence_summary(row), "telemetry": item.sequence.to_json_dict(), "extraction": row.extraction,
            "pattern": pattern_document(item, current_pattern(ctx, seq_id)),
            "search": None if search is None else search_document(search),
            "confirmation": None if confirmation is None else attitude_document(confirmation, row)}


def list_sequences(ctx: AppContext, offset: int, limit: int, spacecraft: str | None, status: str | None) -> dict:
    rows, total = ctx.storage.list_sequences(offset, limit, spacecraft=spacecraft, status=status)
    return {"items": [sequence_summary(r) for r in rows], "total": total, "offset": offset, "limit": limit}


def set_pattern(ctx: AppContext, seq_id: int, definition: dict, operator: str | None) -> dict:
    """Store the operator's pattern as a new version after checking it can be built."""
    row = require_sequence(ctx, seq_id)
    item = loaded(ctx, row)
    try:
        pattern_from_definition(item, definition)
    except ValueError as exc:
        raise ApiError(422, f"the pattern cannot be built: {exc}",
                       problems=[{"location": "body", "message": str(exc)}]) from None
    version = ctx.storage.add_pattern_version(seq_id, definition, kind="edit", operator=operator)
    return pattern_document(item, version)


def reset_pattern(ctx: AppContext, seq_id: int, operator: str | None) -> dict:
    row = require_sequence(ctx, seq_id)
    version = ctx.storage.add_pattern_version(seq_id, automatic_definition(), kind="reset", operator=operator)
    return pattern_document(loaded(ctx, row), version)


# ---------------------------------------------------------------------------
# Search and candidates
# ---------------------------------------------------------------------------

def _candidate_document(solved, candidate) -> dict:
    from app.identification import candidate_json

    doc = candidate_json(solved, candidate)
    for m_doc, match in zip(doc["matches"], candidate.matches):
        m_doc["pattern_index"] = int(match.pattern_index)
    for p_doc, planet in zip(doc["planets"], candidate.planets):
        p_doc["pattern_index"] = int(planet.pattern_index)
    doc["n_matched"] = candidate.n_matched
    doc["n_hypotheses_merged"] = int(candidate.n_hypotheses_merged)
    return doc


def tracking_prior(ctx: AppContext, row: SequenceRow, prior: dict | None):
    """The prior of a tracking search: the one given, else the newest confirmed attitude of the
    same spacecraft propagated with its body rate (422 when there is neither)."""
    from app.attitude import rotation_from_radec_roll
    from app.identification import Prior

    if prior is not None:
        return Prior(rotation=rotation_from_radec_roll(prior["ra_deg"], prior["dec_deg"], prior["roll_deg"]),
                     sigma_deg=prior.get("sigma_deg") or 1.0)
    offset = 0
    while True:
        page, total = ctx.storage.list_confirmations(offset, 100)
        for c in page:
            other = ctx.storage.get_sequence(c.seq_id)
            if other is None or other.spacecraft != row.spacecraft or c.superseded_by is not None:
                continue
            fit = (c.candidate or {}).get("sequence_fit")
            epoch = _confirmation_epoch(ctx, c)
            rate = np.radians(fit["rate_deg_s"]) if fit else None
            # Without a rate the attitude is only a rough guide: widen the prior.
            return Prior(rotation=np.array(c.rotation_matrix, dtype=float), time=epoch, rate_rad_s=rate,
                         sigma_deg=1.0 if rate is not None else 5.0)
        offset += len(page)
        if not page or offset >= total:
            raise ApiError(422, "tracking needs a prior attitude: give \"prior\" (ra_deg, dec_deg, roll_deg, "
                                f"sigma_deg) or confirm an attitude of spacecraft {row.spacecraft!r} first")


def _confirmation_epoch(ctx: AppContext, c: ConfirmationRow) -> datetime | None:
    text = _epoch_of(c)
    return datetime.fromisoformat(text.replace("Z", "+00:00")) if text else None


@dataclass(frozen=True, eq=False)
class SearchJob:
    """Everything one identification needs, gathered from the archive (picklable: it may run in a
    worker process)."""

    seq_id: int
    method: str
    sequence: Any  # app.telemetry.Sequence
    extraction: Any  # app.extraction.Extraction
    pattern: Pattern
    pattern_version: int | None
    options: Any  # app.identification.SearchOptions
    prior: Any  # app.identification.Prior or None


def prepare_search(ctx: AppContext, seq_id: int, method: str, max_candidates: int | None,
                   prior: dict | None = None) -> SearchJob:
    """The job of a search on the current pattern (404 unknown sequence, 422 unknown method or no prior)."""
    if method not in METHODS:
        raise ApiError(422, f"unknown method {method!r}; known: {', '.join(METHODS)}")
    row = require_sequence(ctx, seq_id)
    item = loaded(ctx, row)
    version = current_pattern(ctx, seq_id)
    definition = version.pattern if version is not None else automatic_definition()
    return SearchJob(seq_id=seq_id, method=method, sequence=item.sequence, extraction=item.extraction,
                     pattern=pattern_from_definition(item, definition),
                     pattern_version=version.version if version else None,
                     options=search_options(ctx, max_candidates),
                     prior=tracking_prior(ctx, row, prior) if method == "tracking" else None)


def compute_search(job: SearchJob, *, sky) -> dict:
    """Identify the job's pattern: the search result document (see the module doc)."""
    from app.identification import solve_sequence

    solved = solve_sequence(job.sequence, sky, options=job.options, extraction=job.extraction,
                            pattern=job.pattern, prior=job.prior,
                            method=job.method if job.method != "tracking" else "bright_pair")
    solution = solved.solution
    return {"status": solution.status, "method": job.method,
            "reference_snapshot": int(job.extraction.reference),
            "reference_time": format_time(solved.reference_time),
            "pattern_version": job.pattern_version,
            "pattern": pattern_to_json(job.pattern),
            "candidates": [_candidate_document(solved, c) for c in solution.candidates],
            "notes": list(job.extraction.notes) + list(solution.notes),
            "elapsed_ms": round(solution.elapsed_s * 1000, 2)}


def store_search(ctx: AppContext, job: SearchJob, result: dict) -> dict:
    """Archive a computed search and set the sequence's status from it."""
    search = ctx.storage.add_search(job.seq_id, pattern_version=job.pattern_version, method=job.method,
                                    options=search_options_record(ctx, job.options), result=result,
                                    status=result["status"], elapsed_s=result["elapsed_ms"] / 1000)
    row = require_sequence(ctx, job.seq_id)
    # A confirmed sequence stays confirmed: its attitude stands until a new confirmation supersedes it.
    if row.status != "confirmed":
        ctx.storage.set_status(job.seq_id, result["status"])
    return {**search_document(search), "reused": False}


def search_options(ctx: AppContext, max_candidates: int | None):
    """The identification options of a search request (the server's time-out, the client's count)."""
    from app.identification import SearchOptions

    return SearchOptions(timeout_s=ctx.settings.search_timeout_s,
                         **({} if max_candidates is None else {"max_candidates": max_candidates}))


def search_options_record(ctx: AppContext, options) -> dict:
    """What a stored search depended on besides its pattern and method: its options and the index searched."""
    index = ctx.sky.index
    return {"max_candidates": options.max_candidates, "timeout_s": options.timeout_s,
            "index": {"stars": int(index.n_stars), "pairs": int(index.n_pairs),
                      "mag_limit": float(index.mag_limit)}}


def reusable_search(ctx: AppContext, seq_id: int, method: str, max_candidates: int | None) -> dict | None:
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
    if method not in METHODS or method == "tracking":  # a tracking search depends on its prior too
        return None
    row = ctx.storage.get_sequence(seq_id)
    search = ctx.storage.latest_search(seq_id) if row is not None else None
    if search is None:
        return None
    version = current_pattern(ctx, seq_id)
    options = search_options(ctx, max_candidates)
    timed_out = search.elapsed_s is None or search.elapsed_s >= options.timeout_s
    if (timed_out or search.method != method or search.pattern_version != (version.version if version else None)
            or search.options != search_options_record(ctx, options)):
        return None
    if row.status != "confirmed" and row.status != search.status:
        ctx.storage.set_status(seq_id, search.status)
    return {**search_document(search), "reused": True}


def search_document(search: SearchRow) -> dict:
    return {"search_id": search.id, "sequence": search.seq_id, "created_at": _time_text(search.created_at),
            **search.result}


def latest_search_or_error(ctx: AppContext, seq_id: int, status_code: int) -> SearchRow:
    search = ctx.storage.latest_search(seq_id)
    if search is None:
        raise ApiError(status_code, f"sequence {seq_id} has not been searched yet; "
                                    f"POST /api/sequences/{seq_id}/search first")
    return search


def candidate_of(search: SearchRow, rank: int, status_code: int) -> dict:
    candidates = search.result.get("candidates", [])
    for candidate in candidates:
        if candidate["rank"] == rank:
            return candidate
    raise ApiError(status_code, f"the latest search of sequence {search.seq_id} has no candidate of rank {rank} "
                                f"(it has {len(candidates)})")


def candidate_view(ctx: AppContext, seq_id: int, rank: int, mag: float) -> dict:
    """One candidate of the latest search with its sky section (see :mod:`app.skyview`)."""
    from app.catalogue import load_catalogue, star_names
    from app.planets import planet_vectors
    from app.skyview import sky_section

    row = require_sequence(ctx, seq_id)
    search = latest_search_or_error(ctx, seq_id, 404)
    candidate = candidate_of(search, rank, 404)
    item = loaded(ctx, row)
    t = item.sequence.snapshots[search.result["reference_snapshot"]].time
    section = sky_section(rotation=np.array(candidate["rotation_matrix"]), camera=item.sequence.camera, t=t,
                          catalogue=load_catalogue(), names=star_names(), mag_limit=mag,
                          pattern=search.result["pattern"], candidate=candidate, planets=planet_vectors(t),
                          velocity_km_s=item.sequence.velocity_km_s)
    return {"sequence": seq_id, "search_id": search.id, "status": search.result["status"],
            "rank": rank, "n_candidates": len(search.result["candidates"]),
            "reference_snapshot": search.result["reference_snapshot"],
            "reference_time": search.result["reference_time"], "candidate": candidate, "sky": section}


# ---------------------------------------------------------------------------
# Confirmations and CCSDS exports
# ---------------------------------------------------------------------------

def _object_names(row: SequenceRow) -> tuple[str, str]:
    return (row.spacecraft or "UNKNOWN SPACECRAFT", row.sequence_id or f"SEQUENCE {row.id}")


def render_apm(row: SequenceRow, candidate: dict, epoch: datetime, operator: str, confirmed_at: datetime,
               comment: str | None) -> str:
    from app.ccsds import apm_kvn

    name, object_id = _object_names(row)
    comments = [f"Star pattern identification of sequence {object_id} (archive id {row.id}), "
                f"candidate rank {candidate['rank']}",
                f"Confirmed by {operator}; deviation {candidate['deviation_arcsec']} arcsec, "
                f"false-match probability {candidate['false_match_probability']}",
                *_uncertainty_comments(candidate),
                "REF_FRAME_B SENSOR_1 is the star camera frame: +X pixel column, +Y pixel row, +Z boresight"]
    if comment:
        comments.append(f"Operator comment: {comment}")
    return apm_kvn(epoch=epoch, quaternion_xyzw=_unit(candidate["quaternion"]), originator=ORIGINATOR,
                   object_name=name, object_id=object_id, comments=comments, creation_date=confirmed_at)


def _uncertainty_comments(candidate: dict) -> list[str]:
    """The attitude's 1-sigma (APM 2.0 has no covariance block) and the fitted body rate."""
    out = []
    if candidate.get("sigma_cross_boresight_arcsec") is not None:
        out.append(f"1-sigma uncertainty: {candidate['sigma_cross_boresight_arcsec']} arcsec about each "
                   f"cross-boresight axis, {candidate['sigma_roll_arcsec']} arcsec in roll (camera frame)")
    fit = candidate.get("sequence_fit")
    if fit:
        rate = ", ".join(f"{w:.6f}" for w in fit["rate_deg_s"])
        sig = ", ".join(f"{w:.6f}" for w in fit["rate_sigma_deg_s"])
        out.append(f"Body rate (camera axes) [{rate}] deg/s, 1-sigma [{sig}] deg/s, "
                   f"from {fit['snapshots_used']} snapshots")
    return out


def _unit(q) -> list[float]:
    q = np.asarray(q, dtype=float)
    return list(q / np.linalg.norm(q))


def snapshot_attitudes(item: LoadedSequence, rotation_ref: np.ndarray,
                       rate_rad_s: np.ndarray | None = None) -> tuple[list[datetime], list[np.ndarray]]:
    """ICRS -> camera rotation of every snapshot.

    With the candidate's fitted body rate ``w`` (the sequence fit,
    :mod:`app.attitude.sequence`): ``R_i = exp(-[w]x (t_i - t_ref)) R_ref``
    for every snapshot.  Without one, extraction's motion: ``motion[i]``
    carries snapshot i's camera vectors into the reference frame
    (``v_ref = M_i v_i``), so ``R_i = M_i^T R_ref`` where it is known.
    """
    from scipy.spatial.transform import Rotation

    times, rotations = [], []
    if rate_rad_s is not None:
        t_ref = item.sequence.snapshots[item.extraction.reference].time
        for snapshot in item.sequence.snapshots:
            dt = (snapshot.time - t_ref).total_seconds()
            times.append(snapshot.time)
            rotations.append(Rotation.from_rotvec(-np.asarray(rate_rad_s) * dt).as_matrix() @ rotation_ref)
        return times, rotations
    for snapshot, motion in zip(item.sequence.snapshots, item.extraction.motion):
        if np.all(np.isfinite(motion)):
            times.append(snapshot.time)
            rotations.append(motion.T @ rotation_ref)
    return times, rotations


def render_aem(row: SequenceRow, item: LoadedSequence, candidate: dict, operator: str,
               confirmed_at: datetime) -> str | None:
    from app.ccsds import aem_kvn

    fit = candidate.get("sequence_fit")
    times, rotations = snapshot_attitudes(item, np.array(candidate["rotation_matrix"], dtype=float),
                                          np.radians(fit["rate_deg_s"]) if fit else None)
    if not times:
        return None
    name, object_id = _object_names(row)
    return aem_kvn(epochs=times, quaternions_xyzw=[quaternion_from_rotation(R) for R in rotations],
                   originator=ORIGINATOR, object_name=name, object_id=object_id, creation_date=confirmed_at,
                   comments=[f"Attitude of each snapshot of sequence {object_id} (archive id {row.id}) from "
                             f"candidate rank {candidate['rank']} confirmed by {operator}",
                             "REF_FRAME_B SENSOR_1 is the star camera frame: +X pixel column, +Y pixel row, "
                             "+Z boresight"])


def confirm(ctx: AppContext, seq_id: int, rank: int, operator: str, comment: str | None) -> dict:
    """Append a confirmation of ``rank`` of the latest search (409 if there is no such rank)."""
    row = require_sequence(ctx, seq_id)
    search = latest_search_or_error(ctx, seq_id, 409)
    candidate = candidate_of(search, rank, 409)
    item = loaded(ctx, row)
    epoch = item.sequence.snapshots[search.result["reference_snapshot"]].time
    # One instant for the record and the messages' CREATION_DATE, so they agree exactly.
    confirmed_at = datetime.now(timezone.utc)
    apm = render_apm(row, candidate, epoch, operator, confirmed_at, comment)
    aem = render_aem(row, item, candidate, operator, confirmed_at)
    # The pattern of the search, which later edits may have replaced as the current one.
    searched_version = search.result.get("pattern_version")
    definition = next((v.pattern for v in ctx.storage.pattern_history(seq_id) if v.version == searched_version),
                      automatic_definition())
    pattern_used = {"version": searched_version, "points": search.result["pattern"], "definition": definition}
    stored = ctx.storage.add_confirmation(
        seq_id, search_id=search.id, rank=rank, operator=operator, comment=comment,
        quaternion=_unit(candidate["quaternion"]), rotation_matrix=candidate["rotation_matrix"],
        ra_deg=candidate["ra_deg"], dec_deg=candidate["dec_deg"], roll_deg=candidate["roll_deg"],
        deviation_arcsec=candidate.get("deviation_arcsec"),
        false_match_probability=candidate.get("false_match_probability"),
        pattern=pattern_used, candidate=candidate, apm_text=apm, aem_text=aem, confirmed_at=confirmed_at)
    return attitude_document(stored, ctx.storage.get_sequence(seq_id))


def attitude_document(c: ConfirmationRow, row: SequenceRow | None) -> dict:
    return {"id": c.id, "sequence": c.seq_id, "sequence_id": row.sequence_id if row else None,
            "spacecraft": row.spacecraft if row else None, "search_id": c.search_id, "rank": c.rank,
            "operator": c.operator, "confirmed_at": _time_text(c.confirmed_at), "comment": c.comment,
            "epoch": _epoch_of(c), "ra_deg": c.ra_deg, "dec_deg": c.dec_deg, "roll_deg": c.roll_deg,
            "quaternion": c.quaternion, "rotation_matrix": c.rotation_matrix,
            "deviation_arcsec": c.deviation_arcsec, "false_match_probability": c.false_match_probability,
            "pattern": c.pattern, "candidate": c.candidate, "superseded_by": c.superseded_by,
            "current": c.is_current, "apm_url": f"/api/attitudes/{c.id}/apm",
            "aem_url": f"/api/sequences/{c.seq_id}/aem" if c.aem_text else None}


def _epoch_of(c: ConfirmationRow) -> str | None:
    """The APM's EPOCH (the reference snapshot's time), read back from the stored text."""
    match = re.search(r"^EPOCH = (\S+)$", c.apm_text, flags=re.MULTILINE)
    return match.group(1) + "Z" if match else None


def require_attitude(ctx: AppContext, attitude_id: int) -> ConfirmationRow:
    c = ctx.storage.get_confirmation(attitude_id)
    if c is None:
        raise ApiError(404, f"no confirmed attitude with id {attitude_id}")
    return c


def get_attitude(ctx: AppContext, attitude_id: int) -> dict:
    c = require_attitude(ctx, attitude_id)
    return attitude_document(c, ctx.storage.get_sequence(c.seq_id))


def list_attitudes(ctx: AppContext, offset: int, limit: int) -> dict:
    rows, total = ctx.storage.list_confirmations(offset, limit)
    sequences: dict[int, SequenceRow | None] = {}
    for c in rows:
        if c.seq_id not in sequences:
            sequences[c.seq_id] = ctx.storage.get_sequence(c.seq_id)
    return {"items": [attitude_document(c, sequences[c.seq_id]) for c in rows], "total": total,
            "offset": offset, "limit": limit}


def sequence_aem(ctx: AppContext, seq_id: int) -> tuple[str, ConfirmationRow]:
    require_sequence(ctx, seq_id)
    c = ctx.storage.current_confirmation(seq_id)
    if c is None:
        raise ApiError(404, f"sequence {seq_id} has no confirmed attitude yet; confirm a candidate first")
    if not c.aem_text:
        raise ApiError(404, f"sequence {seq_id} has no snapshot whose attitude is known")
    return c.aem_text, c


def download_name(stem: str | None, fallback: str, suffix: str) -> str:
    """A safe Content-Disposition file name: letters, digits, '.', '-', '_' only."""
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", stem or "").strip("._") or fallback
    return f"{base[:80]}{suffix}"


def health(ctx: AppContext) -> dict:
    db = ctx.storage.health()
    db.pop("path", None)  # a server path is nobody's business over HTTP
    index = ctx.sky.index if ctx.sky is not None else None
    index_doc = {"loaded": index is not None}
    if index is not None:
        index_doc.update(stars=int(index.n_stars), pairs=int(index.n_pairs), mag_limit=float(index.mag_limit))
    ok = bool(db.get("ok")) and index is not None
    return {"status": "ok" if ok else "degraded", "db": db, "index": index_doc,
            "auth_required_for_writes": ctx.access.require_token,
            "max_upload_bytes": ctx.settings.max_upload_bytes, "search_timeout_s": ctx.settings.search_timeout_s,
            "search_workers": ctx.compute.kind}



# ---------------------------------------------------------------------------
# Shared view state of the console and the 3D view (issue 5)
# ---------------------------------------------------------------------------

def view_document(ctx: AppContext) -> dict:
    """The shared view state plus what the archive says about its sequence now.

    The derived fields (latest search, its size, the pattern version, the
    current confirmation) are read fresh on every call, so a reader notices
    a search, an edit or a confirmation made by the other window even though
    only the selection itself is stored.
    """
    state = ctx.view.get()
    doc = {**state.to_json(), "search_id": None, "n_candidates": 0, "status": None,
           "pattern_version": None, "confirmation_id": None}
    row = ctx.storage.get_sequence(state.sequence) if state.sequence is not None else None
    if row is not None:
        search = ctx.storage.latest_search(row.id)
        version = ctx.storage.current_pattern(row.id)
        confirmation = ctx.storage.current_confirmation(row.id)
        doc.update(status=row.status, pattern_version=version.version if version else None,
                   confirmation_id=confirmation.id if confirmation else None)
        if search is not None:
            doc.update(search_id=search.id, n_candidates=len(search.result.get("candidates", [])))
    return doc


def set_view(ctx: AppContext, changes: dict, writer_name: str) -> dict:
    """Write the given view fields (checked against the archive) and return the new document.

    A new sequence without a rank starts at rank 1 of its latest search (or
    none); a rank must exist in the latest search of the sequence shown.
    """
    changes = dict(changes)
    seq_id = changes.get("sequence", ctx.view.get().sequence)
    if "sequence" in changes and seq_id is not None and ctx.storage.get_sequence(seq_id) is None:
        raise ApiError(422, f"no sequence with id {seq_id}",
                       problems=[{"location": "body.sequence", "message": "no such sequence"}])
    search = ctx.storage.latest_search(seq_id) if seq_id is not None else None
    n_candidates = len(search.result.get("candidates", [])) if search is not None else 0
    if "sequence" in changes and "rank" not in changes:
        changes["rank"] = 1 if n_candidates else None
    rank = changes.get("rank")
    if rank is not None and not 1 <= rank <= n_candidates:
        raise ApiError(422, f"rank {rank} is not a candidate of the latest search "
                            f"(it has {n_candidates})",
                       problems=[{"location": "body.rank", "message": f"not in 1..{n_candidates}"}])
    try:
        ctx.view.update(**changes, updated_by=writer_name)
    except ValueError as exc:
        raise ApiError(422, str(exc), problems=[{"location": "body", "message": str(exc)}]) from None
    return view_document(ctx)
