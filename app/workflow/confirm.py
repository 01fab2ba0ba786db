"""The confirmation workflow: an operator confirms a candidate; the archive keeps the audit record and
the CCSDS messages rendered once.

A confirmation stores the candidate, the pattern it was searched on, the
reference epoch and the fitted body rate as columns, and the APM and AEM
texts rendered at that moment (creation date = confirmation time), so its
exports never change afterwards.
"""

from __future__ import annotations

import re
from datetime import datetime, timezone

import numpy as np

from app.attitude import propagate, quaternion_from_rotation
from app.ccsds import aem_kvn, apm_kvn
from app.storage import ConfirmationRow, SequenceRow
from app.workflow.archive import definition_of, loaded, require_sequence
from app.workflow.context import AppContext, LoadedSequence
from app.workflow.documents import AttitudeDocument, AttitudePage, CandidateDocument, PatternUsed
from app.workflow.errors import Conflict, NotFound
from app.workflow.search import candidate_of, latest_search

#: Originator written into the CCSDS messages.
ORIGINATOR = "STARID GROUND STATION"
CAMERA_FRAME_COMMENT = "REF_FRAME_B SENSOR_1 is the star camera frame: +X pixel column, +Y pixel row, +Z boresight"


def _object_names(row: SequenceRow) -> tuple[str, str]:
    return (row.spacecraft or "UNKNOWN SPACECRAFT", row.sequence_id or f"SEQUENCE {row.id}")


def _uncertainty_comments(candidate: CandidateDocument) -> list[str]:
    """The attitude's 1-sigma (APM 2.0 has no covariance block) and the fitted body rate."""
    out = []
    if candidate.sigma_cross_boresight_arcsec is not None:
        out.append(f"1-sigma uncertainty: {candidate.sigma_cross_boresight_arcsec} arcsec about each "
                   f"cross-boresight axis, {candidate.sigma_roll_arcsec} arcsec in roll (camera frame)")
    fit = candidate.sequence_fit
    if fit is not None:
        rate = ", ".join(f"{w:.6f}" for w in fit.rate_deg_s)
        sig = ", ".join(f"{w:.6f}" for w in fit.rate_sigma_deg_s)
        out.append(f"Body rate (camera axes) [{rate}] deg/s, 1-sigma [{sig}] deg/s, "
                   f"from {fit.snapshots_used} snapshots")
    return out


def render_apm(row: SequenceRow, candidate: CandidateDocument, epoch: datetime, operator: str,
               confirmed_at: datetime, comment: str | None) -> str:
    name, object_id = _object_names(row)
    comments = [f"Star pattern identification of sequence {object_id} (archive id {row.id}), "
                f"candidate rank {candidate.rank}",
                f"Confirmed by {operator}; deviation {candidate.deviation_arcsec} arcsec, "
                f"false-match probability {candidate.false_match_probability}",
                *_uncertainty_comments(candidate), CAMERA_FRAME_COMMENT]
    if comment:
        comments.append(f"Operator comment: {comment}")
    return apm_kvn(epoch=epoch, quaternion_xyzw=candidate.unit_quaternion, originator=ORIGINATOR,
                   object_name=name, object_id=object_id, comments=comments, creation_date=confirmed_at)


def attitude_per_snapshot(item: LoadedSequence, candidate: CandidateDocument) -> tuple[list[datetime], list]:
    """ICRS -> camera rotation of every snapshot whose attitude the candidate gives.

    With the candidate's fitted body rate (the sequence fit,
    :mod:`app.attitude.sequence`), every snapshot's attitude is the reference
    attitude propagated at that rate (:func:`app.attitude.propagate`).
    Without one, extraction's motion: ``motion[i]`` carries snapshot i's
    camera vectors into the reference frame (``v_ref = M_i v_i``), so
    ``R_i = M_i^T R_ref`` where it is known.
    """
    rotation_ref = candidate.rotation
    snapshots = item.sequence.snapshots
    if candidate.sequence_fit is not None:
        rate = candidate.sequence_fit.rate_rad_s
        t_ref = snapshots[item.extraction.reference].time
        return ([s.time for s in snapshots],
                [propagate(rotation_ref, rate, (s.time - t_ref).total_seconds()) for s in snapshots])
    known = [(s.time, motion.T @ rotation_ref) for s, motion in zip(snapshots, item.extraction.motion)
             if np.all(np.isfinite(motion))]
    return [t for t, _ in known], [r for _, r in known]


