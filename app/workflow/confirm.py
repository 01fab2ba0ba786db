"""The confirmation workflow: an operator confirms a candidate (or records "no valid attitude"); the
archive keeps the audit record and the CCSDS messages rendered once.

A confirmation stores the candidate, the pattern it was searched on, the
reference epoch and the fitted body rate as columns, and the APM, AEM and ACM
texts rendered at that moment (creation date = confirmation time), so its
exports never change afterwards.  (Confirmations stored before the ACM
existed get theirs rendered from the stored record on request, with the same
creation date: :func:`attitude_acm`.)

Guard rails:

* a candidate that is not the credible best (:mod:`app.workflow.review`:
  not rank 1, a ``no_match`` or ``ambiguous`` search, a search older than
  the pattern) is confirmed only with ``override_reason``, which the audit
  record and the APM keep with the reasons it overrode;
* a sequence has one current verdict: confirming the same candidate of the
  same search again returns the stored record (no second audit record), and
  anything else replaces the verdict only when asked to (``supersede``);
* a client may name the search it looked at (``search_id``): if a newer
  search replaced it meanwhile, nothing is stored.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from datetime import datetime, timezone

import numpy as np

from app.attitude import propagate, quaternion_from_rotation
from app.ccsds import CAMERA_FRAME, AcmDetermination, AcmSensor, acm_kvn, aem_kvn, apm_kvn, comment_lines, format_epoch
from app.storage import ConfirmationRow, RejectionRow, SequenceRow, VerdictExists, verdict_key
from app.timefmt import utc_text
from app.workflow.archive import current_pattern_version, definition_of, loaded, require_sequence
from app.workflow.context import AppContext, LoadedSequence
from app.workflow.documents import (AttitudeDocument, AttitudePage, CandidateDocument, PatternUsed,
                                    RejectionDocument)
from app.workflow.errors import Conflict, Invalid, NotFound
from app.workflow.review import candidate_verdicts
from app.workflow.search import candidate_of, latest_search
from app.workflow.text import require_audit_text

#: Originator written into the CCSDS messages.
ORIGINATOR = "STARID GROUND STATION"
CAMERA_FRAME_COMMENT = "REF_FRAME_B SENSOR_1 is the star camera frame: +X pixel column, +Y pixel row, +Z boresight"
#: First comment of every message of a sequence whose frames carried no time: its epochs are the
#: stated J2000.0 epoch, not when the frames were taken, and a reader of the message alone must know that.
TIME_ASSUMED_COMMENT = ("WARNING: the frames carried no time: the epochs are assumed (J2000.0 plus 1 s a frame), "
                        "not observation times, and the attitude is referred to the stars' J2000.0 mean places "
                        "(no aberration)")


def _time_comments(sequence) -> list[str]:
    """:data:`TIME_ASSUMED_COMMENT` when ``sequence``'s time was assumed, else nothing."""
    return [TIME_ASSUMED_COMMENT] if sequence.time_assumed else []


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


def _quality(candidate: CandidateDocument) -> str:
    """A candidate's quality in a message's reader's terms: the matched stars and their RMS residual, and the
    seed's deviation named a sum over the pattern (read alone, "deviation 1388 arcsec" looked like a pointing
    error)."""
    rms = "" if candidate.rms_arcsec is None else f"{candidate.rms_arcsec:.1f} arcsec RMS; "
    return (f"{candidate.n_matched} stars matched, residual {rms}deviation {candidate.deviation_arcsec} arcsec summed "
            f"over the pattern's points (the seed's measure, not a pointing error), false-match probability "
            f"{candidate.false_match_probability}")


def _verdict_comments(override_reason: str | None, overridden: list[str] | None, comment: str | None) -> list[str]:
    """Why an operator confirmed a candidate that was not the credible best, and their comment: every message of a
    confirmation carries them, so that whoever reads one alone sees it."""
    return ([f"Confirmed by operator override ({'; '.join(overridden)}): {override_reason}"] if overridden else []) \
        + ([f"Operator comment: {comment}"] if comment else [])


