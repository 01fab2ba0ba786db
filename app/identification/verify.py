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
import math
import weakref
from dataclasses import dataclass
from itertools import combinations
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import bdtrc, chdtr  # binomial survival, chi-square CDF (scipy.stats' are 30x slower per call)

from app.attitude.rotations import wahba_rotation
from app.compiled import njit, warm_up_with
from app.identification.cells import NearStarCells, check_kernel, nearest_star


@dataclass(frozen=True, eq=False)
class StarField:
    """The catalogue as seen at one time: apparent unit vectors, and a KD-tree made when first asked for."""

    vectors: np.ndarray  # (n, 3) apparent places, ICRS axes
    rows: np.ndarray  # (n,) catalogue/index rows of these stars
    #: The same stars at one fixed epoch and a KD-tree of them (made once for every observation time), and
    #: the largest angle (a chord) between a star's place there and here; or None.  See :meth:`nearest_chords`.
    epoch_places: tuple[cKDTree, float] | None = None
    #: ``cells(radius, make=True)``: a :class:`app.identification.cells.NearStarCells` of these stars for at
    #: least that radius (None: none fits, or none made yet when ``make`` is False; then every point asks the
    #: tree).
    cells: Callable[[float], object | None] | None = None
    #: (n,) chord within which a point's nearest star is certainly that star (half its distance to the
    #: nearest other one, at any epoch), or None.
    alone_within: np.ndarray | None = None
    #: (n,) the stars' magnitudes, brightest first as the index's (a prefix of it), or None (then every
    #: star counts as equally bright).
    mag: np.ndarray | None = None

    @classmethod
    def from_vectors(cls, vectors: np.ndarray, rows: np.ndarray, cells=None,
                     alone_within: np.ndarray | None = None, mag: np.ndarray | None = None,
                     epoch_places: tuple[cKDTree, float] | None = None) -> "StarField":
        return cls(vectors=vectors, rows=rows, cells=cells, alone_within=alone_within, mag=mag,
                   epoch_places=epoch_places)

    @functools.cached_property
    def tree(self) -> cKDTree:
        """A KD-tree of :attr:`vectors` (~1 ms for 8,000 stars: made only where a query needs one).  An
        unbalanced tree builds twice as fast; queries are as quick on stars."""
        return cKDTree(self.vectors, balanced_tree=False, compact_nodes=False)

    def nearest_chords(self, points: np.ndarray) -> np.ndarray:
        """(N,) chord from each unit vector (N, 3) to its nearest star, however far.

        First from the field's cell map for :meth:`far_radius` (a compiled
        look-up of the few stars listed for each point's cell, the tree's
        answer bit for bit: :mod:`app.identification.cells`); a query of the
        tree costs ~0.1 ms whatever the points, and a search asks for the
        nearest star of its refinements' unmatched points hundreds of times
        on a frame that matches nothing.  The points with no star that close
        (a few in a thousand), or every point where the field has no map, ask
        the tree: through :attr:`epoch_places` when the field has them, so
        that a new observation time needs no tree of its own: a star whose
        place moved by at most ``shift`` (a chord) is, if it is a point's
        nearest, within ``d0 + 2 shift`` of the point at the fixed epoch
        (``d0``: the point's nearest star there), by the triangle inequality
        twice; those few are measured at their places now, as the tree would
        measure them.
        """
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        radius = self.far_radius()
        cells = self.cells(radius) if self.cells is not None and len(points) else None
        if cells is None:
            return self._tree_nearest_chords(points)
        out = cells.nearest_within(points, self.vectors, float(chord(radius)))
        beyond = np.flatnonzero(np.isinf(out))
        if len(beyond):
            out[beyond] = self._tree_nearest_chords(points[beyond])
        return out

    def far_radius(self) -> float:
        """The radius of the cell map :meth:`nearest_chords` asks first: 1.5 times the stars' mean spacing
        (``1 / sqrt(density)``), within the largest map made (0.1 rad).  Measured 2026-11-26 on the points
        whose nearest star a search asked for (20 single snapshots and 20 noise frames per camera): within it
        99.98 % of the 20 deg camera's (6,019 stars, 3.9 deg), 99.97 % of the 12 deg camera's (7,982 stars,
        3.4 deg), 99.4 % of the 30 deg camera's (1,979 stars, 5.7 deg)."""
        return float(min(0.1, 1.5 / np.sqrt(max(self.density_per_sr, 1e-9))))

    def _tree_nearest_chords(self, points: np.ndarray) -> np.ndarray:
        """:meth:`nearest_chords` by the KD-trees alone."""
        if self.epoch_places is None or len(points) == 0:
            return self.tree.query(points, k=1)[0].reshape(len(points))
        tree, shift = self.epoch_places
        k = min(EPOCH_NEIGHBOURS, len(self.vectors))
        d, near = tree.query(points, k=k)
        d, near = d.reshape(len(points), k), near.reshape(len(points), k)

        def nearest(point, rows):  # the chord to the nearest of these stars, summed in a KD-tree's order
            diff = point - self.vectors[rows]
            x, y, z = diff[..., 0], diff[..., 1], diff[..., 2]
            return np.sqrt(np.min((x * x + y * y) + z * z, axis=-1))

        out = nearest(points[:, None, :], near)
        # Where a star beyond the k nearest at the epoch could still be within d0 + 2 shift: all of those.
        for i in np.flatnonzero((d[:, -1] <= d[:, 0] + 2 * shift) & (k < len(self.vectors))).tolist():
            out[i] = nearest(points[i], tree.query_ball_point(points[i], d[i, 0] + 2 * shift + 1e-12))
        return out

    @property
    def density_per_sr(self) -> float:
        return len(self.vectors) / (4 * np.pi)