def render_aem(row: SequenceRow, item: LoadedSequence, candidate: CandidateDocument, operator: str,
               confirmed_at: datetime) -> str | None:
    times, rotations = attitude_per_snapshot(item, candidate)
    if not times:
        return None
    name, object_id = _object_names(row)
    return aem_kvn(epochs=times, quaternions_xyzw=[quaternion_from_rotation(R) for R in rotations],
                   originator=ORIGINATOR, object_name=name, object_id=object_id, creation_date=confirmed_at,
                   comments=[f"Attitude of each snapshot of sequence {object_id} (archive id {row.id}) from "
                             f"candidate rank {candidate.rank} confirmed by {operator}", CAMERA_FRAME_COMMENT])


def confirm(ctx: AppContext, seq_id: int, rank: int, operator: str, comment: str | None) -> AttitudeDocument:
    """Append a confirmation of ``rank`` of the latest search (Conflict if there is no such rank)."""
    row = require_sequence(ctx, seq_id)
    search, result = latest_search(ctx, seq_id, missing=Conflict)
    candidate = candidate_of(search, result, rank, missing=Conflict)
    item = loaded(ctx, row)
    epoch = item.sequence.snapshots[result.reference_snapshot].time
    # One instant for the record and the messages' CREATION_DATE, so they agree exactly.
    confirmed_at = datetime.now(timezone.utc)
    apm = render_apm(row, candidate, epoch, operator, confirmed_at, comment)
    aem = render_aem(row, item, candidate, operator, confirmed_at)
    # The pattern of the search, which later edits may have replaced as the current one.
    searched = next((v for v in ctx.storage.pattern_history(seq_id) if v.version == result.pattern_version), None)
    pattern_used = PatternUsed(version=result.pattern_version, points=result.pattern,
                               definition=definition_of(searched))
    fit = candidate.sequence_fit
    stored = ctx.storage.add_confirmation(
        seq_id, search_id=search.id, rank=rank, operator=operator, comment=comment,
        quaternion=candidate.unit_quaternion, rotation_matrix=candidate.rotation_matrix,
        ra_deg=candidate.ra_deg, dec_deg=candidate.dec_deg, roll_deg=candidate.roll_deg,
        deviation_arcsec=candidate.deviation_arcsec, false_match_probability=candidate.false_match_probability,
        pattern=pattern_used.model_dump(mode="json"), candidate=candidate.model_dump(mode="json"),
        apm_text=apm, aem_text=aem, confirmed_at=confirmed_at, epoch=epoch,
        rate_deg_s=None if fit is None else fit.rate_deg_s)
    return AttitudeDocument.of(stored, ctx.storage.get_sequence(seq_id))


def require_attitude(ctx: AppContext, attitude_id: int) -> ConfirmationRow:
    c = ctx.storage.get_confirmation(attitude_id)
    if c is None:
        raise NotFound(f"no confirmed attitude with id {attitude_id}")
    return c


def get_attitude(ctx: AppContext, attitude_id: int) -> AttitudeDocument:
    c = require_attitude(ctx, attitude_id)
    return AttitudeDocument.of(c, ctx.storage.get_sequence(c.seq_id))


def list_attitudes(ctx: AppContext, offset: int, limit: int) -> AttitudePage:
    rows, total = ctx.storage.list_confirmations(offset, limit)
    sequences: dict[int, SequenceRow | None] = {}
    for c in rows:
        if c.seq_id not in sequences:
            sequences[c.seq_id] = ctx.storage.get_sequence(c.seq_id)
    return AttitudePage(items=[AttitudeDocument.of(c, sequences[c.seq_id]) for c in rows], total=total,
                        offset=offset, limit=limit)


def download_name(stem: str | None, fallback: str, suffix: str) -> str:
    """A safe file name for a download: letters, digits, '.', '-', '_' only."""
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", stem or "").strip("._") or fallback
    return f"{base[:80]}{suffix}"


def attitude_apm(ctx: AppContext, attitude_id: int) -> tuple[str, str]:
    """The APM text of a confirmed attitude, byte for byte as rendered, and its download name."""
    c = require_attitude(ctx, attitude_id)
    row = ctx.storage.get_sequence(c.seq_id)
    name = download_name(f"{row.sequence_id}-attitude-{c.id}" if row else None, f"attitude-{c.id}", ".apm")
    return c.apm_text, name


def sequence_aem(ctx: AppContext, seq_id: int) -> tuple[str, str]:
    """The AEM text of the sequence's current confirmation and its download name."""
    row = require_sequence(ctx, seq_id)
    c = ctx.storage.current_confirmation(seq_id)
    if c is None:
        raise NotFound(f"sequence {seq_id} has no confirmed attitude yet; confirm a candidate first")
    if not c.aem_text:
        raise NotFound(f"sequence {seq_id} has no snapshot whose attitude is known")
    return c.aem_text, download_name(row.sequence_id, f"sequence-{seq_id}", ".aem")