def render_apm(row: SequenceRow, candidate: CandidateDocument, epoch: datetime, operator: str,
               confirmed_at: datetime, comment: str | None, override_reason: str | None = None,
               overridden: list[str] | None = None, time_assumed: bool = False) -> str:
    name, object_id = _object_names(row)
    comments = [*([TIME_ASSUMED_COMMENT] if time_assumed else []), f"Star pattern identification of sequence {object_id} (archive id {row.id}), "
                f"candidate rank {candidate.rank}",
                f"Confirmed by {operator}; {_quality(candidate)}",
                *_uncertainty_comments(candidate), CAMERA_FRAME_COMMENT,
                *_verdict_comments(override_reason, overridden, comment)]
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
               confirmed_at: datetime, comment: str | None = None, override_reason: str | None = None,
               overridden: list[str] | None = None) -> str | None:
    times, rotations = attitude_per_snapshot(item, candidate)
    if not times:
        return None
    name, object_id = _object_names(row)
    return aem_kvn(epochs=times, quaternions_xyzw=[quaternion_from_rotation(R) for R in rotations],
                   originator=ORIGINATOR, object_name=name, object_id=object_id, creation_date=confirmed_at,
                   comments=[*_time_comments(item.sequence), f"Attitude of each snapshot of sequence {object_id} (archive id {row.id}) from "
                             f"candidate rank {candidate.rank} confirmed by {operator}", CAMERA_FRAME_COMMENT,
                             *_verdict_comments(override_reason, overridden, comment)])


def render_acm(row: SequenceRow, item: LoadedSequence, candidate: CandidateDocument, *, epoch: datetime,
               method: str, search_id: int | None, operator: str, confirmed_at: datetime,
               comment: str | None = None, override_reason: str | None = None,
               overridden: list[str] | None = None) -> str:
    """The ACM: every snapshot's attitude with the body rate, the covariance of the attitude
    at the reference epoch (the QUEST model's 1-sigma, camera axes) and how it was determined."""
    times, rotations = attitude_per_snapshot(item, candidate)
    if not times:
        times, rotations = [epoch], [candidate.rotation]
    name, object_id = _object_names(row)
    fit = candidate.sequence_fit
    covariance = None
    if candidate.sigma_cross_boresight_arcsec is not None and candidate.sigma_roll_arcsec is not None:
        cross, roll = (candidate.sigma_cross_boresight_arcsec / 3600.0) ** 2, (candidate.sigma_roll_arcsec / 3600.0) ** 2
        covariance = (epoch, (cross, cross, roll)) if np.isfinite([cross, roll]).all() else None
    snapshots = item.sequence.snapshots
    steps = [(b.time - a.time).total_seconds() for a, b in zip(snapshots, snapshots[1:])]
    sensor = AcmSensor(
        number=1, used="STAR_TRACKER",
        noise_stddev_deg=() if candidate.rms_arcsec is None else (candidate.rms_arcsec / 3600.0,),
        frequency_hz=1.0 / float(np.median(steps)) if steps else None,
        comments=(f"The star camera ({CAMERA_FRAME}): {len(snapshots)} snapshots, {candidate.n_matched} stars "
                  "matched; SENSOR_NOISE_STDDEV is the RMS of the matched stars' residuals",))
    determination = AcmDetermination(
        ad_id=f"SEARCH_{search_id}_RANK_{candidate.rank}", method="BATCH" if fit is not None else "Q_METHOD",
        source="GROUND STAR PATTERN IDENTIFICATION", number_states=7 if fit is not None else 4,
        cov_type="ANGLE" if covariance is not None else None, rate_states="ANGVEL" if fit is not None else None,
        sensors=(sensor,),
        comments=(f"Identified by {method} (search {search_id}, candidate rank {candidate.rank}): "
                  f"{_quality(candidate)}",
                  "Each snapshot's attitude solves Wahba's problem (SVD, Davenport's q-method equivalent); "
                  + (f"the sequence's attitude and body rate are fitted over {fit.snapshots_used} snapshots by "
                     f"batch least squares (reduced chi-square {fit.chi2_reduced})" if fit is not None
                     else "no body rate was fitted")))
    comments = [*_time_comments(item.sequence), f"Star pattern identification of sequence {object_id} (archive id "
                f"{row.id}), candidate rank {candidate.rank}, confirmed by {operator}", CAMERA_FRAME_COMMENT,
                *_verdict_comments(override_reason, overridden, comment)]
    return acm_kvn(
        epochs=times, quaternions_xyzw=[quaternion_from_rotation(R) for R in rotations], originator=ORIGINATOR,
        object_name=name, rate_deg_s=None if fit is None else fit.rate_deg_s, covariance=covariance,
        determination=determination, creation_date=confirmed_at, comments=comments,
        att_comments=["Attitude of each snapshot" + (", propagated from the reference epoch with the fitted "
                                                     "body rate (angular velocity of SENSOR_1 relative to ICRF, "
                                                     "SENSOR_1 axes, deg/s)" if fit is not None else
                                                     " from the tracked motion (no body rate fitted)")],
        cov_comments=[f"1-sigma of the attitude at the reference epoch {format_epoch(epoch)} (QUEST measurement "
                      "model, inflated by the reduced chi-square), as variances about SENSOR_1's X, Y, Z; X and Y "
                      "hold the mean cross-boresight variance"])