#: :meth:`StarField.nearest_chords` measures this many nearest stars at the index epoch for each point (the
#: nearest now is nearly always among them: stars move by ~0.1 deg at most in a century, they lie degrees apart).
EPOCH_NEIGHBOURS = 4

#: How many stars within a match distance are compared (more than two within a few pixels is rare).
NEIGHBOURS_LOOKED_AT = 4


def brightest_within(directions: np.ndarray, field: StarField, tolerance_rad: float) -> np.ndarray:
    """(n,) position in ``field`` of the brightest star within ``tolerance_rad`` of each of ``directions``
    ((n, 3) unit vectors, ICRS), else -1; of equals (or without magnitudes), the nearest.

    Not simply the nearest: a faint star beside a bright one is seldom seen
    at all, and where both are, their blend is named by its brighter member
    (a 97" pixel sees alpha2 CVn and alpha1, 2.7 mag fainter and 20" away,
    as one source, which lies nearer alpha1 as often as not).
    """
    k = min(NEIGHBOURS_LOOKED_AT, len(field.vectors))
    if len(directions) == 0 or k == 0:
        return np.full(len(directions), -1, dtype=int)
    brightness = field.mag if field.mag is not None else np.zeros(len(field.vectors))
    bound = float(chord(tolerance_rad))
    # The sky's cell map of any radius as large (a larger one lists more stars, each measured): a compiled
    # look-up of a few stars, where the tree's query costs ~0.1 ms of call overhead (several a solve).
    cells = field.cells(tolerance_rad, make=False) if field.cells is not None else None
    if cells is not None:
        return cells.brightest_within(directions, field.vectors, brightness, bound, k)
    _, near = field.tree.query(directions, k=k, distance_upper_bound=bound)
    near = near.reshape(len(directions), k)
    within = near < len(field.vectors)  # the tree marks "none" with n, and lists the nearest first
    mags = np.where(within, brightness[np.minimum(near, len(field.vectors) - 1)], np.inf)
    pick = np.argmin(mags, axis=1)  # the first of equals: the nearest
    return np.where(within[:, 0], near[np.arange(len(near)), pick], -1)


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

    @functools.cached_property
    def n_matched(self) -> int:  # asked for each found candidate after every hypothesis a search considers
        return int((self.star_of_point >= 0).sum())


#: After the fit, a matched point whose leave-one-out residual exceeds this
#: many of its sigmas (or of the residuals' own robust scale, if larger) is
#: let go: a displaced star or a blend inside the match tolerance would bias
#: the fit.
FINAL_REJECT_SIGMAS = 3.0
RAYLEIGH_QUARTILE = 0.7585  # lower quartile of |r| for a 2-D Gaussian of unit sigma per axis


#: Up to this many matched points, outliers are found by trying every subset.
SMALL_SET = 7


