"""A spacecraft's attitude over time, read from the archive: what operators look at as a picture.

One entry per stored sequence of the spacecraft whose first snapshot lies in the range asked, oldest
first: its time span (first to last snapshot), its status and who gave it, and the attitude it has --
the current confirmation's candidate, else rank 1 of the newest search when that search identified the
sequence or found it ambiguous (no attitude for no match, "no valid attitude" or no search yet).  The
attitude is the one at the reference snapshot's time (the *epoch*), with its 1-sigma and the fitted
body rate.

Three things are flagged between entries (:func:`find_flags`):

* **gap**: no sequence at all for longer than ``gap_s`` seconds (from the furthest end so far to the next
  start);
* **overlap**: a sequence that starts before an earlier one ends (the same pass uploaded twice, a clock
  error);
* **jump**: two consecutive trusted attitudes (identified or confirmed; an ambiguous rank 1 may be the
  wrong star field and would flag noise), with no gap between them, that differ by more than the body
  rate explains.  The earlier attitude ``R_a`` is carried to the later epoch by its fitted rate ``w``
  (``R(t) = exp(-[w]x dt) R_a``, :func:`app.attitude.rotations.propagate`), and the rotation left over,
  ``e = log(R_b R(t)^T)`` in camera axes, is compared with what the uncertainties allow on each axis:
  ``var_k = s_a,k^2 + s_b,k^2 + (s_w,k dt)^2`` with ``s`` the attitudes' 1-sigma (cross-boresight on x
  and y, roll on z) and ``s_w`` the rate's.  A jump is ``chi2 = sum e_k^2 / var_k`` above
  :data:`JUMP_CHI2` (3 degrees of freedom, chance 1 in 1,000).  When the earlier sequence has no fitted
  rate the later one's carries it back; when neither has one (single snapshots) the pair is not judged.

A request reads at most :data:`MAX_POINTS` sequences: a range holding more is refused, saying how many it
holds, rather than drawn in part (flags between a part's ends would be wrong).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from app.attitude.rotations import rotation_from_rotvec, rotvec_from_rotation
from app.storage import ConfirmationRow, RejectionRow, SearchRow, SequenceRow
from app.timefmt import parse_utc, utc_text
from app.workflow.archive import stored_telemetry
from app.workflow.context import AppContext
from app.workflow.documents import CandidateDocument, TimelineDocument
from app.workflow.errors import Invalid, NotFound

#: Most sequences one timeline request reads: each one's telemetry is parsed again for its snapshots' times
#: (about 4 ms of CPU a sequence with its search: 500 took 1.9 s of CPU on the shared development machine).
MAX_POINTS = 500
#: Sequences read when the request does not say.
DEFAULT_POINTS = 200
#: Seconds without any sequence that make a gap, unless the request says otherwise.
DEFAULT_GAP_S = 600.0
#: chi-square of 3 degrees of freedom exceeded by chance once in 1,000: above it, a jump.
JUMP_CHI2 = 16.266
#: Statuses whose attitude is trusted enough to judge jumps by.
TRUSTED = ("identified", "confirmed")
ARCSEC = math.pi / (180.0 * 3600.0)


@dataclass(frozen=True, eq=False)
class PlottedAttitude:
    """A candidate's attitude at its epoch: the rotation (ICRS -> camera), RA/Dec/roll in degrees, the
    1-sigma about each cross-boresight axis and in roll (radians, camera axes; None: not estimated), and
    the fitted body rate with its 1-sigma per axis (rad/s, camera axes; None: no sequence fit)."""

    rank: int
    rotation: np.ndarray
    ra_deg: float
    dec_deg: float
    roll_deg: float
    sigma_cross_rad: float | None
    sigma_roll_rad: float | None
    rate_rad_s: np.ndarray | None
    rate_sigma_rad_s: np.ndarray | None

    @classmethod
    def of(cls, candidate: CandidateDocument) -> "PlottedAttitude":
        fit = candidate.sequence_fit
        cross, roll = candidate.sigma_cross_boresight_arcsec, candidate.sigma_roll_arcsec
        return cls(rank=candidate.rank, rotation=candidate.rotation, ra_deg=candidate.ra_deg,
                   dec_deg=candidate.dec_deg, roll_deg=candidate.roll_deg,
                   sigma_cross_rad=None if cross is None else cross * ARCSEC,
                   sigma_roll_rad=None if roll is None else roll * ARCSEC,
                   rate_rad_s=None if fit is None else fit.rate_rad_s,
                   rate_sigma_rad_s=None if fit is None else np.radians(np.array(fit.rate_sigma_deg_s, dtype=float)))

    @property
    def axis_sigma_rad(self) -> np.ndarray | None:
        """1-sigma about the camera's x, y, z axes (None when not estimated)."""
        if self.sigma_cross_rad is None or self.sigma_roll_rad is None:
            return None
        return np.array([self.sigma_cross_rad, self.sigma_cross_rad, self.sigma_roll_rad])

    def radec_roll_sigma_deg(self) -> tuple[float | None, float | None, float | None]:
        """1-sigma of RA, Dec and roll, degrees, from the camera-axis sigmas (first order).

        The boresight moves by ``s`` (cross-boresight, each axis) on the sky: Dec by ``s``, RA by
        ``s / cos(Dec)`` (None within 1e-9 of a pole).  Roll is a position angle from north, and north turns
        by ``dRA sin(Dec)`` as the boresight moves east, so ``s_roll^2 = s_z^2 + (s tan(Dec))^2``.
        """
        if self.sigma_cross_rad is None or self.sigma_roll_rad is None:
            return None, None, None
        s, cos_dec = self.sigma_cross_rad, math.cos(math.radians(self.dec_deg))
        ra = None if cos_dec < 1e-9 else math.degrees(s / cos_dec)
        roll = math.degrees(math.hypot(self.sigma_roll_rad, s * math.tan(math.radians(self.dec_deg)))) \
            if cos_dec >= 1e-9 else None
        return ra, math.degrees(s), roll

    def rate_norm_deg_s(self) -> tuple[float | None, float | None]:
        """``|w|`` and its 1-sigma, deg/s: ``s_|w| = sqrt(sum (w_k s_k)^2) / |w|`` (first order), or
        ``sqrt(sum s_k^2 / 3)`` (one axis's, on average) for a rate of exactly zero."""
        if self.rate_rad_s is None:
            return None, None
        w, s = self.rate_rad_s, self.rate_sigma_rad_s
        norm = float(np.linalg.norm(w))
        sigma = float(np.linalg.norm(w * s)) / norm if norm > 0 else float(np.sqrt(np.mean(s ** 2)))
        return math.degrees(norm), math.degrees(sigma)