def describe_verdict(verdict: ConfirmationRow | RejectionRow) -> str:
    """The current verdict in a sentence, for refusals that name it."""
    if isinstance(verdict, ConfirmationRow):
        return (f"attitude #{verdict.id} (rank {verdict.rank} of search {verdict.search_id}) confirmed by "
                f"{verdict.operator} at {utc_text(verdict.confirmed_at)}")
    return f"'no valid attitude' recorded by {verdict.operator} at {utc_text(verdict.rejected_at)}: {verdict.reason}"


def record_confirmation(ctx: AppContext, seq_id: int, rank: int, operator: str, comment: str | None, *,
                        override_reason: str | None = None, supersede: bool = False,
                        search_id: int | None = None,
                        replaces: tuple[str, int] | None = None) -> tuple[AttitudeDocument, bool]:
    """Confirm ``rank`` of the latest search behind the guard rails (module docstring).

    Returns the attitude and whether it was stored now (False: the same
    candidate of the same search was the current verdict already).  Raises
    :class:`Conflict` for a rank not in the latest search, a replaced
    ``search_id``, a candidate that needs ``override_reason`` without one, or
    a different current verdict without ``supersede``, or with ``replaces``
    (:func:`app.storage.verdict_key` of the verdict the operator saw) naming
    another than the current one: a verdict given in between is never
    replaced unseen.
    """
    require_audit_text(operator=operator, comment=comment, override_reason=override_reason)
    row = require_sequence(ctx, seq_id)
    search, result = latest_search(ctx, seq_id, missing=Conflict)
    if search_id is not None and search_id != search.id:
        raise Conflict(f"the candidates of search {search_id} were replaced by search {search.id} of sequence "
                       f"{seq_id}; look at the new candidates before confirming")
    candidate = candidate_of(search, result, rank, missing=Conflict)
    current = ctx.storage.current_verdict(seq_id)
    if current is not None and not supersede:
        return _repeat_or_refuse(ctx, row, current, search.id, rank)
    _check_replaces(seq_id, current, supersede, replaces)
    verdict = next(v for v in candidate_verdicts(result, current_pattern_version(ctx, seq_id)) if v.rank == rank)
    override_reason = (override_reason or "").strip() or None
    if not verdict.credible and override_reason is None:
        raise Conflict(f"rank {rank} of sequence {seq_id} is not the credible best candidate "
                       f"({'; '.join(verdict.reasons)}). Confirming it anyway needs override_reason "
                       "(why you confirm it), which the audit record keeps")
    overridden = None if verdict.credible else verdict.reasons
    item = loaded(ctx, row)
    epoch = item.sequence.snapshots[result.reference_snapshot].time
    # One instant for the record and the messages' CREATION_DATE, so they agree exactly.
    confirmed_at = datetime.now(timezone.utc)
    apm = render_apm(row, candidate, epoch, operator, confirmed_at, comment, override_reason, overridden,
                     time_assumed=item.sequence.time_assumed)
    aem = render_aem(row, item, candidate, operator, confirmed_at, comment, override_reason, overridden)
    acm = render_acm(row, item, candidate, epoch=epoch, method=result.method, search_id=search.id, operator=operator,
                     confirmed_at=confirmed_at, comment=comment, override_reason=override_reason, overridden=overridden)
    # The pattern of the search, which later edits may have replaced as the current one.
    searched = next((v for v in ctx.storage.pattern_history(seq_id) if v.version == result.pattern_version), None)
    pattern_used = PatternUsed(version=result.pattern_version, points=result.pattern,
                               definition=definition_of(searched))
    fit = candidate.sequence_fit
    try:
        stored = ctx.storage.add_confirmation(
            seq_id, search_id=search.id, rank=rank, operator=operator, comment=comment,
            quaternion=candidate.unit_quaternion, rotation_matrix=candidate.rotation_matrix,
            ra_deg=candidate.ra_deg, dec_deg=candidate.dec_deg, roll_deg=candidate.roll_deg,
            deviation_arcsec=candidate.deviation_arcsec, false_match_probability=candidate.false_match_probability,
            pattern=pattern_used.model_dump(mode="json"), candidate=candidate.model_dump(mode="json"),
            apm_text=apm, aem_text=aem, confirmed_at=confirmed_at, epoch=epoch,
            rate_deg_s=None if fit is None else fit.rate_deg_s, override_reason=override_reason,
            overridden=overridden, supersede=supersede, acm_text=acm, replaces=replaces)
    except VerdictExists as exc:  # another operator's verdict landed between our check and our write
        _check_replaces(seq_id, exc.current, supersede, replaces)
        return _repeat_or_refuse(ctx, row, exc.current, search.id, rank)
    return AttitudeDocument.of(stored, ctx.storage.get_sequence(seq_id)), True