def _subset_masks() -> tuple[np.ndarray, np.ndarray]:
    """Every subset of at least 3 of n points, smallest first, for n = 4 .. :data:`SMALL_SET`: masks
    (S, SMALL_SET) whose rows ``start[n]:start[n + 1]`` are those of n points (in their first n columns)."""
    masks, start = [], np.zeros(SMALL_SET + 2, dtype=np.int64)
    for n in range(SMALL_SET + 1):
        start[n] = sum(len(x) for x in masks)
        if n >= 4:
            masks.append([[i in c for i in range(SMALL_SET)] for k in range(3, n + 1) for c in combinations(range(n), k)])
    start[SMALL_SET + 1] = sum(len(x) for x in masks)
    return np.array([row for x in masks for row in x], dtype=np.bool_), start


SUBSET_MASKS, SUBSET_START = _subset_masks()


def refine(rotation: np.ndarray, pattern_vectors: np.ndarray, weights: np.ndarray, field: StarField,
           final_tolerance_rad: np.ndarray, start_tolerance_rad: float, iterations: int = 4) -> Refined:
    """Iterated Wahba fit with a tolerance shrinking to ``final_tolerance_rad``, then outlier rejection.

    ``weights`` are 1 / sigma^2 of each point.  Each iteration matches every
    point to its nearest star within the tolerance (each star to one point,
    the closest) and refits.  The last step drops, one at a time, the
    matched point whose leave-one-out residual (the angle to its star under
    Wahba's fit of the others) exceeds :data:`FINAL_REJECT_SIGMAS` times
    max(sigma_i, a robust scale of those residuals, so that real data with
    larger errors than stated keeps its stars) the most, and refits, while
    more than :data:`SMALL_SET` points remain; smaller sets (of the points
    within twice the tolerance of a star: a biased fit may have pushed a good
    one out) keep the largest subset of at least 3 whose Wahba fit they
    agree with within the noise, ties going to the smallest chi-square
    (leave-one-out cannot unmask two outliers among five).  One hypothesis
    of :func:`refine_many`.
    """
    return refine_many(np.asarray(rotation)[None], pattern_vectors, weights, field, final_tolerance_rad,
                       np.array([start_tolerance_rad], dtype=float), iterations)[0]


def refine_many(rotations: np.ndarray, pattern_vectors: np.ndarray, weights: np.ndarray, field: StarField,
                final_tolerance_rad: np.ndarray, start_tolerance_rad: np.ndarray,
                iterations: int = 4) -> list[Refined]:
    """:func:`refine` of K hypotheses (rotations (K, 3, 3), start tolerances (K,)).

    Each hypothesis is refined on its own by a compiled kernel
    (:func:`_refine_kernel`: a refinement is some 150 small steps on a dozen
    points, where numpy's call overhead was most of the cost); its stars
    within the largest tolerance come from the field's cell map
    (:mod:`app.identification.cells`), and the nearest star of the points
    with none that close (their angle enters the deviation only) from the
    KD-tree, once for the batch.
    """
    R = np.ascontiguousarray(np.array(rotations, dtype=float).reshape(-1, 3, 3))
    K, m = len(R), len(pattern_vectors)
    if K == 0:
        return []
    start = np.ascontiguousarray(np.broadcast_to(np.asarray(start_tolerance_rad, dtype=float).reshape(-1), (K,)))
    # A writable copy, as the kernel's own tolerances are: _assign_kernel compiled once, not also for a read-only
    # view (0.4 s of a first run's compilation).
    final_tol = np.array(np.broadcast_to(np.asarray(final_tolerance_rad, dtype=float), (m,)))
    vectors = np.ascontiguousarray(pattern_vectors, dtype=float)
    reach = max(float(np.max(start)), 2.0 * float(np.max(final_tol)))
    # Slightly beyond, so that rounding never loses a star at exactly the tolerance.
    bound = float(chord(reach)) * (1 + 1e-9) + 1e-15
    cells = cells_within(field, reach * (1 + 1e-6))
    weights = np.ascontiguousarray(weights, dtype=float)
    star, resid, nearest = np.empty((K, m), dtype=np.int64), np.empty((K, m)), np.empty((K, m))
    arrays = cells.kernel_arrays()
    for k in range(K):  # one call each: a batch kernel would double the first run's compilation
        R[k], star[k], resid[k], nearest[k] = _refine_kernel(R[k], vectors, weights, field.vectors, final_tol, start[k],
                                                             iterations, bound, arrays, SUBSET_MASKS, SUBSET_START)
    far = np.isnan(nearest)
    if far.any():
        k, i = np.nonzero(far)
        nearest[k, i] = chord_to_angle(field.nearest_chords(np.einsum("kj,kji->ki", vectors[i], R[k])))
    return [Refined(rotation=R[k], star_of_point=star[k], residual_rad=resid[k], nearest_rad=nearest[k])
            for k in range(K)]


