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

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import bdtrc, chdtr  # binomial survival, chi-square CDF (scipy.stats' are 30x slower per call)

from app.attitude import solve_wahba


@dataclass(frozen=True, eq=False)
class StarField:
    """The catalogue as seen at one time: apparent unit vectors and a KD-tree."""

    vectors: np.ndarray  # (n, 3) apparent places, ICRS axes
    rows: np.ndarray  # (n,) catalogue/index rows of these stars
    tree: cKDTree

    @classmethod
    def from_vectors(cls, vectors: np.ndarray, rows: np.ndarray) -> "StarField":
        # An unbalanced tree builds twice as fast; queries are as quick on stars.
        return cls(vectors=vectors, rows=rows, tree=cKDTree(vectors, balanced_tree=False, compact_nodes=False))

    @property
    def density_per_sr(self) -> float:
        return len(self.vectors) / (4 * np.pi)


def chord(angle_rad):
    return 2 * np.sin(np.asarray(angle_rad) / 2)


def chord_to_angle(c):
    return 2 * np.arcsin(np.minimum(np.asarray(c) / 2, 1.0))  # chords are >= 0


def _nearest_angles(rotations: np.ndarray, vectors: np.ndarray, field: StarField, cap: float) -> np.ndarray:
    """(H, k) angle from each rotated point to its nearest star (2 rad beyond ``cap``)."""
    sky = np.matmul(vectors[None], rotations)  # rows R^T p
    d, _ = field.tree.query(sky.reshape(-1, 3), k=1, distance_upper_bound=float(chord(cap)))
    return chord_to_angle(np.where(np.isfinite(d), d, 2.0)).reshape(len(rotations), len(vectors))


