"""Which stars lie near which parts of the sky: a cube-map grid for checking thousands of hypotheses.

Why.  Checking a batch of hypotheses maps every pattern point of every
hypothesis onto the sky (2,600 hypotheses x 10 points from a first edge on
the 20 deg camera) and asks for its nearest star within the check tolerance.
About 96 % of those points have no star that close, and a KD-tree spends
~0.4 microseconds on each to find that out, 10 ms a batch.  Here each point
is put in its cell of a grid over the sky (a dozen array operations for all
of them); a bitmap says whether any star lies within ``radius`` of some point
of that cell, and for the few cells that have one, the list of those stars
gives the nearest.  The answer is the KD-tree's, bit for bit: the same
distances (the same sum of squares), and every star within the radius of a
point is on its cell's list, by construction.

The grid.  The six faces of the cube around the sphere, each divided into
``G x G`` cells in the gnomonic coordinates ``(u, v) = (x_b / |x_a|,
x_c / |x_a|)`` of the face whose axis ``a`` dominates the point.  A star
marks, on every face it can reach, the cells of the square ``(u_s, v_s) +/-
r sec^2(theta + r)``, ``theta`` its angle from the face's centre: the
gnomonic projection stretches no length by more than ``sec^2`` of the angle
from its centre, so that square holds the projection of every point within
``r`` of the star.

Static.  A map is made from the stars' mean places at the index epoch, each
star's radius grown by how far its apparent place can be from there: its
proper motion over :data:`MAX_YEARS` years plus aberration (the Earth's
orbital speed and up to :data:`MAX_SPACECRAFT_SPEED_KM_S` of the
spacecraft's).  So one map serves every observation time (a new hour costs
nothing here), and :class:`app.identification.sky.Sky` keeps it on disk.
"""

from __future__ import annotations

import math

import numpy as np

from app.attitude.rotations import pair_triad, rotation_into, triads_rotation
from app.compiled import njit, warm_up_with

#: The map holds for observation times within this many years of the stars' epoch ...
MAX_YEARS = 100.0
#: ... and spacecraft speeds up to this (escape velocity is 11.2 km/s).
MAX_SPACECRAFT_SPEED_KM_S = 12.0
#: The Earth's orbital speed never exceeds 30.3 km/s.
MAX_EARTH_SPEED_KM_S = 30.4
SPEED_OF_LIGHT_KM_S = 299792.458
#: Most cells per face edge (6 x 1024^2 bits = 768 kB).
MAX_CELLS_PER_EDGE = 1024
#: Cells per radius: a cell is 1/this radii wide.  Coarse on purpose: a search checks its points against
#: the bitmap in an order no cache predicts, and a bitmap that stays in the processor's cache (6 x 213^2 bits,
#: 34 kB, for a 10-pixel radius on the 20 deg camera) beats a finer one that does not, though more of it is
#: marked and its lists are longer (single snapshots 8.9 -> 7.3 ms, 10 random points 97 -> 74 ms of CPU,
#: against 3 cells per radius: 768 kB; measured 3, 1, 0.7, 0.5, 0.35, 0.25).
CELLS_PER_RADIUS = 0.5
#: The angle of a cube face's corner from its centre, arctan(sqrt 2).
_CORNER = math.atan(math.sqrt(2.0))


def _ragged(counts: np.ndarray) -> np.ndarray:
    """``i`` repeated ``counts[i]`` times, for every i."""
    return np.repeat(np.arange(len(counts)), counts)


def _ragged_offsets(counts: np.ndarray) -> np.ndarray:
    """0, 1, ..., counts[i] - 1 for every i, concatenated."""
    total = int(counts.sum())
    return np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)


def _popcount(words: np.ndarray) -> np.ndarray:
    """Set bits of each uint64 (numpy >= 2 counts them natively; before, byte by byte)."""
    if hasattr(np, "bitwise_count"):
        return np.bitwise_count(words).astype(np.int64)
    as_bytes = words.view(np.uint8).reshape(*words.shape, 8)
    return np.unpackbits(as_bytes, axis=-1).sum(axis=-1, dtype=np.int64)


def motion_margin_rad(pm_ra_cosdec_mas_yr: np.ndarray, pm_dec_mas_yr: np.ndarray) -> np.ndarray:
    """How far each star's apparent place can be from its mean place at the index epoch (radians)."""
    pm = np.hypot(pm_ra_cosdec_mas_yr, pm_dec_mas_yr) * (math.pi / (180 * 3600 * 1000))
    aberration = (MAX_EARTH_SPEED_KM_S + MAX_SPACECRAFT_SPEED_KM_S) / SPEED_OF_LIGHT_KM_S
    # A little more for the second-order terms of both (below 1e-8 rad) and rounding.
    return pm * MAX_YEARS * 1.001 + aberration * 1.01 + 1e-9


