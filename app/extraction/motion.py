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
   problem (:func:`wahba_rotations`) on mutual nearest neighbours within
   the fit gate; the refined one whose
   matches fit best wins and is refined once more (with three or four common stars a wrong
   hypothesis plus one chance match can tie in inlier count, never in fit).

Everything is done for all snapshot pairs at once, no Python loop over
hypotheses or pairs: the hypotheses in a handful of numpy calls (the
pairs' chords sorted together); the scores, the mutual matches and the
Wahba fits, a few arithmetic operations per source pair, in compiled loops
over the hypotheses (:func:`_scores`, :func:`_mutual_matches`,
:func:`wahba_rotations`), where numpy made and scanned (hypotheses x
sources x sources) arrays of chords and paid its overhead per 3x3 SVD.
Chords stand in for angles: they are monotonic in the angle, accurate for
small angles and need no arccos.

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

import functools
from dataclasses import dataclass

import numpy as np

from scipy.special import gammaln

from app.attitude import rotation_from_pair
from app.attitude.rotations import wahba_rotation
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
    i, j = _pairs_of(v.shape[1])
    d = np.take(v, i, axis=1) - np.take(v, j, axis=1)
    # numpy's norm, the same numbers, without its reduction over an axis of three (most of its time)
    return np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]), i, j