def check_hypotheses(rotations: np.ndarray, pattern_vectors: np.ndarray, field: StarField,
                     tolerance_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Matches and capped deviation of every hypothesis.

    Returns (n_matched (H,), deviation (H,) = sum over points of
    min(angle to nearest star, tolerance)).  Every point of every hypothesis
    is checked: the chance fits found this way are the alternatives an
    operator compares the best match with (the seed's "best wrong match").
    """
    tol = np.asarray(tolerance_rad, dtype=float).reshape(-1)
    cap = float(np.max(tol)) if len(rotations) else 0.0
    ang = _nearest_angles(rotations, pattern_vectors, field, cap)
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
    sky = pattern_vectors @ rotation  # rows: R^T p
    d, idx = field.tree.query(sky, k=1)
    ang = chord_to_angle(d)
    star = np.where(ang <= tolerance_rad, idx, -1)
    # One point per star: among points claiming the same star, the closest keeps it.
    claimed = np.flatnonzero(star >= 0)
    if len(claimed) > 1 and len(set(star[claimed].tolist())) < len(claimed):
        order = claimed[np.lexsort((ang[claimed], star[claimed]))]
        repeat = np.concatenate([[False], star[order][1:] == star[order][:-1]])
        star[order[repeat]] = -1
    return star, np.where(star >= 0, ang, np.nan), ang


#: After the fit, a matched point whose leave-one-out residual exceeds this
#: many of its sigmas (or of the residuals' own robust scale, if larger) is
#: let go: a displaced star or a blend inside the match tolerance would bias
#: the fit.
FINAL_REJECT_SIGMAS = 3.0
RAYLEIGH_QUARTILE = 0.7585  # lower quartile of |r| for a 2-D Gaussian of unit sigma per axis


#: Up to this many matched points, outliers are found by trying every subset.
SMALL_SET = 7


def consensus_subset(body: np.ndarray, ref: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n,) mask of the points agreeing with the fit of the best subset of at least 3 of them.

    Every subset of 3 or more points is fitted (all at once: a stack of
    Wahba SVDs); a point agrees when its residual is within
    :data:`FINAL_REJECT_SIGMAS` sigma.  The subset whose fit most points
    agree with wins, ties going to the smallest chi-square.
    """
    from itertools import combinations

    n = len(body)
    if n == 3:  # one subset: it wins whether or not all three agree
        return np.ones(3, dtype=bool)
    sigma = 1.0 / np.sqrt(weights)
    subsets = np.array([[i in c for i in range(n)] for k in range(3, n + 1) for c in combinations(range(n), k)])
    w = subsets * weights[None, :]  # (S, n)
    B = np.einsum("sn,ni,nj->sij", w, body, ref)
    U, _, Vt = np.linalg.svd(B)
    D = np.broadcast_to(np.eye(3), B.shape).copy()
    D[:, 2, 2] = np.linalg.det(U) * np.linalg.det(Vt)
    R = U @ D @ Vt
    predicted = np.einsum("sij,nj->sni", R, ref)
    resid = np.arctan2(np.linalg.norm(np.cross(body[None], predicted), axis=2),
                       np.sum(body[None] * predicted, axis=2))  # (S, n)
    agree = resid <= FINAL_REJECT_SIGMAS * sigma[None, :]
    chi2 = np.where(agree, (resid / sigma[None, :]) ** 2, 0.0).sum(axis=1)
    best = np.lexsort((chi2, -agree.sum(axis=1)))[0]
    return agree[best] if agree[best].sum() >= 3 else np.ones(n, dtype=bool)


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
    instead (:func:`consensus_subset`).
    """
    R = rotation
    fitted = None  # the matches R was last fitted to
    final = None
    for it in range(iterations):
        f = it / max(1, iterations - 1)
        tol = np.maximum(final_tolerance_rad, start_tolerance_rad * (1 - f) + final_tolerance_rad * f)
        star, _, _ = match_points(R, pattern_vectors, field, tol)
        ok = star >= 0
        if ok.sum() < 2:
            break
        if fitted is not None and np.array_equal(star, fitted):
            # Converged: refitting gives the same R, and once the final
            # tolerance keeps these matches too, so does every tolerance between.
            final = match_points(R, pattern_vectors, field, final_tolerance_rad)
            if np.array_equal(final[0], star):
                break
            final = None
        R = solve_wahba(pattern_vectors[ok], field.vectors[star[ok]], weights[ok])
        fitted = star
    star, resid, nearest = final or match_points(R, pattern_vectors, field, final_tolerance_rad)
    sigma = 1.0 / np.sqrt(weights)
    if 3 <= len(pattern_vectors) and (star >= 0).sum() <= SMALL_SET:
        # Few points: leave-one-out cannot unmask two outliers among five, so
        # among the points near a star (twice the tolerance: a biased fit may
        # have pushed a good one out) the largest subset that fits within the
        # noise wins (ties: lowest chi-square).
        near, _, _ = match_points(R, pattern_vectors, field, 2 * final_tolerance_rad)
        ok = np.flatnonzero(near >= 0)
        if 3 <= len(ok) <= SMALL_SET:
            agree = consensus_subset(pattern_vectors[ok], field.vectors[near[ok]], weights[ok])
            R = solve_wahba(pattern_vectors[ok[agree]], field.vectors[near[ok[agree]]], weights[ok[agree]])
            fresh, resid, nearest = match_points(R, pattern_vectors, field, final_tolerance_rad)
            rejected = np.zeros(len(star), dtype=bool)
            rejected[ok[~agree]] = True
            star = np.where(~rejected & (fresh >= 0), fresh, -1)
            resid = np.where(star >= 0, resid, np.nan)
    for _ in range(max(1, len(pattern_vectors) // 3)):
        ok = np.flatnonzero(star >= 0)
        if len(ok) <= SMALL_SET:  # small sets had their subset search; LOO needs redundancy
            break
        # Judge each point by the fit of the others: an outlier cannot hide by pulling the fit.
        loo = leave_one_out_residuals(pattern_vectors[ok], field.vectors[star[ok]], weights[ok])
        # The lower quartile: outliers pull the fit, inflating the others' residuals and the median.
        scale = np.maximum(sigma[ok], np.quantile(loo, 0.25) / RAYLEIGH_QUARTILE)
        worst = int(np.argmax(loo / scale))
        if loo[worst] <= FINAL_REJECT_SIGMAS * scale[worst]:
            break
        star[ok[worst]] = -1
        keep = star >= 0
        R = solve_wahba(pattern_vectors[keep], field.vectors[star[keep]], weights[keep])
        fresh, resid, nearest = match_points(R, pattern_vectors, field, final_tolerance_rad)
        star = np.where(keep & (fresh >= 0), fresh, -1)  # a rejected point stays out
        resid = np.where(star >= 0, resid, np.nan)
    return Refined(rotation=R, star_of_point=star, residual_rad=resid, nearest_rad=nearest)


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
