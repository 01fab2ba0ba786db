"""Robust rotation between two snapshots of the same sky, many snapshot pairs at once.

Between two snapshots the satellite has turned, so the stars of snapshot
``a`` reappear in snapshot ``b`` rotated by one rotation ``R`` (``v_b = R
v_a`` for camera-frame unit vectors), while ghosts and hot pixels do not
follow it.  ``R`` is found by RANSAC:

1. *Hypotheses.*  A rotation preserves angles, so a pair of sources
   (a1, a2) of snapshot a can only be a pair of stars (b1, b2) of snapshot
   b if their chord lengths ``|a1 - a2|`` and ``|b1 - b2|`` agree within
   the position noise.  All agreeing (unordered pair of a) x (ordered pair
   of b) combinations are found at once by sorting the chords of b and
   searching the chords of a.  Each gives the rotation mapping a1 onto b1
   and the great circle a1-a2 onto b1-b2
   (:func:`app.attitude.rotation_from_pair`).
2. *Score.*  Every hypothesis rotates all sources of a; each contributes
   ``max(0, 1 - d^2 / g^2)`` where d is the chord to its nearest source of
   b (a truncated quadratic, MSAC: near misses count less than exact hits,
   which breaks ties between hypotheses with the same inlier count).
3. *Refine.*  The few best hypotheses of each pair are refined by Wahba's
   problem (SVD, :func:`wahba_rotation`) on mutual nearest neighbours
   within the fit gate; the refined one whose
   matches fit best wins and is refined once more (with three or four common stars a wrong
   hypothesis plus one chance match can tie in inlier count, never in fit).

The hypotheses of all snapshot pairs are found in a handful of numpy calls
(the pairs' chords sorted together); scoring and refinement, a few
arithmetic operations per source pair, are compiled loops over the
hypotheses (:func:`_scores`, :func:`_refine_links`), where numpy would pay
its call overhead for every small array.  Chords stand in for angles: they
are monotonic in the angle, accurate for small angles and need no arccos.

**Bounded work.**  Scoring costs (hypotheses) x (sources of a) x (sources
of b) per link, and the hypotheses grow with the fourth power of the
sources: 10 sources give at most ~200 per link, 64 random ones ~900 and a
regular grid of 64 up to 72,000, which took seconds and gigabytes.  So, as
the identification search caps its work, each link scores at most
``max_work // (n_a n_b)`` hypotheses (never fewer than ``min_hypotheses``),
those of the brightest sources first (a star is more often bright than a
ghost, and the seed, too, starts from the brightest stars).  Below the cap
nothing is dropped or reordered, so ordinary telemetry extracts exactly as
without it; and the scoring holds nothing but the scores in memory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scipy.special import gammaln

from app.attitude import rotation_from_pair
from app.compiled import njit, warm_up_with

#: Slot width separating the chords of different snapshot pairs in one
#: sorted array; chords are at most 2.
_SLOT = 10.0
#: Hypotheses expanded per link before the brightest are chosen, as a multiple of the link's cap
#: (bounds the memory of the expansion itself, which a regular grid would blow up).
_EXPANSION_FACTOR = 8


@dataclass(frozen=True, eq=False)
class PairRotations:
    """Result for L snapshot pairs (a, b)."""

    rotation: np.ndarray  # (L, 3, 3) v_b = R v_a; NaN where no rotation was found
    n_inliers: np.ndarray  # (L,) int, mutual nearest neighbours within the fit gate
    matches: np.ndarray  # (L, N) int: source of b matched to each source of a, -1 if none
    inlier_chord_sq: np.ndarray  # (n,) squared chords of all inliers of all valid pairs


def _pair_chords(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chords between all unordered pairs of points, per snapshot.

    ``v`` is (S, K, 3), NaN-padded; returns (S, P) chords (NaN for padding)
    and the (P,) index arrays i < j.
    """
    i, j = np.triu_indices(v.shape[1], 1)
    return np.linalg.norm(v[:, i] - v[:, j], axis=-1), i, j