@dataclass(frozen=True, eq=False)
class TimelineEntry:
    """One sequence on the timeline (see the module docstring for where its attitude comes from)."""

    seq_id: int
    sequence_id: str | None
    filename: str | None
    status: str
    start: datetime
    end: datetime
    epoch: datetime
    n_snapshots: int
    search_id: int | None
    method: str | None
    by: str | None
    verdict_at: datetime | None
    reason: str | None
    attitude: PlottedAttitude | None


@dataclass(frozen=True)
class TimelineFlag:
    """A gap, overlap or jump between entries ``earlier`` and ``later`` (positions in the timeline).

    ``seconds``: the gap's or the overlap's length, or the time between a jump's epochs; a jump also has the
    rotation left over (``angle_rad``), the 1-sigma the uncertainties allow it (``sigma_rad``: the root sum
    of the three axes' variances) and its ``chi2``.
    """

    kind: str
    earlier: int
    later: int
    seconds: float
    angle_rad: float | None = None
    sigma_rad: float | None = None
    chi2: float | None = None


@dataclass(frozen=True, eq=False)
class Timeline:
    spacecraft: str
    start: datetime | None
    end: datetime | None
    limit: int
    total: int
    gap_s: float
    entries: tuple[TimelineEntry, ...]
    flags: tuple[TimelineFlag, ...]


