"""The operator's review of a sequence: each candidate's verdict and the sequence's own.

A candidate is *credible* when it is the credible best: rank 1 of a search
whose status is ``identified`` (identification's own test: at most
``identified_probability`` likely by chance and no rival) on the pattern as
it is now.  Anything else can still be confirmed, but only with a second,
explicit step and a reason that goes into the audit record
(:func:`app.workflow.confirm.record_confirmation`); :func:`candidate_verdicts`
says why each candidate needs it, in the operator's terms.

The sequence's verdict is its current confirmation or rejection ("no valid
attitude"); :func:`review` returns both with the audit trail of every verdict
ever given.
"""

from __future__ import annotations

import math

import numpy as np

from app.identification import SearchOptions
from app.identification.engine import is_rival
from app.storage import ConfirmationRow
from app.timefmt import utc_text
from app.workflow.archive import current_pattern_version, require_sequence
from app.workflow.context import AppContext
from app.workflow.documents import (AttitudeDocument, AuditEntry, CandidateDocument, CandidateVerdict,
                                    RejectionDocument, ReviewDocument, SearchResult)

#: Fewer matched stars than this is "few matches" (FUSE's min_mch asks 4: with 3, any three stars
#: fit some triangle of the catalogue).
MIN_CREDIBLE_MATCHES = 4


def _angle_deg(a: CandidateDocument, b: CandidateDocument) -> float:
    """Rotation angle between two candidates' attitudes, degrees.

    From the Frobenius distance, ``|Ra - Rb| = 2 sqrt(2) sin(angle / 2)``, which stays exact near zero
    where the trace formula's arccos loses half the digits.
    """
    distance = float(np.linalg.norm(a.rotation - b.rotation))
    return float(np.degrees(2.0 * np.arcsin(min(1.0, distance / (2.0 * np.sqrt(2.0))))))


def _rivals(candidate: CandidateDocument, others: list[CandidateDocument], options: SearchOptions
            ) -> list[CandidateDocument]:
    """The other candidates that compete with ``candidate`` as identification's classifier judges them."""
    if candidate.rms_arcsec is None:
        return []
    return [o for o in others if o.rms_arcsec is not None and is_rival(o, candidate, options)]


def candidate_verdicts(result: SearchResult, current_version: int | None,
                       options: SearchOptions | None = None) -> list[CandidateVerdict]:
    """Each candidate's verdict: credible or not, and why not (see the module docstring)."""
    options = options or SearchOptions()
    candidates = result.candidates
    if not candidates:
        return []
    best = min(candidates, key=lambda c: c.rank)
    n_points = len(result.pattern)
    stale = result.pattern_version != current_version
    verdicts = []
    for c in candidates:
        # Chance must not explain it, or it must explain every point (tracking's two-point patterns): a
        # search's status alone is not trusted with what an operator confirms in one click.
        beyond_chance = (c.false_match_probability <= options.identified_probability
                         or c.n_matched == n_points)
        credible = c.rank == best.rank and result.status == "identified" and not stale and beyond_chance
        reasons: list[str] = []
        if not credible:
            if stale:
                reasons.append(f"stale: the pattern changed since this search (searched version "
                               f"{result.pattern_version}, now version {current_version}); search again")
            if result.status == "no_match":
                reasons.append(f"the search found no match: no candidate is at most "
                               f"{options.no_match_probability:g} likely to be chance")
            if c.rank != best.rank:
                reasons.append(f"not the best candidate: rank {best.rank} matches {best.n_matched} of {n_points} "
                               f"points, false-match probability {best.false_match_probability:.2g}")
            if c.false_match_probability > options.identified_probability:
                reasons.append(f"false-match probability {c.false_match_probability:.2g} is above the "
                               f"'identified' threshold {options.identified_probability:g}")
            if c.n_matched < MIN_CREDIBLE_MATCHES or 2 * c.n_matched < n_points:
                reasons.append(f"few matches: {c.n_matched} of {n_points} pattern points")
            if c.rank == best.rank and result.status == "ambiguous":
                rivals = _rivals(c, [o for o in candidates if o is not c], options)
                for o in rivals[:3]:
                    reasons.append(f"rival: rank {o.rank} fits almost as well (false-match probability "
                                   f"{o.false_match_probability:.2g}, RMS {o.rms_arcsec:.0f}″ against "
                                   f"{c.rms_arcsec:.0f}″)")
                if not rivals and len(reasons) == 0:
                    reasons.append("the search is ambiguous: an operator must decide")
            if not reasons:  # never leave "not credible" unexplained
                reasons.append(f"the search's status is {result.status.replace('_', ' ')}")
        ratio = c.false_match_probability / max(best.false_match_probability, 1e-300)
        verdicts.append(CandidateVerdict(
            rank=c.rank, credible=credible, reasons=reasons,
            deviation_gap_arcsec=round(c.deviation_arcsec - best.deviation_arcsec, 1),
            odds_vs_best=round(math.log10(ratio), 1) if ratio > 0 else None,
            separation_from_best_deg=round(_angle_deg(c, best), 3)))
    return verdicts


def review(ctx: AppContext, seq_id: int) -> ReviewDocument:
    """The candidates' verdicts of the latest search, the sequence's current verdict and its audit trail."""
    row = require_sequence(ctx, seq_id)
    search = ctx.storage.latest_search(seq_id)
    version = current_pattern_version(ctx, seq_id)
    result = SearchResult.model_validate(search.result) if search is not None else None
    verdict = ctx.storage.current_verdict(seq_id)
    confirmations = ctx.storage.confirmation_history(seq_id)
    rejections = ctx.storage.rejection_history(seq_id)
    audit = [AuditEntry(kind="confirmed", id=c.id, operator=c.operator, at=utc_text(c.confirmed_at), rank=c.rank,
                        search_id=c.search_id, reason=c.override_reason, comment=c.comment, current=c.is_current)
             for c in confirmations]
    audit += [AuditEntry(kind="rejected", id=r.id, operator=r.operator, at=utc_text(r.rejected_at),
                         search_id=r.search_id, reason=r.reason, current=r.is_current) for r in rejections]
    audit.sort(key=lambda e: e.at)
    return ReviewDocument(
        sequence=seq_id, status=row.status, search_id=search.id if search else None,
        search_status=result.status if result else None, method=result.method if result else None,
        search_pattern_version=result.pattern_version if result else None, pattern_version=version,
        stale=result is not None and result.pattern_version != version,
        identified_probability=SearchOptions().identified_probability,
        candidates=candidate_verdicts(result, version) if result else [],
        confirmation=AttitudeDocument.of(verdict, row) if isinstance(verdict, ConfirmationRow) else None,
        rejection=RejectionDocument.of(verdict, row) if verdict is not None
        and not isinstance(verdict, ConfirmationRow) else None,
        audit=audit)