#: Cell maps made here for fields that have none (an observer too fast or an epoch too far for the
#: sky's own maps, or a radius beyond them), by field and radius.
_own_cells: "weakref.WeakKeyDictionary[StarField, dict]" = weakref.WeakKeyDictionary()


def cells_within(field: StarField, radius_rad: float) -> NearStarCells:
    """A cell map of the field's stars for at least ``radius_rad``: the sky's (kept on disk), else one made
    from the field's own places (exact for them; 30-50 ms, kept with the field)."""
    cells = field.cells(radius_rad) if field.cells is not None else None
    if cells is not None:
        return cells
    own = _own_cells.setdefault(field, {})
    fitting = [c for r, c in own.items() if radius_rad <= r <= 2 * radius_rad]
    if fitting:
        return fitting[0]
    own[radius_rad * 1.2] = NearStarCells.build(field.vectors, radius_rad * 1.2)
    return own[radius_rad * 1.2]


# --- the compiled refinement ----------------------------------------------------------------

@njit
def _lower_quartile(x):
    """``np.quantile(x, 0.25)`` (linear interpolation, numpy's formula) of a short array."""
    v = x.copy()
    for i in range(1, v.shape[0]):  # insertion sort: a dozen values
        key, j = v[i], i - 1
        while j >= 0 and v[j] > key:
            v[j + 1] = v[j]
            j -= 1
        v[j + 1] = key
    position = 0.25 * (v.shape[0] - 1)
    lo = int(np.floor(position))
    t = position - lo
    if lo + 1 >= v.shape[0]:
        return v[lo]
    a, b = v[lo], v[lo + 1]
    return b - (b - a) * (1 - t) if t >= 0.5 else a + (b - a) * t


@njit
def _wahba_kernel(body, ref, w):
    """Wahba's rotation of ``body`` (n, 3) onto ``ref`` with weights ``w`` (:func:`app.attitude.solve_wahba`)."""
    B = np.zeros((3, 3))
    for i in range(body.shape[0]):
        for r in range(3):
            for c in range(3):
                B[r, c] += (body[i, r] * w[i]) * ref[i, c]
    return wahba_rotation(B)


@njit
def _residual_angle(body, R, ref):
    """Angle between ``body`` and ``R ref`` (arctan2 of the cross and dot products: exact at small angles)."""
    p0 = R[0, 0] * ref[0] + R[0, 1] * ref[1] + R[0, 2] * ref[2]
    p1 = R[1, 0] * ref[0] + R[1, 1] * ref[1] + R[1, 2] * ref[2]
    p2 = R[2, 0] * ref[0] + R[2, 1] * ref[1] + R[2, 2] * ref[2]
    c0, c1, c2 = body[1] * p2 - body[2] * p1, body[2] * p0 - body[0] * p2, body[0] * p1 - body[1] * p0
    return np.arctan2(np.sqrt(c0 * c0 + c1 * c1 + c2 * c2), body[0] * p0 + body[1] * p1 + body[2] * p2)


@njit
def _look_up(R, pattern_vectors, bound, star_vectors, cells):
    """Angle to the nearest star (nan: none within chord ``bound``) and that star (-1) of every rotated point."""
    G, words, word_rank, first, stars = cells
    m = pattern_vectors.shape[0]
    ang = np.full(m, np.nan)
    idx = np.full(m, -1, dtype=np.int64)
    for i in range(m):
        p0, p1, p2 = pattern_vectors[i, 0], pattern_vectors[i, 1], pattern_vectors[i, 2]
        d, s = nearest_star(p0 * R[0, 0] + p1 * R[1, 0] + p2 * R[2, 0], p0 * R[0, 1] + p1 * R[1, 1] + p2 * R[2, 1],
                            p0 * R[0, 2] + p1 * R[1, 2] + p2 * R[2, 2], star_vectors, G, words, word_rank, first, stars)
        if d <= bound:
            ang[i] = 2.0 * np.arcsin(min(d / 2, 1.0))
            idx[i] = s
    return ang, idx