def _check_replaces(seq_id: int, current: ConfirmationRow | RejectionRow | None, supersede: bool,
                    replaces: tuple[str, int] | None) -> None:
    """A new verdict replaces the one the operator saw (``replaces``), or none: Conflict when another
    operator's verdict came in between, Invalid when the sequence has no verdict to replace."""
    if not supersede or replaces is None:
        return
    if current is None:
        raise Invalid(f"sequence {seq_id} has no verdict to replace ({replaces[0]} #{replaces[1]} was named)",
                      location="body.replaces", message="the sequence has no verdict")
    if verdict_key(current) != tuple(replaces):
        raise Conflict(f"another verdict came first: sequence {seq_id}'s verdict is now {describe_verdict(current)}, "
                       f"not {replaces[0]} #{replaces[1]}, named to be replaced; look at it before replacing it")


def _repeat_or_refuse(ctx: AppContext, row: SequenceRow, current: ConfirmationRow | RejectionRow,
                      search_id: int, rank: int) -> tuple[AttitudeDocument, bool]:
    """The stored confirmation when it is this very one again; otherwise the refusal naming the verdict."""
    if isinstance(current, ConfirmationRow) and current.search_id == search_id and current.rank == rank:
        return AttitudeDocument.of(current, row), False
    raise Conflict(f"sequence {row.id} already has a verdict: {describe_verdict(current)}. "
                   "Send supersede: true to replace it (the earlier record stays in the audit trail)")


def confirm(ctx: AppContext, seq_id: int, rank: int, operator: str, comment: str | None, *,
            override_reason: str | None = None, supersede: bool = False) -> AttitudeDocument:
    """:func:`record_confirmation` for callers that do not need to know whether it was stored now."""
    return record_confirmation(ctx, seq_id, rank, operator, comment, override_reason=override_reason,
                               supersede=supersede)[0]