# ---------------------------------------------------------------------------
# Gaps, overlaps and jumps (pure)
# ---------------------------------------------------------------------------

def coverage_flags(start_s: np.ndarray, end_s: np.ndarray, gap_s: float) -> list[TimelineFlag]:
    """Gaps and overlaps of time spans sorted by start (seconds on any common scale).

    Each span ``j`` is compared with the *reach* before it, the furthest end of spans ``0..j-1`` (held by
    the earlier span named in the flag): ``start_j - reach > gap_s`` is a gap of that length, ``start_j <
    reach`` an overlap of ``min(reach, end_j) - start_j``.  Spans that only touch neither overlap nor gap.
    """
    start_s, end_s = np.asarray(start_s, dtype=float), np.asarray(end_s, dtype=float)
    if len(start_s) < 2:
        return []
    reach = np.maximum.accumulate(end_s)
    index = np.arange(len(end_s))
    holder = np.maximum.accumulate(np.where(end_s >= reach, index, 0))
    flags = []
    for j in range(1, len(start_s)):
        before, who = reach[j - 1], int(holder[j - 1])
        if start_s[j] - before > gap_s:
            flags.append(TimelineFlag("gap", who, j, float(start_s[j] - before)))
        elif start_s[j] < before:
            flags.append(TimelineFlag("overlap", who, j, float(min(before, end_s[j]) - start_s[j])))
    return flags


def unexplained_rotation(R_a: np.ndarray, R_b: np.ndarray, dt_s: float, rate_rad_s: np.ndarray) -> np.ndarray:
    """``log(R_b (exp(-[w]x dt) R_a)^T)``: the rotation vector (camera axes, radians) from attitude ``R_a``
    carried ``dt_s`` seconds by the body rate ``w`` to attitude ``R_b``; zero when the rate explains it all."""
    carried = rotation_from_rotvec(-np.asarray(rate_rad_s, dtype=float) * dt_s) @ np.asarray(R_a)  # as propagate()
    return rotvec_from_rotation(np.asarray(R_b) @ carried.T)


def jump_chi2(rotation: np.ndarray, dt_s: float, sigma_a: np.ndarray, sigma_b: np.ndarray,
              rate_sigma: np.ndarray) -> tuple[float, float]:
    """``(chi2, sigma)`` of a left-over rotation (:func:`unexplained_rotation`): ``chi2 = sum e_k^2 / var_k``
    with ``var_k = s_a,k^2 + s_b,k^2 + (s_w,k dt)^2`` per camera axis, and ``sigma = sqrt(sum var_k)``."""
    var = np.asarray(sigma_a) ** 2 + np.asarray(sigma_b) ** 2 + (np.asarray(rate_sigma) * dt_s) ** 2
    return float(np.sum(np.asarray(rotation) ** 2 / var)), float(np.sqrt(np.sum(var)))


def judge_jump(a: PlottedAttitude, b: PlottedAttitude, dt_s: float) -> tuple[float, float, float] | None:
    """``(angle, sigma, chi2)`` of attitude ``b``, ``dt_s`` seconds after ``a``, against ``a`` carried by the
    body rate (``a``'s, else ``b``'s carried back); None when neither has a rate or a sigma is missing."""
    if a.axis_sigma_rad is None or b.axis_sigma_rad is None:
        return None
    if a.rate_rad_s is not None:
        left, rate_sigma = unexplained_rotation(a.rotation, b.rotation, dt_s, a.rate_rad_s), a.rate_sigma_rad_s
    elif b.rate_rad_s is not None:
        left, rate_sigma = unexplained_rotation(b.rotation, a.rotation, -dt_s, b.rate_rad_s), b.rate_sigma_rad_s
    else:
        return None
    chi2, sigma = jump_chi2(left, dt_s, a.axis_sigma_rad, b.axis_sigma_rad, rate_sigma)
    return float(np.linalg.norm(left)), sigma, chi2