def expand_ranges(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (k, i) with lo[k] <= i < hi[k], as two flat arrays, without a Python loop."""
    counts = hi - lo
    owner = np.repeat(np.arange(len(lo)), counts)
    position = np.arange(int(counts.sum())) + np.repeat(lo - (np.cumsum(counts) - counts), counts)
    return owner, position


def _hypotheses(chords: np.ndarray, pi: np.ndarray, pj: np.ndarray, links: np.ndarray,
                pair_tol: float, min_baseline: float, cap: np.ndarray | None = None):
    """The (link, a-pair, b-pair) combinations whose chords agree within ``pair_tol``.

    Points are indexed in order of brightness (``hypothesis_sources``), so a
    hypothesis' rank is the faintest of its four points.  With ``cap``
    ((L,) ints) a link keeps at most ``cap[l]`` hypotheses, the brightest
    (:func:`_brightest_first`); a link with no more than that keeps all, in
    the same order as without a cap.  Returns (link, a1, a2, b1, b2) index
    arrays, grouped by link.
    """
    n_links, n_pairs = len(links), chords.shape[1]
    # b side: both orientations of every pair; unusable chords are parked in
    # the link's slot above any real chord so they never match.
    chord_b = chords[links[:, 1]]
    chord_b = np.where(np.isfinite(chord_b), chord_b, 5.0)
    keys_b = np.concatenate([chord_b, chord_b], axis=1) + _SLOT * np.arange(n_links)[:, None]
    b1 = np.concatenate([pi, pj])
    b2 = np.concatenate([pj, pi])
    keys_b = keys_b.ravel()
    order_b = np.argsort(keys_b, kind="stable")
    sorted_b = keys_b[order_b]

    # a side: only pairs with a long enough baseline (a short pair fixes the
    # rotation about its own axis badly).
    chord_a = chords[links[:, 0]]
    usable = np.isfinite(chord_a) & (chord_a >= min_baseline)
    link_of_a, pair_of_a = np.nonzero(usable)
    keys_a = chord_a[link_of_a, pair_of_a] + _SLOT * link_of_a
    lo = np.searchsorted(sorted_b, keys_a - pair_tol, side="left")
    hi = np.searchsorted(sorted_b, keys_a + pair_tol, side="right")
    if cap is not None:
        # Expand only the a-pairs of the brightest points, up to a multiple of the cap per link.
        a_rank = np.maximum(pi[pair_of_a], pj[pair_of_a])
        hi = lo + _brightest_first(link_of_a, a_rank, hi - lo, _EXPANSION_FACTOR * cap)
    hyp_a, position = expand_ranges(lo, hi)
    flat_b = order_b[position]
    link = link_of_a[hyp_a]
    pa = pair_of_a[hyp_a]
    pb = flat_b % (2 * n_pairs)
    a1, a2, bb1, bb2 = pi[pa], pj[pa], b1[pb], b2[pb]
    if cap is not None:
        rank = np.maximum(np.maximum(a1, a2), np.maximum(bb1, bb2))
        keep = _brightest_first(link, rank, np.ones(len(link), dtype=int), cap).astype(bool)
        link, a1, a2, bb1, bb2 = link[keep], a1[keep], a2[keep], bb1[keep], bb2[keep]
    return link, a1, a2, bb1, bb2


def _brightest_first(group: np.ndarray, rank: np.ndarray, count: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """How many of each item's ``count`` to keep so that no group keeps more than ``cap[group]``.

    Items are taken in order of ``rank`` (lower first, ties in their given
    order), whole while they fit; the one that crosses the cap is cut short
    and the rest get 0.  A group whose total fits keeps everything.
    """
    if len(group) == 0 or np.all(np.bincount(group, count) <= cap[:group.max() + 1]):
        return count  # every group fits (ordinary telemetry): nothing to sort
    order = np.lexsort((np.arange(len(group)), rank, group))
    counts = count[order]
    ends = np.cumsum(counts)
    group_sorted = group[order]
    starts = np.r_[True, group_sorted[1:] != group_sorted[:-1]]
    before = np.maximum.accumulate(np.where(starts, ends - counts, 0))  # total of earlier groups
    taken_before = ends - counts - before  # this group's items ahead of this one
    kept = np.clip(cap[group_sorted] - taken_before, 0, counts)
    result = np.empty_like(count)
    result[order] = kept
    return result


def false_alarms(n_hypotheses, n_a, n_b, n_inliers, radius_sq, field_area) -> np.ndarray:
    """Expected number of hypotheses as good as the winner in unrelated point sets (a contrario).

    A hypothesis fixes two matches; each of the other ``n_a - 2`` rotated
    points of a lands by chance within ``r`` of one of the ``n_b`` points of
    b with probability ``p = n_b pi r^2 / area`` (r: the largest match
    residual).  The chance of ``k - 2`` such extra matches is at most
    ``C(n_a - 2, k - 2) p^(k - 2)``; times the number of hypotheses tried it
    is the expected count of equally good false alarms.  Three random
    matches within 5 px are common among 10 + 10 points; within 1 px, or
    four of them, they are not.
    """
    extra = np.maximum(np.asarray(n_inliers) - 2, 0)
    p = np.minimum(1.0, np.asarray(n_b) * np.pi * np.asarray(radius_sq) / field_area)
    log_binom = (gammaln(np.asarray(n_a) - 1.0) - gammaln(extra + 1.0)
                 - gammaln(np.maximum(np.asarray(n_a) - 2 - extra, 0) + 1.0))
    with np.errstate(divide="ignore"):
        return np.asarray(n_hypotheses) * np.exp(log_binom + extra * np.log(p))


@njit
def _scores(rotation, va_index, vb_index, vectors, score_gate):
    """(H,) truncated-quadratic score of each hypothesis: sum over a's sources of max(0, 1 - d^2 / g^2).

    Hypothesis h rotates the sources of snapshot ``va_index[h]`` by ``rotation[h]``; d is the chord to the
    nearest source of snapshot ``vb_index[h]``.  The nearest source has the largest dot product, and
    ``2 - 2 max(dot)`` is the smallest squared chord (2 - 2x rounds monotonically).  Zero padding rows
    rotate to 0, a dot of 0 and d^2 = 2: beyond every gate, they add nothing.
    """
    n = vectors.shape[1]
    gate_sq = score_gate * score_gate
    score = np.zeros(rotation.shape[0])
    for h in range(rotation.shape[0]):
        R = rotation[h]
        a = vectors[va_index[h]]
        b = vectors[vb_index[h]]
        total = 0.0
        for i in range(n):
            p0 = R[0, 0] * a[i, 0] + R[0, 1] * a[i, 1] + R[0, 2] * a[i, 2]
            p1 = R[1, 0] * a[i, 0] + R[1, 1] * a[i, 1] + R[1, 2] * a[i, 2]
            p2 = R[2, 0] * a[i, 0] + R[2, 1] * a[i, 1] + R[2, 2] * a[i, 2]
            best = -np.inf
            for j in range(n):
                best = max(best, p0 * b[j, 0] + p1 * b[j, 1] + p2 * b[j, 2])
            total += max(0.0, 1.0 - (2.0 - 2.0 * best) / gate_sq)
        score[h] = total
    return score


@njit
def _mutual_matches(rotation, va, vb, gate_sq):
    """Mutual nearest neighbours within the gate of ``rotation @ va[i]`` and ``vb[j]``.

    Returns (N,) the source of b matched to each source of a (-1: none) and (N,) the squared chord of each
    match (0 elsewhere).  Chords come as ``2 - 2 (R v_a).v_b``; zero padding rows are at 2 (a right angle),
    beyond every gate.  Ties go to the first source, as numpy's argmin gives them.
    """
    n_a, n_b = va.shape[0], vb.shape[0]
    d2 = np.empty((n_a, n_b))
    for i in range(n_a):
        p0 = rotation[0, 0] * va[i, 0] + rotation[0, 1] * va[i, 1] + rotation[0, 2] * va[i, 2]
        p1 = rotation[1, 0] * va[i, 0] + rotation[1, 1] * va[i, 1] + rotation[1, 2] * va[i, 2]
        p2 = rotation[2, 0] * va[i, 0] + rotation[2, 1] * va[i, 1] + rotation[2, 2] * va[i, 2]
        for j in range(n_b):
            d2[i, j] = 2.0 - 2.0 * (p0 * vb[j, 0] + p1 * vb[j, 1] + p2 * vb[j, 2])
    match = np.full(n_a, -1)
    match_sq = np.zeros(n_a)
    for i in range(n_a):
        j = np.argmin(d2[i])
        if np.argmin(d2[:, j]) == i and d2[i, j] < gate_sq:
            match[i] = j
            match_sq[i] = d2[i, j]
    return match, match_sq


@njit
def _refit(rotation, va, vb, gate_sq):
    """``rotation`` re-solved by Wahba's problem on its mutual matches within the gate (kept with fewer than
    two): :func:`wahba_rotation` of B = sum_i v_b(i) v_a(i)^T."""
    match, _ = _mutual_matches(rotation, va, vb, gate_sq)
    B = np.zeros((3, 3))
    for i in range(va.shape[0]):
        if match[i] >= 0:
            for r in range(3):
                for c in range(3):
                    B[r, c] += vb[match[i], r] * va[i, c]
    if np.sum(match >= 0) < 2:
        return rotation
    return wahba_rotation(B)


@njit
def wahba_rotation(B):
    """The rotation R minimising sum_i |b_i - R a_i|^2 from its attitude profile B = sum_i b_i a_i^T.

    With B = U S V^T, R = U diag(1, 1, det U V^T) V^T (:func:`app.attitude.solve_wahba`'s SVD method):
    where U V^T is a reflection, the axis of the smallest singular value is flipped.
    """
    U, _, Vt = np.linalg.svd(B)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        for r in range(3):
            for c in range(3):
                R[r, c] -= 2.0 * U[r, 2] * Vt[2, c]
    return R


@njit
def _refine_links(hypotheses, score, link, links, vectors, fit_gate, n_refine):
    """Each link's best rotation from its scored hypotheses (module docstring, step 3), and its matches.

    ``hypotheses`` (H, 3, 3) are grouped by ``link``; link l relates snapshot ``links[l, 0]`` to ``links[l, 1]``.
    The ``n_refine`` best scored of a link (the first on ties) are refined once (:func:`_refit`); the one
    whose mutual matches fit best (truncated quadratic sum_i max(0, 1 - d_i^2 / g^2)) wins, the first on
    ties, and is refined once more.  Returns (L, 3, 3) rotations (NaN for a link without hypotheses),
    (L, N) matches of the winner (-1: none) and (L, N) their squared chords (0 elsewhere).
    """
    n = vectors.shape[1]
    gate_sq = fit_gate * fit_gate
    n_links = links.shape[0]
    rotation = np.full((n_links, 3, 3), np.nan)
    matches = np.full((n_links, n), -1)
    match_sq = np.zeros((n_links, n))
    start = 0
    while start < link.shape[0]:
        lk = link[start]
        stop = start
        while stop < link.shape[0] and link[stop] == lk:
            stop += 1
        va, vb = vectors[links[lk, 0]], vectors[links[lk, 1]]
        taken = np.zeros(stop - start, dtype=np.bool_)
        best_fit, winner = -np.inf, np.empty((3, 3))
        for _ in range(min(n_refine, stop - start)):
            pick = -1  # the best score not yet refined, the first on ties
            for h in range(stop - start):
                if not taken[h] and (pick < 0 or score[start + h] > score[start + pick]):
                    pick = h
            taken[pick] = True
            r = _refit(hypotheses[start + pick], va, vb, gate_sq)
            match, d2 = _mutual_matches(r, va, vb, gate_sq)
            fit = 0.0
            for i in range(n):
                if match[i] >= 0:
                    fit += 1.0 - d2[i] / gate_sq
            if fit > best_fit:
                best_fit, winner = fit, r
        rotation[lk] = _refit(winner, va, vb, gate_sq)
        matches[lk], match_sq[lk] = _mutual_matches(rotation[lk], va, vb, gate_sq)
        start = stop
    return rotation, matches, match_sq


def estimate_pair_rotations(vectors: np.ndarray, hypothesis_sources: np.ndarray, links: np.ndarray, *,
                            pair_tol: float, min_baseline: float, score_gate: float,
                            fit_gate: float, min_inliers: int, field_area: float, min_radius: float,
                            max_false_alarms: float = 0.1, n_refine: int = 4,
                            max_work: int | None = None, min_hypotheses: int = 64) -> PairRotations:
    """Robust rotation a -> b for every snapshot pair ``links[l] = (a, b)``.

    ``vectors`` (S, N, 3) camera-frame unit vectors, zero-padded;
    ``hypothesis_sources`` (S, K) indices into the N sources (-1 padding) of
    those allowed to generate hypotheses (the K brightest: brightness is
    unreliable but a star is more often bright than a ghost, and K bounds
    the (K^2)^2 growth of the pair combinations).  Tolerances are chords
    (radians for small angles).  A pair gets a rotation only with at least
    ``min_inliers`` mutual matches (two points always fit a pair hypothesis)
    and when chance explains them poorly: :func:`false_alarms` at most
    ``max_false_alarms`` (``field_area`` is the sensor's area in squared
    chords, ``min_radius`` the smallest match radius credited).  With
    ``max_work`` a link scores at most ``max(min_hypotheses, max_work //
    (n_a n_b))`` hypotheses, the brightest (module docstring).
    """
    links = np.asarray(links, dtype=int).reshape(-1, 2)
    n_links = len(links)
    rotation = np.full((n_links, 3, 3), np.nan)
    n_inliers = np.zeros(n_links, dtype=int)
    if n_links == 0:
        return PairRotations(rotation, n_inliers, np.full((n_links, vectors.shape[1]), -1), np.zeros(0))

    # hypotheses must not come from padding: give it NaN chords
    padded = np.concatenate([vectors, np.full((vectors.shape[0], 1, 3), np.nan)], axis=1)
    hyp_vectors = np.take_along_axis(padded, np.where(hypothesis_sources < 0, vectors.shape[1],
                                                      hypothesis_sources)[..., None], axis=1)
    chords, pi, pj = _pair_chords(hyp_vectors)
    n_sources = (np.abs(vectors).sum(axis=2) > 0).sum(axis=1)  # zero rows are padding
    cap = None
    if max_work is not None:
        cost = np.maximum(1, n_sources[links[:, 0]] * n_sources[links[:, 1]])
        cap = np.maximum(min_hypotheses, max_work // cost)
    link, a1, a2, b1, b2 = _hypotheses(chords, pi, pj, links, pair_tol, min_baseline, cap)
    if len(link) == 0:
        return PairRotations(rotation, n_inliers, np.full((n_links, vectors.shape[1]), -1), np.zeros(0))

    sa, sb = links[link, 0], links[link, 1]
    hyp_r = rotation_from_pair(hyp_vectors[sb, b1], hyp_vectors[sb, b2],
                               hyp_vectors[sa, a1], hyp_vectors[sa, a2])
    score = _scores(hyp_r, sa, sb, vectors, score_gate)
    # among a link's refined candidates the one whose matches fit best wins (truncated quadratic again):
    # a chance match that made a wrong hypothesis tie in inliers leaves a visibly larger residual
    refined, match, match_sq = _refine_links(hyp_r, score, link, links, vectors, fit_gate, n_refine)
    found = np.flatnonzero(np.isfinite(refined[:, 0, 0]))
    count = (match[found] >= 0).sum(axis=1)
    radius_sq = np.maximum(match_sq[found].max(axis=1), min_radius**2)
    n_hyp = np.bincount(link, minlength=n_links)[found]
    nfa = false_alarms(n_hyp, n_sources[links[found, 0]], n_sources[links[found, 1]], count, radius_sq,
                       field_area)
    ok = found[(count >= min_inliers) & (nfa <= max_false_alarms)]
    rotation[ok] = refined[ok]
    n_inliers[found] = count
    matches = np.full((n_links, vectors.shape[1]), -1, dtype=int)
    matches[ok] = match[ok]
    inlier_sq = match_sq[ok][match[ok] >= 0]
    return PairRotations(rotation, n_inliers, matches, inlier_sq)


@warm_up_with
def _warm_up_motion() -> None:
    """Compile :func:`_scores` and :func:`_refine_links` for the arrays :func:`estimate_pair_rotations` passes."""
    vectors = np.array([[[0.0, 0.0, 1.0], [0.0, 0.01, 1.0]], [[0.0, 0.0, 1.0], [0.01, 0.0, 1.0]]])
    _scores(np.eye(3)[None], np.array([0]), np.array([1]), vectors, 0.01)
    _refine_links(np.eye(3)[None], np.ones(1), np.array([0]), np.array([[0, 1]]), vectors, 0.01, 4)