@njit
def _assign_kernel(ang, idx, tol):
    """(star, residual) of :func:`_assign` for one hypothesis: a point matches its nearest star within its
    tolerance, and a star claimed by several points goes to the closest (the first on a tie)."""
    m = ang.shape[0]
    star = np.full(m, -1, dtype=np.int64)
    for i in range(m):
        if idx[i] >= 0 and ang[i] <= tol[i]:
            star[i] = idx[i]
    for i in range(m):
        if star[i] < 0:
            continue
        for j in range(i + 1, m):
            if star[j] == star[i]:
                if ang[j] < ang[i]:
                    star[i] = -1
                    break
                star[j] = -1
    resid = np.full(m, np.nan)
    for i in range(m):
        if star[i] >= 0:
            resid[i] = ang[i]
    return star, resid


@njit
def _consensus_kernel(body, ref, w, subsets):
    """:func:`consensus_subset` of one set of n (4-7) points: the agreeing points of the best subset's fit."""
    n = body.shape[0]
    sigma = np.empty(n)
    for i in range(n):
        sigma[i] = 1.0 / np.sqrt(w[i])
    best_count, best_chi2, best = -1, np.inf, np.zeros(n, dtype=np.bool_)
    agree = np.zeros(n, dtype=np.bool_)
    for k in range(subsets.shape[0]):
        B = np.zeros((3, 3))
        for i in range(n):
            if subsets[k, i]:
                for r in range(3):
                    for c in range(3):
                        B[r, c] += (w[i] * body[i, r]) * ref[i, c]
        R = wahba_rotation(B)
        count, chi2 = 0, 0.0
        for i in range(n):
            resid = _residual_angle(body[i], R, ref[i])
            agree[i] = resid <= FINAL_REJECT_SIGMAS * sigma[i]
            if agree[i]:
                count += 1
                chi2 += (resid / sigma[i]) ** 2
        if count > best_count or (count == best_count and chi2 < best_chi2):
            best_count, best_chi2, best = count, chi2, agree.copy()
    if best_count < 3:
        best[:] = True
    return best


@njit
def _loo_kernel(body, ref, w):
    """:func:`leave_one_out_residuals` of one set."""
    n = body.shape[0]
    B = np.zeros((3, 3))
    for i in range(n):
        for r in range(3):
            for c in range(3):
                B[r, c] += (w[i] * body[i, r]) * ref[i, c]
    out = np.empty(n)
    for i in range(n):
        Bi = B.copy()
        for r in range(3):
            for c in range(3):
                Bi[r, c] -= (w[i] * body[i, r]) * ref[i, c]
        out[i] = _residual_angle(body[i], wahba_rotation(Bi), ref[i])
    return out


@njit
def _count(star):
    """How many points matched a star (star >= 0)."""
    n = 0
    for i in range(star.shape[0]):
        n += star[i] >= 0
    return n


@njit
def _gather(pattern_vectors, star_vectors, weights, star):
    """(body, ref, w) of the points matched to a star (``star >= 0``): their directions, their stars' and
    their weights.  (Loops, not array expressions, here and in the kernels below: numba compiles an array
    expression's broadcasting in seconds, on the first run after an install.)"""
    n = 0
    for i in range(star.shape[0]):
        n += star[i] >= 0
    body, ref, w = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    k = 0
    for i in range(star.shape[0]):
        if star[i] >= 0:
            for c in range(3):
                body[k, c] = pattern_vectors[i, c]
                ref[k, c] = star_vectors[star[i], c]
            w[k] = weights[i]
            k += 1
    return body, ref, w