def cells_of(points: np.ndarray, cells_per_edge: int) -> np.ndarray:
    """The cube-map cell of each unit vector (N, 3): ``(face G + i_u) G + i_v``, face = 2 axis + (negative).

    The face is that of the largest coordinate (the first on a tie), ``i_u`` and ``i_v`` the cells of
    the other two coordinates divided by it.  Written with masks and products rather than fancy
    indexing or ``np.where`` (several times slower on 30,000 points), and int32 casts (the int64 one is
    not vectorised).
    """
    G = cells_per_edge
    x, y, z = np.ascontiguousarray(points.T)
    ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
    on_x = (ax >= ay) & (ax >= az)
    on_y = ~on_x & (ay >= az)
    on_z = ~(on_x | on_y)
    inv = 1.0 / np.maximum(np.maximum(ax, ay), az)
    half = G / 2
    # One of the three products is the coordinate, the other two are zero.
    u = ((on_x * y + on_y * z + on_z * x) * inv + 1.0) * half
    v = ((on_x * z + on_y * x + on_z * y) * inv + 1.0) * half
    face = on_y * 2 + on_z * 4 + ((on_x * x + on_y * y + on_z * z) < 0)
    iu = np.minimum(u.astype(np.int32), G - 1)
    iv = np.minimum(v.astype(np.int32), G - 1)
    return (face * G + iu) * G + iv