def find_flags(entries: list[TimelineEntry] | tuple[TimelineEntry, ...], gap_s: float) -> list[TimelineFlag]:
    """The gaps, overlaps and jumps of ``entries`` (sorted by start), ordered by the later entry."""
    if not entries:
        return []
    t0 = entries[0].start
    start_s = np.array([(e.start - t0).total_seconds() for e in entries])
    end_s = np.array([(e.end - t0).total_seconds() for e in entries])
    flags = coverage_flags(start_s, end_s, gap_s)
    gap_before = np.zeros(len(entries) + 1, dtype=int)  # gap_before[j]: gaps ending at or before entry j
    for f in flags:
        if f.kind == "gap":
            gap_before[f.later + 1:] += 1
    trusted = sorted((i for i, e in enumerate(entries) if e.attitude is not None and e.status in TRUSTED),
                     key=lambda i: (entries[i].epoch, i))
    for i, j in zip(trusted, trusted[1:]):
        if gap_before[max(i, j) + 1] != gap_before[min(i, j) + 1]:
            continue  # across a gap the attitude need not follow the rate
        dt = (entries[j].epoch - entries[i].epoch).total_seconds()
        judged = judge_jump(entries[i].attitude, entries[j].attitude, dt)
        if judged is not None and judged[2] > JUMP_CHI2:
            flags.append(TimelineFlag("jump", i, j, dt, angle_rad=judged[0], sigma_rad=judged[1], chi2=judged[2]))
    return sorted(flags, key=lambda f: (f.later, f.kind))


def flag_text(flag: TimelineFlag, entries: list[TimelineEntry] | tuple[TimelineEntry, ...]) -> str:
    """The operator's sentence about a flag, naming both sequences by archive id."""
    a, b = (f"#{entries[k].seq_id}" + (f" {entries[k].sequence_id}" if entries[k].sequence_id else "")
            for k in (flag.earlier, flag.later))
    if flag.kind == "gap":
        return f"gap: no sequence for {_duration(flag.seconds)} between {a} and {b}"
    if flag.kind == "overlap":
        return f"overlap: {b} starts {_duration(flag.seconds)} before {a} ends"
    return (f"jump: {b} is {math.degrees(flag.angle_rad):.4g} deg from {a}'s attitude carried "
            f"{_duration(abs(flag.seconds))} by the body rate, {_times_sigma(flag)} its 1-sigma of "
            f"{math.degrees(flag.sigma_rad):.2g} deg")


def _times_sigma(flag: TimelineFlag) -> str:
    """How far beyond its uncertainty a jump is, in words an operator reads at a glance."""
    ratio = flag.angle_rad / flag.sigma_rad if flag.sigma_rad else math.inf
    return "far beyond" if not math.isfinite(ratio) or ratio >= 1000 else f"{ratio:.3g} times"


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.3g} s"
    if seconds < 7200:
        return f"{seconds / 60:.3g} min"
    if seconds < 3 * 86400:
        return f"{seconds / 3600:.3g} h"
    if seconds < 730 * 86400:
        return f"{seconds / 86400:.3g} days"
    return f"{seconds / (365.25 * 86400):.3g} years"


# ---------------------------------------------------------------------------
# From the archive
# ---------------------------------------------------------------------------