@njit
def _refine_kernel(R0, pattern_vectors, weights, star_vectors, final_tol, start, iterations, bound, cells,
                   subset_masks, subset_start):
    """One hypothesis's :func:`refine` (see there), every look-up within chord ``bound`` (>= the largest
    tolerance used, within the cell map's radius): (rotation, star_of_point, residual, nearest angle, nan
    where no star lies within ``bound``).  Plain loops: numba compiles them several times faster than array
    expressions (the first run's compilation)."""
    m = pattern_vectors.shape[0]
    R = R0.copy()
    fitted = np.full(m, -1, dtype=np.int64)
    star = np.full(m, -1, dtype=np.int64)
    resid = np.full(m, np.nan)
    have_final = False
    tol = np.empty(m)
    for it in range(iterations):
        f = it / max(1, iterations - 1)
        for i in range(m):
            tol[i] = max(final_tol[i], start * (1 - f) + final_tol[i] * f)
        ang, idx = _look_up(R, pattern_vectors, bound, star_vectors, cells)
        s, _ = _assign_kernel(ang, idx, tol)
        go = _count(s) >= 2
        if it > 0 and go:
            same = True
            for i in range(m):
                same = same and s[i] == fitted[i]
            if same:
                # Converged: refitting gives the same R, and once the final tolerance keeps these matches
                # too, so does every tolerance between.
                f_star, f_resid = _assign_kernel(ang, idx, final_tol)
                kept = True
                for i in range(m):
                    kept = kept and f_star[i] == s[i]
                if kept:
                    star, resid, have_final = f_star, f_resid, True
                    go = False
        if not go:
            break
        body, ref, w = _gather(pattern_vectors, star_vectors, weights, s)
        R = _wahba_kernel(body, ref, w)
        fitted = s
    nearest, idx = _look_up(R, pattern_vectors, bound, star_vectors, cells)
    if not have_final:
        star, resid = _assign_kernel(nearest, idx, final_tol)
    if m >= 3 and _count(star) <= SMALL_SET:
        # Few points: the largest subset that fits within the noise, among those near a star.
        near, _ = _assign_kernel(nearest, idx, 2 * final_tol)
        n = _count(near)
        if 3 <= n <= SMALL_SET:
            body, ref, w = _gather(pattern_vectors, star_vectors, weights, near)
            agree = np.ones(n, dtype=np.bool_)
            if n > 3:
                agree = _consensus_kernel(body, ref, w, subset_masks[subset_start[n]:subset_start[n + 1]])
            for k in range(n):
                if not agree[k]:
                    w[k] = 0.0
            R = _wahba_kernel(body, ref, w)
            nearest, idx = _look_up(R, pattern_vectors, bound, star_vectors, cells)
            fresh, f_resid = _assign_kernel(nearest, idx, final_tol)
            k = 0
            for i in range(m):
                keep = True
                if near[i] >= 0:
                    keep = agree[k]
                    k += 1
                star[i] = fresh[i] if (keep and fresh[i] >= 0) else -1
                resid[i] = f_resid[i] if star[i] >= 0 else np.nan
    if _count(star) > SMALL_SET:
        # Judge each point by the fit of the others: an outlier cannot hide by pulling the fit.
        sigma = np.empty(m)
        for i in range(m):
            sigma[i] = 1.0 / np.sqrt(weights[i])
        for _ in range(max(1, m // 3)):
            n = _count(star)
            if n <= SMALL_SET:
                break
            body, ref, w = _gather(pattern_vectors, star_vectors, weights, star)
            loo = _loo_kernel(body, ref, w)
            # The lower quartile: outliers pull the fit, inflating the others' residuals and the median.
            robust = _lower_quartile(loo) / RAYLEIGH_QUARTILE
            worst, worst_point, worst_ratio, k = 0, 0, -np.inf, 0
            for i in range(m):
                if star[i] >= 0:
                    ratio = loo[k] / max(sigma[i], robust)
                    if ratio > worst_ratio:
                        worst, worst_point, worst_ratio = k, i, ratio
                    k += 1
            if loo[worst] <= FINAL_REJECT_SIGMAS * max(sigma[worst_point], robust):
                break
            star = star.copy()
            star[worst_point] = -1
            body, ref, w = _gather(pattern_vectors, star_vectors, weights, star)
            R = _wahba_kernel(body, ref, w)
            nearest, idx = _look_up(R, pattern_vectors, bound, star_vectors, cells)
            fresh, f_resid = _assign_kernel(nearest, idx, final_tol)
            for i in range(m):
                star[i] = fresh[i] if (star[i] >= 0 and fresh[i] >= 0) else -1  # a rejected point stays out
                resid[i] = f_resid[i] if star[i] >= 0 else np.nan
    return R, star, resid, nearest


@warm_up_with
def _warm_up_refine() -> None:
    """Compile the refinement for the types the searches pass (three stars and three points)."""
    stars = np.array([[1.0, 0.0, 0.0], [0.99, 0.1, 0.0], [0.99, 0.0, 0.1], [0.98, 0.1, 0.1]])
    stars /= np.linalg.norm(stars, axis=1, keepdims=True)
    field = StarField.from_vectors(stars, np.arange(4))
    refine_many(np.eye(3)[None], stars, np.ones(4), field, np.full(4, 1e-3), np.array([2e-3]))


def local_density_per_sr(field: StarField, boresight: np.ndarray, radius_rad: float) -> float:
    """Stars per steradian of ``field`` within ``radius_rad`` of ``boresight`` (a unit vector, ICRS), never
    less than their mean over the sky.

    Chance matches are as likely as the stars are dense where the camera
    looks: the Milky Way holds two to three times the mean density, and a
    probability from the mean there is too small by that factor to the power
    of the chance points matched (a few hundredfold for five).
    """
    # The stars within the cap, by their cosines: as quick as a tree's count and needs no tree.
    count = int(np.count_nonzero(field.vectors @ np.asarray(boresight, dtype=float) >= np.cos(radius_rad)))
    cap_sr = 2 * np.pi * (1 - np.cos(radius_rad))
    return max(field.density_per_sr, count / cap_sr)


def false_match_probability(n_points: int, n_matched: int, capture_tolerance_rad: float,
                            density_per_sr: float, n_hypotheses: int, sum_sq_residual_rad2: float,
                            n_fitted: int = 0) -> float:
    """Expected number of chance matches as good as this one (capped at 1); see the module doc.

    Two factors: enough points captured, ``N * P[Binomial(m - 2, p) >= k - 2]``,
    and, given that, a least-squares fit as tight as the one found.  A chance
    point captured within ``r`` sits uniformly in that disc (variance r^2/4
    per axis), so the sum of squared residuals of such points is at most
    ~ (r^2/4) chi^2(d) and ``P[fit this tight] = chi2.cdf(4 S / r^2, d)``.
    (The Gaussian has twice the uniform disc's density at zero, so this errs
    on the safe, larger side.)  Of the 2k coordinates the attitude absorbs 3,
    and the generating pair's separation, matched by the index lookup, is no
    chance evidence: ``d = 2k - 4``.  Optical parameters fitted with the
    attitude (``n_fitted``: the focal length, k1) absorb one more each:
    ``d = 2k - 4 - n_fitted``.  Refinement keeps, when :data:`SMALL_SET` points
    or fewer remain, the largest subset that agrees within the noise (tried
    among all of them: :func:`refine`), so a fit of ``k`` such points is the
    tightest of up to ``C(min(m, SMALL_SET) - 2, k - 2)`` subsets, and its
    probability is multiplied by that count (1 when every point matched, and
    for larger sets, whose leave-one-out rejection follows a single path).
    Charging ``C(m - 2, k - 2)`` instead left real frames of 16-32 points
    ambiguous; counting only the points within reach at the end (the
    rotation moves while refining) left 4-6 wrong candidates of 1,200 below
    1e-3 in ``bench --suite camera``.

    Measured over 1,600 simulated cases (``bench --suite camera --n 100``):
    without the last two terms, 35 of the 1,233 candidates put below 1e-3
    were wrong, all of them 3-5 matched points of 10 or more.
    """
    if n_matched < 3 or n_points < 3:
        return 1.0
    r = float(capture_tolerance_rad)
    p = 1.0 - np.exp(-density_per_sr * np.pi * r * r)
    capture = float(bdtrc(n_matched - 3, n_points - 2, p))  # P[X >= k - 2] = P[X > k - 3]
    dof = 2 * n_matched - 4 - n_fitted
    subsets = math.comb(min(n_points, SMALL_SET) - 2, n_matched - 2) if n_matched <= SMALL_SET else 1
    tight = min(1.0, subsets * float(chdtr(dof, 4.0 * sum_sq_residual_rad2 / (r * r)))) if dof > 0 else 1.0
    return float(min(1.0, max(1, n_hypotheses) * capture * tight))