def reject(ctx: AppContext, seq_id: int, operator: str, reason: str | None, *,
           supersede: bool = False, replaces: tuple[str, int] | None = None) -> tuple[RejectionDocument, bool]:
    """Record "no valid attitude" for a sequence, with the operator's reason, as its verdict.

    Returns the rejection and whether it was stored now (False: the current
    verdict already is a rejection).  A current confirmation is withdrawn
    only with ``supersede`` (Conflict otherwise), and with ``replaces`` only if
    it is the one named (see :func:`record_confirmation`); it stays in the
    audit trail.
    """
    require_audit_text(operator=operator, reason=reason)
    row = require_sequence(ctx, seq_id)
    reason = (reason or "").strip()
    if not reason:
        raise Invalid("'no valid attitude' needs the reason (what makes every candidate wrong)",
                      location="body.reason", message="missing reason")
    search = ctx.storage.latest_search(seq_id)
    _check_replaces(seq_id, ctx.storage.current_verdict(seq_id), supersede, replaces)
    try:
        stored = ctx.storage.add_rejection(seq_id, operator=operator, reason=reason,
                                           search_id=search.id if search else None, supersede=supersede,
                                           replaces=replaces)
    except VerdictExists as exc:
        _check_replaces(seq_id, exc.current, supersede, replaces)
        if isinstance(exc.current, RejectionRow):
            return RejectionDocument.of(exc.current, row), False
        raise Conflict(f"sequence {seq_id} already has a verdict: {describe_verdict(exc.current)}. "
                       "Send supersede: true to withdraw it (it stays in the audit trail)") from None
    return RejectionDocument.of(stored, ctx.storage.get_sequence(seq_id)), True


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


def attitude_acm(ctx: AppContext, attitude_id: int) -> tuple[str, str]:
    """The ACM text of a confirmed attitude as rendered at confirmation, and its download name; for a
    confirmation stored before ACMs existed, rendered now from the stored record (same creation date)."""
    c = require_attitude(ctx, attitude_id)
    row = ctx.storage.get_sequence(c.seq_id)
    name = download_name(f"{row.sequence_id}-attitude-{c.id}" if row else None, f"attitude-{c.id}", ".acm")
    if c.acm_text:
        return c.acm_text, name
    candidate = CandidateDocument.model_validate(c.candidate)
    item = loaded(ctx, row)
    search = ctx.storage.get_search(c.search_id) if c.search_id is not None else None
    epoch = c.epoch or item.sequence.snapshots[item.extraction.reference].time
    return render_acm(row, item, candidate, epoch=epoch, method=search.method if search else "unknown method",
                      search_id=c.search_id, operator=c.operator, confirmed_at=c.confirmed_at, comment=c.comment,
                      override_reason=c.override_reason, overridden=c.overridden), name


def attitude_aem(ctx: AppContext, attitude_id: int) -> tuple[str, str]:
    """The AEM text of a confirmed attitude, byte for byte as rendered at its confirmation (superseded or
    not), and its download name."""
    c = require_attitude(ctx, attitude_id)
    if not c.aem_text:
        raise NotFound(f"attitude {attitude_id} has no AEM: no snapshot's attitude was known when it was confirmed")
    row = ctx.storage.get_sequence(c.seq_id)
    return c.aem_text, download_name(f"{row.sequence_id}-attitude-{c.id}" if row else None, f"attitude-{c.id}", ".aem")


def sequence_aem(ctx: AppContext, seq_id: int) -> tuple[str, str]:
    """The AEM text of the sequence's current confirmation and its download name."""
    row = require_sequence(ctx, seq_id)
    c = ctx.storage.current_confirmation(seq_id)
    if c is None:
        if row.status == "rejected":
            raise NotFound(f"sequence {seq_id} has no attitude: its verdict is 'no valid attitude'")
        raise NotFound(f"sequence {seq_id} has no confirmed attitude yet; confirm a candidate first")
    if not c.aem_text:
        raise NotFound(f"sequence {seq_id} has no snapshot whose attitude is known")
    return c.aem_text, download_name(row.sequence_id, f"sequence-{seq_id}", ".aem")