@functools.lru_cache(maxsize=8)
def _pairs_of(k: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.triu_indices(k, 1)``, made once per k (its cost is most of :func:`_pair_chords` for 20 points)."""
    i, j = np.triu_indices(k, 1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


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
def _mutual_matches(rotation, va_index, vb_index, vectors, gate_sq):
    """Mutual nearest neighbours within the gate of ``rotation[h] @ v_a`` and ``v_b``, for each hypothesis h
    relating snapshot ``va_index[h]`` to ``vb_index[h]``.

    Returns (H, N) the source of b matched to each source of a (-1: none), (H, N) the squared chord of each
    match (0 elsewhere) and (H, 3, 3) the attitude profile of the matches, B = sum v_b v_a^T (Wahba's
    problem: :func:`wahba_rotations`).  Chords come as ``2 - 2 (R v_a).v_b``; zero padding rows are at 2
    (a right angle), beyond every gate.  Ties go to the first source, as numpy's argmin gives them.
    """
    n = vectors.shape[1]
    match = np.full((rotation.shape[0], n), -1)
    match_sq = np.zeros((rotation.shape[0], n))
    profiles = np.zeros((rotation.shape[0], 3, 3))
    d2 = np.empty((n, n))
    for h in range(rotation.shape[0]):
        R, va, vb = rotation[h], vectors[va_index[h]], vectors[vb_index[h]]
        for i in range(n):
            p0 = R[0, 0] * va[i, 0] + R[0, 1] * va[i, 1] + R[0, 2] * va[i, 2]
            p1 = R[1, 0] * va[i, 0] + R[1, 1] * va[i, 1] + R[1, 2] * va[i, 2]
            p2 = R[2, 0] * va[i, 0] + R[2, 1] * va[i, 1] + R[2, 2] * va[i, 2]
            for j in range(n):
                d2[i, j] = 2.0 - 2.0 * (p0 * vb[j, 0] + p1 * vb[j, 1] + p2 * vb[j, 2])
        for i in range(n):
            j = 0  # a's nearest in b
            for k in range(1, n):
                if d2[i, k] < d2[i, j]:
                    j = k
            back = 0  # that one's nearest in a
            for k in range(1, n):
                if d2[k, j] < d2[back, j]:
                    back = k
            if back == i and d2[i, j] < gate_sq:
                match[h, i] = j
                match_sq[h, i] = d2[i, j]
                for r in range(3):
                    for c in range(3):
                        profiles[h, r, c] += vb[j, r] * va[i, c]
    return match, match_sq, profiles


def _refit(rotation: np.ndarray, va_index: np.ndarray, vb_index: np.ndarray, vectors: np.ndarray,
           gate: float) -> np.ndarray:
    """One Wahba re-solve of each rotation on its mutual matches within the gate (kept with fewer than two)."""
    match, _, profiles = _mutual_matches(rotation, va_index, vb_index, vectors, gate**2)
    return np.where(((match >= 0).sum(axis=1) >= 2)[:, None, None], wahba_rotations(profiles), rotation)


@njit
def wahba_rotations(profiles):
    """(K, 3, 3) rotations R minimising sum_i |b_i - R a_i|^2, from attitude profiles B = sum_i b_i a_i^T
    (:func:`app.attitude.rotations.wahba_rotation` of each)."""
    out = np.empty((profiles.shape[0], 3, 3))
    for k in range(profiles.shape[0]):
        R = wahba_rotation(profiles[k])
        for r in range(3):  # element by element: a slice assignment costs numba seconds to compile
            for c in range(3):
                out[k, r, c] = R[r, c]
    return out


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
    # zero rows are padding (|x| + |y| + |z|: a sum over an axis of three costs numpy more than the data)
    n_sources = (np.abs(vectors[..., 0]) + np.abs(vectors[..., 1]) + np.abs(vectors[..., 2]) > 0).sum(axis=1)
    cap = None
    if max_work is not None:
        cost = np.maximum(1, n_sources[links[:, 0]] * n_sources[links[:, 1]])
        cap = np.maximum(min_hypotheses, max_work // cost)
    link, a1, a2, b1, b2 = _hypotheses(chords, pi, pj, links, pair_tol, min_baseline, cap)
    if len(link) == 0:
        return PairRotations(rotation, n_inliers, np.full((n_links, vectors.shape[1]), -1), np.zeros(0))

    sa, sb = links[link, 0], links[link, 1]
    flat = hyp_vectors.reshape(-1, 3)  # hyp_vectors[s, i] is flat[s K + i]
    k = hyp_vectors.shape[1]
    hyp_r = rotation_from_pair(flat[sb * k + b1], flat[sb * k + b2], flat[sa * k + a1], flat[sa * k + a2])
    score = _scores(hyp_r, sa, sb, vectors, score_gate)

    # the best few hypotheses per link: sort by (link, -score), keep each group's head
    order = np.lexsort((-score, link))
    sorted_link = link[order]
    rank = np.arange(len(order)) - np.searchsorted(sorted_link, sorted_link)  # place within its link
    keep = order[rank < n_refine]
    found = link[keep]
    r = _refit(hyp_r[keep], sa[keep], sb[keep], vectors, fit_gate)
    # among a link's refined candidates the one whose matches fit best wins
    # (truncated quadratic again): a chance match that made a wrong
    # hypothesis tie in inliers leaves a visibly larger residual
    match, match_sq, _ = _mutual_matches(r, sa[keep], sb[keep], vectors, fit_gate**2)
    fit_score = np.where(match >= 0, 1.0 - match_sq / fit_gate**2, 0.0).sum(axis=1)
    order = np.lexsort((-fit_score, found))
    winner = order[np.r_[True, found[order][1:] != found[order][:-1]]]
    found, sa, sb = found[winner], sa[keep][winner], sb[keep][winner]
    r = _refit(r[winner], sa, sb, vectors, fit_gate)

    match, match_sq, _ = _mutual_matches(r, sa, sb, vectors, fit_gate**2)
    count = (match >= 0).sum(axis=1)
    radius_sq = np.maximum(match_sq.max(axis=1), min_radius**2)
    n_hyp = np.bincount(link, minlength=n_links)[found]
    nfa = false_alarms(n_hyp, n_sources[sa], n_sources[sb], count, radius_sq, field_area)
    ok = (count >= min_inliers) & (nfa <= max_false_alarms)
    rotation[found[ok]] = r[ok]
    n_inliers[found] = count
    matches = np.full((n_links, vectors.shape[1]), -1, dtype=int)
    matches[found[ok]] = match[ok]
    inlier_sq = match_sq[ok][match[ok] >= 0]
    return PairRotations(rotation, n_inliers, matches, inlier_sq)


@warm_up_with
def _warm_up_motion() -> None:
    """Compile :func:`_scores`, :func:`_mutual_matches` and :func:`wahba_rotations` for the arrays
    :func:`estimate_pair_rotations` passes."""
    vectors = np.array([[[0.0, 0.0, 1.0], [0.0, 0.01, 1.0]], [[0.0, 0.0, 1.0], [0.01, 0.0, 1.0]]])
    _scores(np.eye(3)[None], np.array([0]), np.array([1]), vectors, 0.01)
    _mutual_matches(np.eye(3)[None], np.array([0]), np.array([1]), vectors, 0.01)
    wahba_rotations(np.eye(3)[None])
