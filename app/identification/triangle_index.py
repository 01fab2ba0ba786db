"""The bright triangles of the bright-pair index, looked up by their shape.

The seed's bright pairs (:mod:`app.index`) are the edges of the bright
triangles, whose enclosing disc holds only fainter stars.  A pattern
triangle of the Delaunay triangulation whose circumcircle lies in the sensor
holds no pattern point, and the pattern is the field's brightest sources, so
it is bright: its three sides are bright pairs
(:func:`app.identification.hypotheses.delaunay_triangles`).  The triangles of
the index are taken as every three stars joined pairwise by bright pairs (a
superset of the bright triangles: complete, and only a little larger).

Shape key.  Sides sorted ``s1 <= s2 <= s3``; the key is ``(s1/s3, s2/s3)``,
and the corners are named by the side opposite them (corner 0 opposite
``s1``, ...), so the longest side joins corners 0 and 1.  A rotation cannot
mirror, so the sense of the corners (the sign of ``det[v0 v1 v2]``) must
agree too.  A shape does not change with the scale: one lookup finds the
triangles a pattern triangle can be whatever the focal length
(:mod:`.focal_estimate`; tetra3's "hashed" pattern lookup works the same
way, with four stars).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from app.compiled import njit, warm_up_with
from app.identification.verify import chord_to_angle
from app.index import BrightPairIndex


@dataclass(frozen=True, eq=False)
class BrightTriangles:
    """Every three stars of the index joined pairwise by bright pairs, sorted by their first shape ratio.

    ``corners`` (T, 3) are index rows named by the opposite side, shortest
    first; ``ratio1``/``ratio2`` the shorter sides over the longest;
    ``longest_rad`` the longest side; ``sense`` the sign of
    ``det[v0 v1 v2]`` (mean places; no triangle of bright pairs is that
    flat); ``faintest`` the largest of its corners' rows (the index's stars
    are sorted brightest first, so a field down to a magnitude is a prefix).
    """

    FORMAT = 1  # of :meth:`arrays`, for the disk cache (:meth:`app.identification.sky.Sky.bright_triangles`)

    corners: np.ndarray
    ratio1: np.ndarray
    ratio2: np.ndarray
    longest_rad: np.ndarray
    sense: np.ndarray
    faintest: np.ndarray  # (T,) the largest corner row (stars are sorted brightest first)

    def __len__(self) -> int:
        return int(self.corners.shape[0])

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def sides_of(v: np.ndarray) -> np.ndarray:
    """(T, 3) angles of the sides opposite corners 0, 1, 2 of the triangles ``v`` (T, 3, 3)."""
    def angle(a, b):
        return chord_to_angle(np.linalg.norm(a - b, axis=-1))
    return np.column_stack([angle(v[:, 1], v[:, 2]), angle(v[:, 0], v[:, 2]), angle(v[:, 0], v[:, 1])])


def _named(corners: np.ndarray, sides: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners and sides reordered so that side k (opposite corner k) grows with k."""
    order = np.argsort(sides, axis=1, kind="stable")
    return np.take_along_axis(corners, order, axis=1), np.take_along_axis(sides, order, axis=1)


def sense_of(v: np.ndarray) -> np.ndarray:
    """(T,) the sign of ``det[v0 v1 v2]`` of the triangles ``v`` (T, 3, 3): which way round the corners go."""
    return np.sign(np.einsum("ti,ti->t", v[:, 0], np.cross(v[:, 1], v[:, 2])))


def bright_triangles(index: BrightPairIndex) -> BrightTriangles:
    """The triangles of ``index``'s bright pairs (about 90,000 for the stars to Hp 6.5; 0.15 s)."""
    n = index.n_stars
    a = np.minimum(index.star_a, index.star_b).astype(np.int64)
    b = np.maximum(index.star_a, index.star_b).astype(np.int64)
    keys = np.sort(a * n + b)
    # Each star's neighbours, sorted; a triangle x < y < z is found once, at its corner x, as two of x's
    # neighbours y < z that are themselves a bright pair.
    u, w = np.concatenate([a, b]), np.concatenate([b, a])
    order = np.lexsort((w, u))
    u, w = u[order], w[order]
    start = np.searchsorted(u, np.arange(n + 1))
    degree = np.diff(start)
    found = []
    for d in np.unique(degree[degree >= 2]).tolist():
        x = np.flatnonzero(degree == d)
        neighbours = w[start[x][:, None] + np.arange(d)]
        i, j = np.triu_indices(d, k=1)
        y, z = neighbours[:, i], neighbours[:, j]
        wedge = x[:, None] < y
        x3 = np.broadcast_to(x[:, None], y.shape)[wedge]
        y, z = y[wedge], z[wedge]
        k = y * n + z
        at = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
        joined = keys[at] == k
        found.append(np.column_stack([x3[joined], y[joined], z[joined]]))
    corners = np.concatenate(found) if found else np.empty((0, 3), np.int64)
    corners, sides = _named(corners, sides_of(index.vectors[corners]))
    order = np.argsort(sides[:, 0] / sides[:, 2], kind="stable")
    corners, sides = corners[order], sides[order]
    return BrightTriangles(corners=corners.astype(np.int32), ratio1=sides[:, 0] / sides[:, 2],
                           ratio2=sides[:, 1] / sides[:, 2], longest_rad=sides[:, 2],
                           sense=sense_of(index.vectors[corners]).astype(np.int8),
                           faintest=corners.max(axis=1).astype(np.int32))


def shape_matches(triangles: BrightTriangles, ratio1: float, ratio2: float, sense: int, tolerance: float,
                  longest_lo: float, longest_hi: float, star_limit: int) -> np.ndarray:
    """Rows of ``triangles`` whose shape is within ``tolerance`` of (ratio1, ratio2), of the same sense,
    with the longest side in [longest_lo, longest_hi] and every corner among the first ``star_limit``
    stars: the run of the first ratio found by a binary search, the rest tested in one compiled loop
    (:func:`_matching_rows`; numpy's half-dozen calls took ~80 us a lookup, two dozen a search)."""
    lo, hi = np.searchsorted(triangles.ratio1, [ratio1 - tolerance, ratio1 + tolerance]).tolist()
    return _matching_rows(lo, hi, triangles.ratio2, float(ratio2), float(tolerance), triangles.sense, int(sense),
                          triangles.longest_rad, float(longest_lo), float(longest_hi), triangles.faintest,
                          int(star_limit))


@njit
def _matching_rows(lo, hi, ratio2, wanted_ratio2, tolerance, sense, wanted_sense, longest, longest_lo, longest_hi,
                   faintest, star_limit):
    """The rows in ``lo:hi`` whose second ratio is within ``tolerance`` of ``wanted_ratio2``, of that sense, the
    longest side in [longest_lo, longest_hi] and the faintest corner below ``star_limit``, in order."""
    rows = np.empty(max(hi - lo, 0), dtype=np.int64)
    n = 0
    for row in range(lo, hi):
        if (abs(ratio2[row] - wanted_ratio2) <= tolerance and sense[row] == wanted_sense
                and longest_lo <= longest[row] <= longest_hi and faintest[row] < star_limit):
            rows[n] = row
            n += 1
    return rows[:n]


@warm_up_with
def _warm_up_shape_matches() -> None:
    """Compile the shape lookup's loop for the types of the bright triangles' arrays."""
    one = np.zeros(1)
    _matching_rows(0, 1, one, 0.0, 1.0, np.zeros(1, dtype=np.int8), 0, one, 0.0, 1.0, np.zeros(1, dtype=np.int32), 1)
