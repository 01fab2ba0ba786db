"""Checking, refining and scoring attitude hypotheses.

* Check (seed 004): map the whole pattern onto the sky with a hypothesis and
  find each point's nearest catalogue star (KD-tree on unit vectors).
* Refine: least squares over every matched pair (Wahba's problem, SVD),
  re-matching with a tolerance that shrinks as the attitude improves, and
  rejecting points whose residual stays beyond it (planets, ghosts, a
  misidentified neighbour); each catalogue star takes at most one point.
* Score: the seed's deviation (sum of the angles to the nearest star) and a
  false-match probability: the expected number of hypotheses, among the
  ``N`` tried, that would match ``k`` of ``m`` points by chance.  A point
  lands within ``r`` of one of the visible stars (density ``rho`` per
  steradian) with probability ``p = 1 - exp(-rho pi r^2)``; the two points
  of the generating edge match by construction, so::

      P_false = min(1, N * P[Binomial(m - 2, p) >= k - 2])

  (the reasoning of astrometry.net's and tetra3's match statistics).
  ``r`` is the tolerance with which the hypothesis *collected* its extra
  matches before the least-squares fit pulled them in, not the final,
  tighter one (the fit has three degrees of freedom to make chance
  coincidences look good; using the final tolerance underestimated the
  chance matches of random patterns a hundredfold).  A second factor then
  asks how likely chance points would fit as tightly as the matched ones
  do (see :func:`false_match_probability`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from itertools import combinations
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import bdtrc, chdtr  # binomial survival, chi-square CDF (scipy.stats' are 30x slower per call)

from app.attitude import solve_wahba
from app.identification.cells import check_kernel


@dataclass(frozen=True, eq=False)
class StarField:
    """The catalogue as seen at one time: apparent unit vectors and a KD-tree."""

    vectors: np.ndarray  # (n, 3) apparent places, ICRS axes
    rows: np.ndarray  # (n,) catalogue/index rows of these stars
    tree: cKDTree
    #: ``cells(radius)``: a :class:`app.identification.cells.NearStarCells` of these stars for at least
    #: that radius (None: none fits; then every point asks the tree).
    cells: Callable[[float], object | None] | None = None
    #: (n,) chord within which a point's nearest star is certainly that star (half its distance to the
    #: nearest other one, at any epoch), or None.
    alone_within: np.ndarray | None = None

    @classmethod
    def from_vectors(cls, vectors: np.ndarray, rows: np.ndarray, cells=None,
                     alone_within: np.ndarray | None = None) -> "StarField":
        # An unbalanced tree builds twice as fast; queries are as quick on stars.
        return cls(vectors=vectors, rows=rows, tree=cKDTree(vectors, balanced_tree=False, compact_nodes=False),
                   cells=cells, alone_within=alone_within)

    @property
    def density_per_sr(self) -> float:
        return len(self.vectors) / (4 * np.pi)


def chord(angle_rad):
    return 2 * np.sin(np.asarray(angle_rad) / 2)


def chord_to_angle(c):
    return 2 * np.arcsin(np.minimum(np.asarray(c) / 2, 1.0))  # chords are >= 0


def check_hypotheses(rotations: np.ndarray, pattern_vectors: np.ndarray, field: StarField,
                     tolerance_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Matches and capped deviation of every hypothesis.

    Returns (n_matched (H,), deviation (H,) = sum over points of
    min(angle to nearest star, tolerance)).  Every point of every hypothesis
    is checked: the chance fits found this way are the alternatives an
    operator compares the best match with (the seed's "best wrong match").
    The nearest star within the largest tolerance is the field's cell map's
    (:mod:`app.identification.cells`: a compiled loop over the points, the
    KD-tree's answer bit for bit, no temporaries); where the field has no map
    (an observer too fast or an epoch too far for one), the tree's.
    """
    tol = np.ascontiguousarray(tolerance_rad, dtype=float).reshape(-1)
    H = len(rotations)
    if H == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    cap = float(np.max(tol))
    bound = float(chord(cap))
    cells = field.cells(cap) if field.cells is not None else None
    if cells is not None:
        return check_kernel(np.ascontiguousarray(rotations, dtype=float), np.ascontiguousarray(pattern_vectors),
                            tol, field.vectors, bound, *cells.kernel_arrays())
    sky = np.matmul(pattern_vectors[None], rotations).reshape(-1, 3)  # rows R^T p
    d, _ = field.tree.query(sky, k=1, distance_upper_bound=bound)
    ang = chord_to_angle(np.where(np.isfinite(d), d, 2.0)).reshape(H, -1)
    return (ang <= tol[:, None]).sum(axis=1), np.minimum(ang, tol[:, None]).sum(axis=1)