class NearStarCells:
    """The cube-map cells that have a star within ``radius_rad`` of some point in them, with those stars.

    ``maybe_near`` is the bitmap's answer (one look-up per point);
    ``nearest_within`` the nearest star's chord for each point, exactly as a
    KD-tree query bounded at the radius would give it (the same sum of
    squares), from the few stars listed for its cell.
    """

    #: Bump when what a map holds changes (its disk cache, :meth:`arrays`, is then made again).
    FORMAT = 2

    def __init__(self, radius_rad: float, cells_per_edge: int, words: np.ndarray, first: np.ndarray,
                 stars: np.ndarray) -> None:
        self.radius_rad = float(radius_rad)
        self.cells_per_edge = int(cells_per_edge)
        # Bit i of word w: cell 64 w + i.  A marked cell's rank (how many marked cells come before it) is
        # its word's rank plus the marked bits below it in the word: its row in ``first``.
        self._words = words
        self._word_rank = np.cumsum(_popcount(words)) - _popcount(words)
        # The stars of the marked cell of rank k: stars[first[k]:first[k + 1]].
        self._first = first
        self._stars = stars

    @property
    def fraction_marked(self) -> float:
        return float(self._word_rank[-1] + _popcount(self._words[-1:])[0]) / (6 * self.cells_per_edge ** 2)

    def arrays(self) -> dict[str, np.ndarray]:
        """What :meth:`from_arrays` needs, for a disk cache."""
        return {"format": np.array(self.FORMAT), "radius_rad": np.array(self.radius_rad),
                "cells_per_edge": np.array(self.cells_per_edge), "words": self._words,
                "first": self._first.astype(np.int32, copy=False), "stars": self._stars.astype(np.uint16, copy=False)}

    @classmethod
    def from_arrays(cls, arrays) -> "NearStarCells":
        if int(arrays["format"]) != cls.FORMAT:
            raise ValueError(f"cell map format {int(arrays['format'])}, expected {cls.FORMAT}")
        return cls(float(arrays["radius_rad"]), int(arrays["cells_per_edge"]), arrays["words"],
                   arrays["first"], arrays["stars"])

    @classmethod
    def build(cls, vectors: np.ndarray, radius_rad: float, margins_rad: np.ndarray | float = 0.0) -> "NearStarCells":
        """The map of stars ``vectors`` (unit vectors at the epoch the margins are counted from), each
        star's radius grown by its margin (~30 ms for 6,000 stars)."""
        if len(vectors) >= 1 << 16:
            raise ValueError("at most 65,535 stars")
        r = float(radius_rad) + np.broadcast_to(np.asarray(margins_rad, dtype=float), (len(vectors),))
        G = int(min(MAX_CELLS_PER_EDGE, max(8, math.ceil(2.0 * CELLS_PER_RADIUS / float(radius_rad)))))
        cell_parts, star_parts = [], []
        for face in range(6):
            axis, sign = divmod(face, 2)
            c = (1.0 - 2.0 * sign) * vectors[:, axis]  # cosine of the angle from the face's centre
            reach = np.minimum(_CORNER + r, math.pi / 2 - 1e-6)
            rows = np.flatnonzero(c > np.cos(reach))
            if len(rows) == 0:
                continue
            cc = c[rows]
            u = vectors[rows, (axis + 1) % 3] / cc
            v = vectors[rows, (axis + 2) % 3] / cc
            theta = np.arccos(np.minimum(cc, 1.0))
            half = r[rows] / np.cos(np.minimum(theta + r[rows], math.pi / 2 - 1e-6)) ** 2 * (1 + 1e-9) + 1e-12
            lo_u, hi_u = cls._span(u, half, G)
            lo_v, hi_v = cls._span(v, half, G)
            keep = (lo_u <= hi_u) & (lo_v <= hi_v)
            rows, lo_u, lo_v = rows[keep], lo_u[keep], lo_v[keep]
            wu, wv = hi_u[keep] - lo_u + 1, hi_v[keep] - lo_v + 1
            # Every cell of every square: the columns of each square, then the cells of each column.
            k = _ragged(wu)
            iu = lo_u[k] + _ragged_offsets(wu)
            kk = _ragged(wv[k])
            iv = lo_v[k][kk] + _ragged_offsets(wv[k])
            cell_parts.append((face * G + iu[kk]) * G + iv)
            star_parts.append(rows[k][kk])
        cells = np.concatenate(cell_parts).astype(np.int64) if cell_parts else np.zeros(0, np.int64)
        stars = np.concatenate(star_parts).astype(np.int64) if star_parts else np.zeros(0, np.int64)
        marked = np.zeros(-(-6 * G * G // 64) * 64, dtype=bool)
        marked[cells] = True
        words = np.packbits(marked, bitorder="little").view("<u8")
        # The stars of each marked cell, cell after cell (sorting packed (cell, star) keys is four times
        # faster than an argsort).
        keys = np.sort((cells << 16) | stars)
        cells, stars = keys >> 16, keys & 0xFFFF
        first = np.append(np.flatnonzero(np.r_[True, cells[1:] != cells[:-1]]), len(cells))
        return cls(radius_rad, G, words, first.astype(np.int32), stars.astype(np.uint16))

    @staticmethod
    def _span(u: np.ndarray, half: np.ndarray, G: int) -> tuple[np.ndarray, np.ndarray]:
        """First and last cell index of [u - half, u + half] on a face edge of G cells (lo > hi: off the face)."""
        lo = np.floor((u - half + 1.0) * (G / 2)).astype(np.int64)
        hi = np.floor((u + half + 1.0) * (G / 2)).astype(np.int64)
        return np.maximum(lo, 0), np.minimum(hi, G - 1)

    def _marked(self, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(whether each cell is marked, its word) for int cell numbers."""
        word = self._words[cell >> 6]
        return ((word >> (cell & 63).astype(np.uint64)) & np.uint64(1)).astype(bool), word

    def maybe_near(self, points: np.ndarray) -> np.ndarray:
        """(N,) False where a unit vector has no star within the radius (True: perhaps)."""
        return self._marked(cells_of(points, self.cells_per_edge))[0]

    def nearest_within(self, points: np.ndarray, star_vectors: np.ndarray, bound_chord: float) -> np.ndarray:
        """(N,) chord from each point to its nearest star if that is at most ``bound_chord`` (<= the
        radius's chord), else inf: ``cKDTree(star_vectors).query(points, distance_upper_bound=...)[0]``.

        ``star_vectors`` are the stars' places now (within their margins of the ones the map was made from).
        """
        points = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
        return _nearest_within_kernel(points, np.ascontiguousarray(star_vectors, dtype=float), float(bound_chord),
                                      *self.kernel_arrays())

    def brightest_within(self, points: np.ndarray, star_vectors: np.ndarray, mag: np.ndarray, bound_chord: float,
                         neighbours: int) -> np.ndarray:
        """(N,) the brightest (smallest ``mag``) of the ``neighbours`` stars nearest each point within
        ``bound_chord`` (<= the radius's chord), the nearest of equals; -1 where none is that close: a
        KD-tree's ``query(points, k=neighbours, distance_upper_bound=...)`` then the brightest of those."""
        points = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
        return _brightest_within_kernel(points, np.ascontiguousarray(star_vectors, dtype=float),
                                        np.ascontiguousarray(mag, dtype=float), float(bound_chord), int(neighbours),
                                        *self.kernel_arrays())

    def kernel_arrays(self) -> tuple:
        """The map as the compiled kernels take it: (cells per edge, words, word ranks, first, stars)."""
        return (self.cells_per_edge, self._words, self._word_rank, self._first, self._stars)


# --- compiled look-ups: one point at a time, no temporaries ----------------------------------

@njit
def _popcount64(x):
    """Set bits of a uint64 (the SWAR count)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


@njit
def cell_of(x, y, z, G):
    """:func:`cells_of` of one unit vector."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        top, cu, cv, face = ax, y, z, 0 + (x < 0)
    elif ay >= az:
        top, cu, cv, face = ay, z, x, 2 + (y < 0)
    else:
        top, cu, cv, face = az, x, y, 4 + (z < 0)
    inv = 1.0 / top
    half = G / 2
    iu = min(np.int64(np.int32((cu * inv + 1.0) * half)), G - 1)
    iv = min(np.int64(np.int32((cv * inv + 1.0) * half)), G - 1)
    return (face * G + iu) * G + iv


@njit
def _nearest_chords(points, star_vectors, bound, G, words, word_rank, first, stars):
    """(N,) chord from each point (N, 3) to its nearest star if within ``bound``, else inf (see
    :meth:`NearStarCells.nearest_within`).  Two passes: every point's cell and bit first (independent
    loads, which the processor overlaps: the bitmap is larger than its cache), then the few marked cells'
    star lists."""
    n = points.shape[0]
    out = np.full(n, np.inf)
    cell = np.empty(n, dtype=np.int64)
    marked = np.empty(n, dtype=np.bool_)
    for i in range(n):
        c = cell_of(points[i, 0], points[i, 1], points[i, 2], G)
        cell[i] = c
        marked[i] = (words[c >> 6] >> np.uint64(c & 63)) & np.uint64(1) != 0
    for i in range(n):
        if marked[i]:
            d2, _ = _nearest_listed(points[i, 0], points[i, 1], points[i, 2], cell[i], star_vectors, words,
                                    word_rank, first, stars)
            d = np.sqrt(d2)
            if d <= bound:
                out[i] = d
    return out


@njit
def listed_stars(c, words, word_rank, first):
    """(begin, end): where marked cell ``c``'s stars lie in the map's star list (its rank among the marked
    cells: its word's rank plus the marked bits below it in the word)."""
    word = words[c >> 6]
    rank = word_rank[c >> 6] + _popcount64(word & ((np.uint64(1) << np.uint64(c & 63)) - np.uint64(1)))
    return first[rank], first[rank + 1]


@njit
def _nearest_listed(x, y, z, c, star_vectors, words, word_rank, first, stars):
    """(squared chord, star) of the nearest star listed for marked cell ``c`` of the unit vector (x, y, z)."""
    begin, end = listed_stars(c, words, word_rank, first)
    best, star = np.inf, -1
    for k in range(begin, end):
        s = np.int64(stars[k])
        dx, dy, dz = x - star_vectors[s, 0], y - star_vectors[s, 1], z - star_vectors[s, 2]
        d2 = (dx * dx + dy * dy) + dz * dz  # a KD-tree's order: the same sums, bit for bit
        if d2 < best:
            best, star = d2, s
    return best, star


@njit
def nearest_star(x, y, z, star_vectors, G, words, word_rank, first, stars):
    """(chord, star) from the unit vector (x, y, z) to its nearest star within the map's radius; (inf, -1)
    when none is that close (one point: a refinement's look-up)."""
    c = cell_of(x, y, z, G)
    if (words[c >> 6] >> np.uint64(c & 63)) & np.uint64(1) == 0:
        return np.inf, -1
    d2, star = _nearest_listed(x, y, z, c, star_vectors, words, word_rank, first, stars)
    return np.sqrt(d2), star


@njit
def _brightest_within_kernel(points, star_vectors, mag, bound, neighbours, G, words, word_rank, first, stars):
    """See :meth:`NearStarCells.brightest_within`: the listed stars of each point's cell within ``bound``,
    the ``neighbours`` nearest kept in order (an insertion into a short sorted list), the brightest of them."""
    n = points.shape[0]
    out = np.full(n, -1, dtype=np.int64)
    near_d2 = np.empty(neighbours)
    near_star = np.empty(neighbours, dtype=np.int64)
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        c = cell_of(x, y, z, G)
        if (words[c >> 6] >> np.uint64(c & 63)) & np.uint64(1) == 0:
            continue
        begin, end = listed_stars(c, words, word_rank, first)
        count = 0
        for k in range(begin, end):
            s = np.int64(stars[k])
            dx, dy, dz = x - star_vectors[s, 0], y - star_vectors[s, 1], z - star_vectors[s, 2]
            d2 = (dx * dx + dy * dy) + dz * dz
            if np.sqrt(d2) > bound:
                continue
            j = min(count, neighbours - 1)
            if count == neighbours and d2 >= near_d2[j]:
                continue
            while j > 0 and near_d2[j - 1] > d2:
                near_d2[j], near_star[j] = near_d2[j - 1], near_star[j - 1]
                j -= 1
            near_d2[j], near_star[j] = d2, s
            count = min(count + 1, neighbours)
        if count:
            best = 0
            for j in range(1, count):
                if mag[near_star[j]] < mag[near_star[best]]:
                    best = j
            out[i] = near_star[best]
    return out


@njit
def _nearest_within_kernel(points, star_vectors, bound, G, words, word_rank, first, stars):
    return _nearest_chords(points, star_vectors, bound, G, words, word_rank, first, stars)


@njit
def check_kernel(rotations, pattern_vectors, tolerance, star_vectors, bound, G, words, word_rank, first, stars):
    """(matches (H,), capped deviation (H,)) of hypotheses ``rotations`` (H, 3, 3): each pattern point mapped
    onto the sky (``R^T p``), the angle to its nearest star within ``bound`` (a chord; pi beyond it), a match
    within ``tolerance[h]``, the deviation the sum of min(angle, tolerance[h]).  See
    :func:`app.identification.verify.check_hypotheses`."""
    H, m = rotations.shape[0], pattern_vectors.shape[0]
    points = np.empty((H * m, 3))
    for h in range(H):
        R = rotations[h]
        for i in range(m):
            p0, p1, p2 = pattern_vectors[i, 0], pattern_vectors[i, 1], pattern_vectors[i, 2]
            points[h * m + i, 0] = p0 * R[0, 0] + p1 * R[1, 0] + p2 * R[2, 0]
            points[h * m + i, 1] = p0 * R[0, 1] + p1 * R[1, 1] + p2 * R[2, 1]
            points[h * m + i, 2] = p0 * R[0, 2] + p1 * R[1, 2] + p2 * R[2, 2]
    d = _nearest_chords(points, star_vectors, bound, G, words, word_rank, first, stars)
    n_match = np.zeros(H, dtype=np.int64)
    deviation = np.zeros(H)
    for h in range(H):
        tol = tolerance[h]
        count, total = 0, 0.0
        for i in range(m):
            chord = d[h * m + i]
            angle = 2.0 * np.arcsin(min(chord / 2, 1.0)) if chord <= bound else np.pi
            if angle <= tol:
                count += 1
                total += angle
            else:
                total += tol
        n_match[h], deviation[h] = count, total
    return n_match, deviation


@njit
def check_pairs_kernel(pattern_vectors, steps, pattern_edge, catalogue_pair, index_vectors, tolerance, min_matches,
                       star_vectors, bound, G, words, word_rank, first, stars):
    """:func:`check_kernel` of the rotations of :func:`app.attitude.rotation_from_pair` (edge ``pattern_edge[h]``'s
    points, seen at focal length ``steps[h]`` (``pattern_vectors`` (S, m, 3)), onto index stars
    ``catalogue_pair[h]``), each made where it is checked, keeping those that match ``min_matches`` points or
    more: (their rows (K,), matches (K,), capped deviations (K,), rotations (K, 3, 3)); a star is looked for
    within chord ``bound[steps[h]]``.

    The same numbers as making every rotation (the same triads and products) and checking those of each focal
    length with :func:`check_kernel`, without an (H, 3, 3) array of rotations or an (H m, 3) one of sky points.  Each
    hypothesis's points are put in their cells first, then the marked ones looked up in their cells' star
    lists (independent loads the processor overlaps; one pass with a branch per point took a fifth longer),
    the points off the edge first: the edge's own two land on their stars (the costliest look-ups), and are
    looked up only when the others could make ``min_matches`` with them (a third of the hypotheses of a
    pattern that matches nothing).  The deviation is summed in the points' order, as :func:`check_kernel`
    sums it.
    """
    H, m = pattern_edge.shape[0], pattern_vectors.shape[1]
    rows = np.empty(H, dtype=np.int64)
    n_match = np.empty(H, dtype=np.int64)
    deviation = np.empty(H)
    rotations = np.empty((H, 3, 3))
    kept = 0
    sky = np.empty((m, 3))  # the hypothesis's points on the sky, R^T p
    cell = np.empty(m, dtype=np.int64)
    marked = np.empty(m, dtype=np.int64)  # the points whose cell is marked, off the edge first
    angles = np.empty(m)
    visit = np.empty(m, dtype=np.int64)  # the points off the edge in order, then the edge's two
    last_step, last_i, last_j = -1, -1, -1
    Tb = (0.0,) * 9
    for h in range(H):
        step, i, j = steps[h], pattern_edge[h, 0], pattern_edge[h, 1]
        v = pattern_vectors[step]
        if step != last_step or i != last_i or j != last_j:  # a batch holds each edge's pairs together
            Tb = pair_triad(v[i, 0], v[i, 1], v[i, 2], v[j, 0], v[j, 1], v[j, 2])
            n = 0
            for k in range(m):
                if k != i and k != j:
                    visit[n] = k
                    n += 1
            visit[m - 2], visit[m - 1] = i, j
            last_step, last_i, last_j = step, i, j
        a, b = catalogue_pair[h, 0], catalogue_pair[h, 1]
        R = triads_rotation(Tb, pair_triad(index_vectors[a, 0], index_vectors[a, 1], index_vectors[a, 2],
                                           index_vectors[b, 0], index_vectors[b, 1], index_vectors[b, 2]))
        n_marked = 0
        for n in range(m):
            k = visit[n]
            p0, p1, p2 = v[k, 0], v[k, 1], v[k, 2]
            x = p0 * R[0] + p1 * R[3] + p2 * R[6]
            y = p0 * R[1] + p1 * R[4] + p2 * R[7]
            z = p0 * R[2] + p1 * R[5] + p2 * R[8]
            sky[k, 0], sky[k, 1], sky[k, 2] = x, y, z
            c = cell_of(x, y, z, G)
            cell[k] = c
            angles[k] = np.pi
            marked[n_marked] = k
            n_marked += np.int64((words[c >> 6] >> np.uint64(c & 63)) & np.uint64(1))  # no branch
        tol = tolerance[h]
        off_edge = 0  # matches among the points off the edge
        for n in range(n_marked):
            k = marked[n]
            if (k == i or k == j) and off_edge + 2 < min_matches:
                break
            # _nearest_listed's loop written out: a call here (its arrays passed field by field) cost a
            # quarter of the check.
            x, y, z = sky[k, 0], sky[k, 1], sky[k, 2]
            begin, end = listed_stars(cell[k], words, word_rank, first)
            d2 = np.inf
            for q in range(begin, end):
                s = np.int64(stars[q])
                dx, dy, dz = x - star_vectors[s, 0], y - star_vectors[s, 1], z - star_vectors[s, 2]
                d2 = min(d2, (dx * dx + dy * dy) + dz * dz)  # a KD-tree's order, as _nearest_listed's
            d = np.sqrt(d2)
            if d <= bound[step]:
                angles[k] = 2.0 * np.arcsin(min(d / 2, 1.0))
                off_edge += angles[k] <= tol and k != i and k != j
        if off_edge + 2 < min_matches:
            continue
        count, total = 0, 0.0
        for k in range(m):
            if angles[k] <= tol:
                count += 1
                total += angles[k]
            else:
                total += tol
        if count >= min_matches:
            rows[kept], n_match[kept], deviation[kept] = h, count, total
            rotation_into(rotations[kept], R)
            kept += 1
    return rows[:kept], n_match[:kept], deviation[:kept], rotations[:kept]


@warm_up_with
def _warm_up_cells() -> None:
    """Compile the look-ups for the types the searches pass (a map of two stars)."""
    stars = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    cells = NearStarCells.build(stars, 0.01)
    cells.nearest_within(stars, stars, 0.01)
    cells.brightest_within(stars, stars, np.zeros(2), 0.01, 4)
    check_kernel(np.eye(3)[None], stars, np.array([0.01]), stars, 0.01, *cells.kernel_arrays())
    pair = np.array([[0, 1]])
    check_pairs_kernel(stars[None], np.zeros(1, dtype=np.int64), pair, pair, stars, np.array([0.01]), 3, stars,
                       np.array([0.01]), *cells.kernel_arrays())