def timeline_entry(ctx: AppContext, row: SequenceRow, search: SearchRow | None,
                   verdict: ConfirmationRow | RejectionRow | None) -> TimelineEntry:
    """The entry of a stored sequence (``row`` with its raw text), its newest search and current verdict.

    The snapshots' times come from the telemetry parsed again (the sequence cache's when it holds it): 1-3 ms
    a sequence, most of a timeline's time.
    """
    cached = ctx.cache.get(row.id)
    times = [s.time for s in (stored_telemetry(row) if cached is None else cached.sequence).snapshots]
    # The members read from the stored search, not the whole SearchResult: its pattern and every candidate's
    # matches cost a millisecond a sequence to validate, as much again as the rest of the entry.
    result = None if search is None else search.result
    epoch = times[0] if result is None else parse_utc(result["reference_time"])
    attitude = by = verdict_at = reason = None
    if isinstance(verdict, ConfirmationRow):
        attitude = PlottedAttitude.of(CandidateDocument.model_validate(verdict.candidate))
        epoch, by, verdict_at = verdict.epoch or epoch, verdict.operator, verdict.confirmed_at
    elif isinstance(verdict, RejectionRow):
        by, verdict_at, reason = verdict.operator, verdict.rejected_at, verdict.reason
    elif result is not None and result["status"] in ("identified", "ambiguous"):
        first = next((c for c in result["candidates"] if c["rank"] == 1), None)
        attitude = None if first is None else PlottedAttitude.of(CandidateDocument.model_validate(first))
    return TimelineEntry(seq_id=row.id, sequence_id=row.sequence_id, filename=row.filename, status=row.status,
                         start=times[0], end=times[-1], epoch=epoch, n_snapshots=len(times),
                         search_id=None if search is None else search.id,
                         method=None if search is None else search.method, by=by, verdict_at=verdict_at,
                         reason=reason, attitude=attitude)


def build_timeline(ctx: AppContext, spacecraft: str, start: datetime | None, end: datetime | None,
                   limit: int = DEFAULT_POINTS, gap_s: float = DEFAULT_GAP_S) -> Timeline:
    """The timeline of ``spacecraft``'s sequences starting in [start, end); without either bound, its newest
    ``limit`` sequences.  Refused (Invalid) for an empty range, a limit outside 1..MAX_POINTS, a gap that is
    not a positive number of seconds, or a bounded range holding more than ``limit`` sequences; NotFound for
    a spacecraft the archive has no sequence of."""
    if not 1 <= limit <= MAX_POINTS:
        raise Invalid(f"limit must be 1 to {MAX_POINTS}, not {limit}", location="query.limit",
                      message=f"must be 1 to {MAX_POINTS}")
    if not (math.isfinite(gap_s) and gap_s > 0):
        raise Invalid(f"gap_s must be a positive number of seconds, not {gap_s}", location="query.gap_s",
                      message="must be a positive number of seconds")
    if start is not None and end is not None and end <= start:
        raise Invalid(f"the time range is empty: end {utc_text(end)} is not after start {utc_text(start)}",
                      location="query.end", message="must be after start")
    rows, total = ctx.storage.timeline_rows(spacecraft, start, end, limit)
    if total > limit and (start is not None or end is not None):
        raise Invalid(f"the range holds {total} sequences of {spacecraft!r}, more than the limit of {limit}: narrow "
                      f"it (or raise limit, at most {MAX_POINTS})", location="query",
                      message=f"{total} sequences in the range, limit {limit}")
    if total == 0 and spacecraft not in {name for name, _ in ctx.storage.spacecraft_names()}:
        raise NotFound(f"the archive has no sequence of spacecraft {spacecraft!r}")
    entries = tuple(timeline_entry(ctx, *r) for r in rows)
    return Timeline(spacecraft=spacecraft, start=start, end=end, limit=limit, total=total, gap_s=gap_s,
                    entries=entries, flags=tuple(find_flags(entries, gap_s)))


def spacecraft_timeline(ctx: AppContext, spacecraft: str, start: datetime | None, end: datetime | None,
                        limit: int = DEFAULT_POINTS, gap_s: float = DEFAULT_GAP_S) -> TimelineDocument:
    """:func:`build_timeline` as the API answers it."""
    timeline = build_timeline(ctx, spacecraft, start, end, limit, gap_s)
    return TimelineDocument.of(timeline, [flag_text(f, timeline.entries) for f in timeline.flags])