def _time_range_comment(start: datetime | None, end: datetime | None) -> str:
    """The bulk AEM's time range in words ("every confirmed attitude", "from T", "before T", "from T to T")."""
    if start is None and end is None:
        return "Time range: every confirmed attitude"
    if end is None:
        return f"Time range: reference epochs from {utc_text(start)}"
    if start is None:
        return f"Time range: reference epochs before {utc_text(end)}"
    return f"Time range: reference epochs from {utc_text(start)} to before {utc_text(end)}"


_SEGMENT_TIME = re.compile(r"^(START_TIME|STOP_TIME) = (\S+)$", re.MULTILINE)


def _overlap_comments(rows: list[ConfirmationRow], segments: list[str],
                      name_of: Callable[[int], str | None]) -> list[str]:
    """A warning for each pair of segments whose times overlap: one spacecraft has one attitude at a time,
    so two confirmed sequences over the same seconds mean one is another spacecraft's, or mis-timed."""
    spans = []
    for c, segment in zip(rows, segments):
        times = dict(_SEGMENT_TIME.findall(segment))
        start, stop = (datetime.fromisoformat(times[k]).replace(tzinfo=timezone.utc)  # TIME_SYSTEM = UTC
                       for k in ("START_TIME", "STOP_TIME"))
        spans.append((start, stop, c))
    spans.sort(key=lambda span: (span[0], span[1]))
    warnings = []
    for k, (start, stop, c) in enumerate(spans):
        for other_start, other_stop, other in spans[k + 1:]:
            if other_start > stop:
                break
            warnings.append(
                f"WARNING: the segments of sequences {name_of(c.seq_id)} (attitude {c.id}) and "
                f"{name_of(other.seq_id)} (attitude {other.id}) overlap in time, from {format_epoch(other_start)} to "
                f"{format_epoch(min(stop, other_stop))}: a spacecraft has one attitude at a time, so one of them "
                "is another spacecraft's or has wrong times")
    return warnings


def bulk_aem(ctx: AppContext, spacecraft: str, start: datetime | None, end: datetime | None) -> tuple[str, str]:
    """One AEM holding the attitudes of every confirmed sequence of ``spacecraft`` whose reference epoch
    lies in [start, end), oldest first, and its download name.

    Each segment is the stored AEM's segment byte for byte (what was rendered
    at confirmation); the message gets one new header, created now.
    """
    if start is not None and end is not None and end <= start:
        raise Invalid(f"the time range is empty: end {utc_text(end)} is not after start {utc_text(start)}",
                      location="query.end", message="must be after start")
    rows = [c for c in ctx.storage.current_confirmations(spacecraft, start, end) if c.aem_text]
    if not rows:
        span = f" from {utc_text(start) if start else 'the beginning'} to {utc_text(end) if end else 'now'}"
        raise NotFound(f"no confirmed attitude of spacecraft {spacecraft!r}{span}")
    segments = []
    for c in rows:
        text = c.aem_text
        at = text.find("\nMETA_START")
        segments.append(text[at + 1:].rstrip("\n"))
    version_line = rows[0].aem_text.split("\n", 1)[0]  # "CCSDS_AEM_VERS = 2.0", as the stored messages say
    created = datetime.now(timezone.utc)
    header = [version_line,
              *comment_lines([f"Confirmed attitudes of spacecraft {spacecraft}: {len(rows)} "
                              f"sequence{'s' * (len(rows) != 1)}, one segment each, as rendered at their "
                              "confirmation",
                              _time_range_comment(start, end),
                              # a sequence's id read only for a warning that names it
                              *_overlap_comments(rows, segments,
                                                 lambda seq_id: ctx.storage.get_sequence(seq_id).sequence_id)]),
              f"CREATION_DATE = {format_epoch(created)}", f"ORIGINATOR = {ORIGINATOR}"]
    text = "\n".join(header) + "\n\n" + "\n\n".join(segments) + "\n"
    stamp = "" if start is None else "-" + start.strftime("%Y%m%dT%H%M%S")
    return text, download_name(f"{spacecraft}{stamp}-attitudes", "attitudes", ".aem")