@dataclass(frozen=True, eq=False)
class Refined:
    rotation: np.ndarray
    star_of_point: np.ndarray  # (m,) field row matched to each pattern point, -1 if none
    residual_rad: np.ndarray  # (m,) angle to the matched star (nan if none)
    nearest_rad: np.ndarray  # (m,) angle to the nearest star, matched or not

    @property
    def n_matched(self) -> int:
        return int((self.star_of_point >= 0).sum())


def match_points(rotation: np.ndarray, pattern_vectors: np.ndarray, field: StarField,
                 tolerance_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one nearest-star matching under one rotation.

    Returns (star_of_point, residual, nearest angle); a star claimed by two
    points goes to the closer one.
    """
    star, resid, ang = match_points_many(np.asarray(rotation)[None], pattern_vectors, field, tolerance_rad)
    return star[0], resid[0], ang[0]


def match_points_many(rotations: np.ndarray, pattern_vectors: np.ndarray, field: StarField,
                      tolerance_rad: np.ndarray, nearest: bool = True
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`match_points` for a stack of rotations (K, 3, 3): (K, m) arrays, one KD-tree query for all.

    ``tolerance_rad`` is (m,) or (K, m).  A KD-tree query of a dozen points
    costs ~50 microseconds of call overhead, more than the search itself:
    one query for every hypothesis of a batch pays it once.  With
    ``nearest=False`` the search stops at the largest tolerance (faster;
    the nearest angle is then inf where no star lies within it).
    """
    K, m = len(rotations), len(pattern_vectors)
    d, idx = _query(rotations, pattern_vectors, field, None if nearest else np.max(tolerance_rad))
    ang = chord_to_angle(d).reshape(K, m)
    return _assign(ang, idx.reshape(K, m), tolerance_rad) + (ang,)


def _query(rotations: np.ndarray, pattern_vectors: np.ndarray, field: StarField, within_rad: float | None = None):
    """Chord to the nearest star (and its field position) of every rotated point, flattened (K m,).

    ``within_rad``: stop the search there (the tree answers inf, angle pi, beyond it): enough to match at
    any tolerance up to it, and faster for the points far from every star.
    """
    sky = np.matmul(pattern_vectors[None], rotations).reshape(-1, 3)  # rows R^T p
    if within_rad is None:
        return field.tree.query(sky, k=1)
    # Slightly beyond the bound, so that rounding never loses a star at exactly the tolerance.
    return field.tree.query(sky, k=1, distance_upper_bound=float(chord(within_rad)) * (1 + 1e-9) + 1e-15)


def _assign(ang: np.ndarray, idx: np.ndarray, tolerance_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(star_of_point, residual) (K, m) from each point's nearest star (field position ``idx``, angle ``ang``)."""
    star = np.where(ang <= tolerance_rad, idx, -1)
    # One point per star: among points of one hypothesis claiming the same star, the closest keeps it.
    ordered = np.sort(star, axis=1)
    if ((ordered[:, 1:] == ordered[:, :-1]) & (ordered[:, 1:] >= 0)).any():
        k, i = np.nonzero(star >= 0)
        claimed = star[k, i]
        order = np.lexsort((ang[k, i], claimed, k))
        repeat = (claimed[order][1:] == claimed[order][:-1]) & (k[order][1:] == k[order][:-1])
        lose = order[1:][repeat]
        star[k[lose], i[lose]] = -1
    return star, np.where(star >= 0, ang, np.nan)


#: After the fit, a matched point whose leave-one-out residual exceeds this
#: many of its sigmas (or of the residuals' own robust scale, if larger) is
#: let go: a displaced star or a blend inside the match tolerance would bias
#: the fit.
FINAL_REJECT_SIGMAS = 3.0
RAYLEIGH_QUARTILE = 0.7585  # lower quartile of |r| for a 2-D Gaussian of unit sigma per axis


#: Up to this many matched points, outliers are found by trying every subset.
SMALL_SET = 7


@functools.lru_cache(maxsize=None)
def _subsets(n: int) -> np.ndarray:
    """(S, n) masks of every subset of at least 3 of n points, smallest first."""
    return np.array([[i in c for i in range(n)] for k in range(3, n + 1) for c in combinations(range(n), k)])


def consensus_subset(body: np.ndarray, ref: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n,) mask of the points agreeing with the fit of the best subset of at least 3 of them.

    Every subset of 3 or more points is fitted (all at once: a stack of
    Wahba SVDs); a point agrees when its residual is within
    :data:`FINAL_REJECT_SIGMAS` sigma.  The subset whose fit most points
    agree with wins, ties going to the smallest chi-square.
    """
    return consensus_subsets(body[None], ref[None], weights[None])[0]


def consensus_subsets(body: np.ndarray, ref: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """:func:`consensus_subset` for G sets of n points at once: (G, n, 3), (G, n, 3), (G, n) -> (G, n)."""
    G, n = weights.shape
    if n == 3:  # one subset: it wins whether or not all three agree
        return np.ones((G, 3), dtype=bool)
    agree, chi2 = _subset_fits(body, ref, weights, _subsets(n))
    count = agree.sum(axis=-1)
    # Most points agreeing, then the smallest chi-square; the first subset on a tie.
    best = np.argmin(np.where(count == count.max(axis=1, keepdims=True), chi2, np.inf), axis=1)
    out = agree[np.arange(G), best]
    out[out.sum(axis=1) < 3] = True
    return out


def _subset_fits(body: np.ndarray, ref: np.ndarray, weights: np.ndarray,
                 subsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wahba's fit of each subset (S, n) of each set: which points agree with it (G, S, n), and its chi2 (G, S)."""
    sigma = 1.0 / np.sqrt(weights)
    w = subsets[None] * weights[:, None, :]  # (G, S, n)
    B = np.einsum("gsn,gni,gnj->gsij", w, body, ref)
    U, _, Vt = np.linalg.svd(B)
    D = np.broadcast_to(np.eye(3), B.shape).copy()
    D[..., 2, 2] = np.linalg.det(U) * np.linalg.det(Vt)
    R = U @ D @ Vt
    predicted = np.einsum("gsij,gnj->gsni", R, ref)
    b = body[:, None]
    resid = np.arctan2(np.linalg.norm(np.cross(b, predicted), axis=-1), np.sum(b * predicted, axis=-1))  # (G, S, n)
    agree = resid <= FINAL_REJECT_SIGMAS * sigma[:, None, :]
    chi2 = np.where(agree, (resid / sigma[:, None, :]) ** 2, 0.0).sum(axis=-1)
    return agree, chi2


def leave_one_out_residuals(body: np.ndarray, ref: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Angle between each ``body_i`` and ``R_(-i) ref_i``, with ``R_(-i)`` Wahba's fit without point i.

    All fits at once: ``B_(-i) = B - w_i b_i r_i^T``, a stack of 3x3 SVDs.
    """
    outer = weights[:, None, None] * body[:, :, None] * ref[:, None, :]
    B = outer.sum(axis=0)[None] - outer
    U, _, Vt = np.linalg.svd(B)
    d = np.linalg.det(U) * np.linalg.det(Vt)
    D = np.zeros((len(body), 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = U @ D @ Vt
    predicted = np.einsum("nij,nj->ni", R, ref)
    return np.arctan2(np.linalg.norm(np.cross(body, predicted), axis=1), np.sum(body * predicted, axis=1))


def refine(rotation: np.ndarray, pattern_vectors: np.ndarray, weights: np.ndarray, field: StarField,
           final_tolerance_rad: np.ndarray, start_tolerance_rad: float, iterations: int = 4) -> Refined:
    """Iterated Wahba fit with a tolerance shrinking to ``final_tolerance_rad``, then outlier rejection.

    ``weights`` are 1 / sigma^2 of each point.  The last step drops, one at a
    time, the matched point whose leave-one-out residual exceeds
    :data:`FINAL_REJECT_SIGMAS` times max(sigma_i, a robust scale of those
    residuals, so that real data with larger errors than stated keeps its
    stars) the most, and refits, while more than :data:`SMALL_SET` points
    remain; smaller sets keep the largest subset that fits within the noise
    instead (:func:`consensus_subset`).  One hypothesis of
    :func:`refine_many` (the same arithmetic, so the same answer whatever
    the batch).
    """
    return refine_many(np.asarray(rotation)[None], pattern_vectors, weights, field, final_tolerance_rad,
                       np.array([start_tolerance_rad], dtype=float), iterations)[0]


def _wahba_masked(pattern_vectors: np.ndarray, star_vectors: np.ndarray, weights: np.ndarray,
                  use: np.ndarray) -> np.ndarray:
    """Wahba's rotation of each row's points where ``use`` (K, m): a zero weight leaves a point out."""
    body = np.broadcast_to(pattern_vectors, star_vectors.shape)
    return solve_wahba(body, star_vectors, np.where(use, weights, 0.0))


def refine_many(rotations: np.ndarray, pattern_vectors: np.ndarray, weights: np.ndarray, field: StarField,
                final_tolerance_rad: np.ndarray, start_tolerance_rad: np.ndarray,
                iterations: int = 4) -> list[Refined]:
    """:func:`refine` of K hypotheses (rotations (K, 3, 3), start tolerances (K,)) at once.

    Why a batch: a refinement is some 150 small numpy operations (KD-tree
    queries, 3x3 SVDs) on a dozen points, where the call overhead is most of
    the cost; the steps of all hypotheses run as one operation each.  Each
    hypothesis follows exactly the steps :func:`refine` describes (its own
    number of iterations, its own outlier rejection), so its result does not
    depend on the others in the batch.
    """
    R = np.array(rotations, dtype=float).reshape(-1, 3, 3)
    K, m = len(R), len(pattern_vectors)
    start = np.broadcast_to(np.asarray(start_tolerance_rad, dtype=float).reshape(-1), (K,))
    final_tol = np.asarray(final_tolerance_rad, dtype=float)
    stars_xyz = field.vectors
    fitted = np.full((K, m), -1)
    active = np.ones(K, dtype=bool)
    have_final = np.zeros(K, dtype=bool)
    star = np.full((K, m), -1)
    resid = np.full((K, m), np.nan)
    # Only the stars within the tolerances are looked for while iterating (a bounded query is faster); the
    # nearest star of every point (the deviation) is asked for the rotations the iterations end at.
    for it in range(iterations):
        a = np.flatnonzero(active)
        if len(a) == 0:
            break
        f = it / max(1, iterations - 1)
        tol = np.maximum(final_tol, start[a, None] * (1 - f) + final_tol * f)
        d, idx = _query(R[a], pattern_vectors, field, np.max(tol))
        ang, idx = chord_to_angle(d).reshape(len(a), m), idx.reshape(len(a), m)
        s, _ = _assign(ang, idx, tol)
        go = (s >= 0).sum(axis=1) >= 2
        if it > 0:
            # Converged: refitting gives the same R, and once the final tolerance keeps these matches
            # too, so does every tolerance between.  (The final tolerance is the smallest: the same
            # query answers it.)
            same = go & (s == fitted[a]).all(axis=1)
            if same.any():
                f_star, f_resid = _assign(ang[same], idx[same], final_tol)
                done = (f_star == s[same]).all(axis=1)
                rows = a[same][done]
                star[rows], resid[rows] = f_star[done], f_resid[done]
                have_final[rows] = True
                go[np.flatnonzero(same)[done]] = False
        active[a[~go]] = False
        rows = a[go]
        if len(rows):
            s = s[go]
            R[rows] = _wahba_masked(pattern_vectors, stars_xyz[s], weights, s >= 0)
            fitted[rows] = s
    # The nearest star of every point under the rotations reached: the last match of the rows that
    # converged, the final match of the others, and every point's nearest star (the deviation).
    d, idx = _query(R, pattern_vectors, field)
    nearest, idx = chord_to_angle(d).reshape(K, m), idx.reshape(K, m)
    rest = np.flatnonzero(~have_final)
    if len(rest):
        star[rest], resid[rest] = _assign(nearest[rest], idx[rest], final_tol)
    sigma = 1.0 / np.sqrt(weights)
    if m >= 3:
        # Few points: leave-one-out cannot unmask two outliers among five, so
        # among the points near a star (twice the tolerance: a biased fit may
        # have pushed a good one out) the largest subset that fits within the
        # noise wins (ties: lowest chi-square).
        small = np.flatnonzero((star >= 0).sum(axis=1) <= SMALL_SET)
        near, _ = _assign(nearest[small], idx[small], 2 * final_tol)
        count = (near >= 0).sum(axis=1)
        fit = (count >= 3) & (count <= SMALL_SET)
        rejected = np.zeros((len(small), m), dtype=bool)
        for n in np.unique(count[fit]).tolist():
            g = np.flatnonzero(count == n)
            cols = np.nonzero(near[g] >= 0)[1].reshape(len(g), n)  # each row's points near a star, in order
            body = pattern_vectors[cols]
            ref = stars_xyz[near[g][np.arange(len(g))[:, None], cols]]
            agree = consensus_subsets(body, ref, weights[cols])
            R[small[g]] = solve_wahba(body, ref, np.where(agree, weights[cols], 0.0))
            rejected[g[:, None], cols] = ~agree
        rows = small[fit]
        if len(rows):
            d, idx = _query(R[rows], pattern_vectors, field)
            nearest[rows] = chord_to_angle(d).reshape(len(rows), m)
            fresh, f_resid = _assign(nearest[rows], idx.reshape(len(rows), m), final_tol)
            star[rows] = np.where(~rejected[fit] & (fresh >= 0), fresh, -1)
            resid[rows] = np.where(star[rows] >= 0, f_resid, np.nan)
    for k in np.flatnonzero((star >= 0).sum(axis=1) > SMALL_SET):
        # Judge each point by the fit of the others: an outlier cannot hide by pulling the fit.  (Large
        # sets are the true matches, one or two per search: one at a time.)
        s = star[k]
        for _ in range(max(1, m // 3)):
            ok = np.flatnonzero(s >= 0)
            if len(ok) <= SMALL_SET:  # small sets had their subset search; LOO needs redundancy
                break
            loo = leave_one_out_residuals(pattern_vectors[ok], stars_xyz[s[ok]], weights[ok])
            # The lower quartile: outliers pull the fit, inflating the others' residuals and the median.
            scale = np.maximum(sigma[ok], np.quantile(loo, 0.25) / RAYLEIGH_QUARTILE)
            worst = int(np.argmax(loo / scale))
            if loo[worst] <= FINAL_REJECT_SIGMAS * scale[worst]:
                break
            s = s.copy()
            s[ok[worst]] = -1
            keep = s >= 0
            R[k] = solve_wahba(pattern_vectors[keep], stars_xyz[s[keep]], weights[keep])
            fresh, f_resid, nearest[k] = match_points(R[k], pattern_vectors, field, final_tol)
            s = np.where(keep & (fresh >= 0), fresh, -1)  # a rejected point stays out
            resid[k] = np.where(s >= 0, f_resid, np.nan)
        star[k] = s
    return [Refined(rotation=R[k], star_of_point=star[k], residual_rad=resid[k], nearest_rad=nearest[k])
            for k in range(K)]


def false_match_probability(n_points: int, n_matched: int, capture_tolerance_rad: float,
                            density_per_sr: float, n_hypotheses: int, sum_sq_residual_rad2: float,
                            n_fitted: int = 0) -> float:
    """Expected number of chance matches as good as this one (capped at 1); see the module doc.

    Two factors: enough points captured, ``N * P[Binomial(m - 2, p) >= k - 2]``,
    and, given that, a least-squares fit as tight as the one found.  A chance
    point captured within ``r`` sits uniformly in that disc (variance r^2/4
    per axis); after the fit has absorbed 3 degrees of freedom, the sum of
    squared residuals of ``k`` such points is at most ~ (r^2/4) chi^2(2k - 3),
    so ``P[fit this tight] = chi2.cdf(4 S / r^2, 2k - 3)``.  (The Gaussian
    has twice the uniform disc's density at zero, so this errs on the safe,
    larger side.)  Optical parameters fitted with the attitude (``n_fitted``:
    the focal length, k1) absorb one degree of freedom each, so a chance fit
    with free optics is judged against ``chi2(2k - 3 - n_fitted)``.
    """
    if n_matched < 3 or n_points < 3:
        return 1.0
    r = float(capture_tolerance_rad)
    p = 1.0 - np.exp(-density_per_sr * np.pi * r * r)
    capture = float(bdtrc(n_matched - 3, n_points - 2, p))  # P[X >= k - 2] = P[X > k - 3]
    dof = 2 * n_matched - 3 - n_fitted
    tight = float(chdtr(dof, 4.0 * sum_sq_residual_rad2 / (r * r))) if dof > 0 else 1.0
    return float(min(1.0, max(1, n_hypotheses) * capture * tight))
