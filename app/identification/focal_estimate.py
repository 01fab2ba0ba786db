"""The focal length a pattern was seen with, from its bright triangles' shapes.

Why.  A wrong focal length scales every angle of the pattern by the same
factor, beyond the bright-pair lookup's edge window, so the engine searches
focal lengths in steps (:mod:`.optics`), a full lookup at each: 20,000-60,000
hypotheses and 100-600 ms for a camera 5 % off.  A triangle's *shape* (its
sides' ratios) does not change with the scale, so one lookup by shape
(:mod:`.triangle_index`) finds the catalogue triangles a pattern triangle can
be, at every focal length within the tolerance at once, and each says which
focal length it needs.

Naming.  The ratios of a pattern triangle err by its sides' errors over the
longest side; sides within that error of each other may be named either
way, so each such naming is looked up.

Estimate.  Each shape match gives a focal length ``f' = f s3_pattern /
s3_catalogue`` (angles measured through the declared focal length ``f`` are
``f'/f`` times the true ones) and a rotation (its longest side onto the
catalogue's, :func:`app.attitude.rotation_from_pair`); the whole pattern,
seen at ``f'``, is checked against the sky under that rotation.  The match
that catches most points gives the estimate, when chance would not explain
it: with ``H`` matches checked, a point caught within ``r`` of one of the
stars (density ``rho``) with probability ``p = 1 - exp(-rho pi r^2)``, and
the triangle's corners caught by construction, the expected number of
chance matches catching ``k`` of ``m`` points,
``H P[Binomial(m - 3, p) >= k - 3]``, must be at most
:data:`CHANCE_LIMIT` (the reasoning of :mod:`.verify`'s false-match
probability; random points caught 5 of 16 by chance before this test).  The
focal length is then fitted on all the points caught.

Use (:func:`app.identification.engine.identify`, when the declared camera's
first bright-pair edge has not settled the pattern).  Away from the declared
focal length, the engine searches there first with its usual machinery
(check, refine, optics fit, false-match probability, every hypothesis
counted).  At the declared focal length, the match is refined as one more of
its hypotheses, which usually settles the pattern at once.  Either way the
answer rests on the engine's own refinement and scoring, never on the
estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import bdtrc  # binomial survival function

from app.attitude.rotations import pair_triad, rotation_into, triads_rotation, wahba_rotation
from app.compiled import njit, warm_up_with
from app.identification.candidates import PreparedPattern
from app.identification.cells import NearStarCells, cell_of, listed_stars, nearest_star
from app.identification.hypotheses import delaunay_triangles
from app.identification.options import SearchOptions
from app.identification.triangle_index import BrightTriangles, sense_of, shape_matches, sides_of
from app.identification.verify import cells_within, chord

#: Expected number of chance matches as good as the estimate's, at most (see the module doc).
CHANCE_LIMIT = 1e-3
#: Shape matches checked at most: a true triangle is usually among the first few (20-350 matches in all for
#: the 20 deg camera); a pattern of ghosts or the Earth must not check them all.
MAX_TRIED = 1500
#: A point of a shape match's pattern is caught when a star lies within this many pixels: the match's
#: rotation and focal length err by its sides' errors (a few pixels across the pattern), far less than the
#: distance between stars (~100 px for the 20 deg camera).
CHECK_RADIUS_PX = 5.0
#: ... or this many of its points' sighting sigmas, where that is more (a finely sampled frame, whose
#: sighting noise is assumed larger: :func:`app.extraction.assumed_sighting_noise_px`).
CHECK_RADIUS_SIGMAS = 7.0


def check_radius_px(p) -> float:
    """The radius (pixels) within which a star catches a point of prepared pattern ``p``: :data:`CHECK_RADIUS_PX`,
    or :data:`CHECK_RADIUS_SIGMAS` times its points' median sighting sigma where that is more."""
    return max(CHECK_RADIUS_PX, CHECK_RADIUS_SIGMAS * float(np.median(p.sigma_px))) if p.m else CHECK_RADIUS_PX
#: Fixed part of the shape tolerance (ratio units): the gnomonic projection changes a triangle's ratios
#: with the focal length by up to ~3 % of the focal error over a 20 deg field (0.15 % at 5 %).
SHAPE_MARGIN = 0.002


@dataclass(frozen=True, eq=False)
class FocalEstimate:
    """The focal length fitted on the first shape match that chance does not explain, and how it was found."""

    focal_length_px: float
    n_matched: int  # pattern points within the check radius, its triangle's three included ...
    n_points: int  # ... of these
    n_tried: int  # shape matches checked (each a hypothesis, for the false-match count)
    rotation: np.ndarray  # (3, 3) ICRS -> camera, fitted with the focal length on the caught points
    pattern_edge: tuple[int, int]  # the matched triangle's longest side: pattern rows ...
    catalogue_pair: tuple[int, int]  # ... and the star rows matched to them


def _namings(triangle: np.ndarray, sides: np.ndarray, error: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The corner orders of a pattern triangle under which its sides may be sorted, each with its sides
    (side k opposite corner k): sides within their error of each other may be named either way round."""
    order = np.argsort(sides, kind="stable")
    names = {tuple(order.tolist())}
    for first, second in ((0, 1), (1, 2)):
        if sides[order[second]] - sides[order[first]] <= 2 * error:
            swapped = order.copy()
            swapped[[first, second]] = order[[second, first]]
            names.add(tuple(swapped.tolist()))
    return [(triangle[list(name)], sides[list(name)]) for name in sorted(names)]


def estimate_focal_length(pattern_triangles: np.ndarray, plane: np.ndarray, focal_length_px: float,
                          tolerance: float, side_error_rad: np.ndarray, triangles: BrightTriangles,
                          cells: NearStarCells, bound: float, star_vectors: np.ndarray,
                          catch_probability: float, tried_out: list[int] | None = None,
                          max_tried: int = MAX_TRIED) -> FocalEstimate | None:
    """The focal length of the first shape match of a pattern triangle that chance does not explain.

    ``pattern_triangles`` (K, 3) pattern rows (bright triangles of the
    pattern); ``plane`` (m, 2) the pattern's undistorted normalised
    coordinates at the declared ``focal_length_px`` (a direction is
    ``(plane, 1)`` normalised, and at focal length ``f'`` it is
    ``(plane f / f', 1)``); ``tolerance`` the declared focal tolerance
    (fraction); ``side_error_rad`` (K,) how far a side of each triangle may
    be off; a sky point is caught by the nearest star of ``star_vectors``
    (the places of the index rows now) within chord ``bound`` of it, found
    with ``cells`` (a :class:`app.identification.cells.NearStarCells` of
    those stars for at least that radius); ``catch_probability`` the chance
    that a point lands within the check radius of a star.

    The triangles are taken in order of their shape tolerance (the most
    telling first), all shape matches of one at once, and the search stops
    at the first match that passes the chance test, counting every match
    checked until then (or once ``max_tried``, :data:`MAX_TRIED` by default, are checked, or once a match
    catching every point would no longer pass: a few points pass only among few matches).  The best
    match of each triangle has its focal length (:func:`_fitted_focal_length`)
    and rotation (Wahba) fitted on the points it caught, twice, before the
    pattern is checked again and the chance test is made (compiled loops, :func:`_caught_counts` and
    :func:`_refitted`: a pattern that matches nothing checks a few thousand matches and refits a dozen, where
    numpy's calls on a dozen points cost ~0.5 ms a refit).  ``tried_out``, when given, gets the number of
    shape matches checked appended (also when none passes: a search over scales counts them all).
    """
    m = plane.shape[0]
    v = np.column_stack([plane, np.ones(m)])
    v /= np.linalg.norm(v, axis=1, keepdims=True)  # the points' directions at the declared focal length
    named = [(c, sides, float(err))
             for t, s, err in zip(pattern_triangles, sides_of(v[pattern_triangles]), side_error_rad)
             for c, sides in _namings(t, s, float(err))]
    if not named:
        return None
    shape_tolerance = [2 * err / sides[2] + SHAPE_MARGIN for _, sides, err in named]
    # The best a match can do is to catch every point: once that would not pass the chance test, none will.
    all_caught = float(bdtrc(m - 4, m - 3, catch_probability)) if m > 3 else np.inf
    senses = sense_of(v[np.array([c for c, _, _ in named])]).astype(int).tolist()
    plane = np.ascontiguousarray(plane, dtype=float)
    map_arrays = cells.kernel_arrays()
    tried = 0
    for k in np.argsort(shape_tolerance, kind="stable").tolist():
        if tried >= max_tried:
            break
        c, s, err = named[k]
        rows = shape_matches(triangles, s[0] / s[2], s[1] / s[2], senses[k], shape_tolerance[k],
                             s[2] / (1 + tolerance) - err, s[2] / (1 - tolerance) + err, len(star_vectors))
        if len(rows) == 0:
            continue
        if (tried + len(rows)) * all_caught > CHANCE_LIMIT:
            break
        tried += len(rows)
        f_new = focal_length_px * s[2] / triangles.longest_rad[rows]
        stars = triangles.corners[rows].astype(np.int64)
        caught = _caught_counts(plane, int(c[0]), int(c[1]), focal_length_px / f_new, stars, star_vectors, bound,
                                *map_arrays)
        best = int(np.argmax(caught))
        if caught[best] <= 3:
            continue
        # The match's focal length and rotation fitted on the points it caught, then the pattern checked
        # again: one side's focal length errs by ~1 %, enough to miss the far points of a pattern seen
        # 10-20 % off the declared focal length.
        f, rotation, n = _refitted(plane, float(focal_length_px), float(f_new[best]), int(c[0]), int(c[1]),
                                   int(stars[best, 0]), int(stars[best, 1]), star_vectors, bound, *map_arrays)
        # The corners are caught by construction: P[Binomial(m - 3, p) >= n - 3] = P[... > n - 4].
        if n > 3 and tried * float(bdtrc(n - 4, m - 3, catch_probability)) <= CHANCE_LIMIT:
            if tried_out is not None:
                tried_out.append(tried)
            return FocalEstimate(f, n, m, tried, rotation, (int(c[0]), int(c[1])),
                                 (int(stars[best, 0]), int(stars[best, 1])))
    if tried_out is not None:
        tried_out.append(tried)
    return None


@njit
def _fitted_focal_length(plane, declared_px, start_px, stars):
    """The focal length at which the angles between the points (``plane``: normalised coordinates at
    ``declared_px``) are those between their stars, by least squares, from ``start_px``.

    An angle seen at focal length ``f`` is about ``f_true / f`` times the
    true one, so the scale ``sum(a_seen a_star) / sum(a_star^2)`` corrects
    ``f``; the gnomonic projection departs from that proportion by a few
    per cent over a 20 deg field, so each round leaves a few per cent of the
    error before it, and three take a start 1 % off to 1e-7.  A triangle's
    longest side alone gives the focal length to ~1 %; the pairs of all the
    caught points, to ~0.1 %.
    """
    n = plane.shape[0]
    star_angle = np.empty(n * (n - 1) // 2)
    k = 0
    for i in range(n):
        for j in range(i + 1, n):
            dx, dy, dz = stars[i, 0] - stars[j, 0], stars[i, 1] - stars[j, 1], stars[i, 2] - stars[j, 2]
            star_angle[k] = 2.0 * np.arcsin(min(np.sqrt(dx * dx + dy * dy + dz * dz) / 2, 1.0))
            k += 1
    v = np.empty((n, 3))
    f = start_px
    for _ in range(3):
        _seen_at(plane, declared_px / f, v)
        product, norm = 0.0, 0.0
        k = 0
        for i in range(n):
            for j in range(i + 1, n):
                dx, dy, dz = v[i, 0] - v[j, 0], v[i, 1] - v[j, 1], v[i, 2] - v[j, 2]
                seen = 2.0 * np.arcsin(min(np.sqrt(dx * dx + dy * dy + dz * dz) / 2, 1.0))
                product += seen * star_angle[k]
                norm += star_angle[k] * star_angle[k]
                k += 1
        f *= product / norm
    return f


@njit
def _seen_at(plane, scale, out):
    """The unit vectors (m, 3) of the points ``plane`` (normalised coordinates at the declared focal length)
    seen at the focal length ``declared / scale``, written into ``out``."""
    for k in range(plane.shape[0]):
        x, y = plane[k, 0] * scale, plane[k, 1] * scale
        norm = np.sqrt(x * x + y * y + 1.0)
        out[k, 0], out[k, 1], out[k, 2] = x / norm, y / norm, 1.0 / norm


@njit
def _caught_star(v, R, star_vectors, bound, G, words, word_rank, first, stars):
    """The star whose place is nearest ``R^T v`` (a unit vector) within chord ``bound``, else -1."""
    x = v[0] * R[0, 0] + v[1] * R[1, 0] + v[2] * R[2, 0]
    y = v[0] * R[0, 1] + v[1] * R[1, 1] + v[2] * R[2, 1]
    z = v[0] * R[0, 2] + v[1] * R[1, 2] + v[2] * R[2, 2]
    chord_to_star, star = nearest_star(x, y, z, star_vectors, G, words, word_rank, first, stars)
    return star if chord_to_star <= bound else -1


@njit
def _pair_rotation(v, c0, c1, a, b):
    """:func:`app.attitude.rotation_from_pair` of points ``v[c0]``, ``v[c1]`` and stars ``a``, ``b`` (3,)."""
    R = triads_rotation(pair_triad(v[c0, 0], v[c0, 1], v[c0, 2], v[c1, 0], v[c1, 1], v[c1, 2]),
                        pair_triad(a[0], a[1], a[2], b[0], b[1], b[2]))
    out = np.empty((3, 3))
    rotation_into(out, R)
    return out


@njit
def _caught_counts(plane, c0, c1, scale, corners, star_vectors, bound, G, words, word_rank, first, stars):
    """(H,) the points each shape match catches: the pattern seen at ``scale[h]`` (declared over the match's
    focal length), turned by :func:`_pair_rotation` of its corners ``c0``, ``c1`` onto the match's stars
    ``corners[h, 0]``, ``corners[h, 1]``, each point caught by a star within chord ``bound`` (the look-up of
    :func:`_caught_star` written out: called here, with its arrays passed field by field, it took three
    times as long)."""
    H, m = scale.shape[0], plane.shape[0]
    caught = np.zeros(H, dtype=np.int64)
    v = np.empty((m, 3))
    for h in range(H):
        _seen_at(plane, scale[h], v)
        R = _pair_rotation(v, c0, c1, star_vectors[corners[h, 0]], star_vectors[corners[h, 1]])
        for k in range(m):
            x = v[k, 0] * R[0, 0] + v[k, 1] * R[1, 0] + v[k, 2] * R[2, 0]  # R^T v
            y = v[k, 0] * R[0, 1] + v[k, 1] * R[1, 1] + v[k, 2] * R[2, 1]
            z = v[k, 0] * R[0, 2] + v[k, 1] * R[1, 2] + v[k, 2] * R[2, 2]
            cell = cell_of(x, y, z, G)
            if (words[cell >> 6] >> np.uint64(cell & 63)) & np.uint64(1) != 0:
                begin, end = listed_stars(cell, words, word_rank, first)
                d2 = np.inf
                for q in range(begin, end):
                    s = np.int64(stars[q])
                    dx, dy, dz = x - star_vectors[s, 0], y - star_vectors[s, 1], z - star_vectors[s, 2]
                    d2 = min(d2, (dx * dx + dy * dy) + dz * dz)
                caught[h] += np.sqrt(d2) <= bound
    return caught


@njit
def _refitted(plane, declared_px, f, c0, c1, a, b, star_vectors, bound, G, words, word_rank, first, stars):
    """(focal length, rotation, points caught) of a shape match (its focal length ``f``, its corners ``c0``,
    ``c1`` on stars ``a``, ``b``), fitted twice on the points it catches: the focal length
    (:func:`_fitted_focal_length`), the rotation (Wahba's), each pattern point's star again."""
    m = plane.shape[0]
    v = np.empty((m, 3))
    _seen_at(plane, declared_px / f, v)
    rotation = _pair_rotation(v, c0, c1, star_vectors[a], star_vectors[b])
    star = np.empty(m, dtype=np.int64)
    for k in range(m):
        star[k] = _caught_star(v[k], rotation, star_vectors, bound, G, words, word_rank, first, stars)
    for _ in range(2):
        n = 0
        for k in range(m):
            n += star[k] >= 0
        if n < 3:  # a refit lost its points: no estimate from this match
            break
        caught_plane, caught_stars = np.empty((n, 2)), np.empty((n, 3))
        i = 0
        for k in range(m):
            if star[k] >= 0:
                caught_plane[i, 0], caught_plane[i, 1] = plane[k, 0], plane[k, 1]
                for c in range(3):
                    caught_stars[i, c] = star_vectors[star[k], c]
                i += 1
        f = _fitted_focal_length(caught_plane, declared_px, f, caught_stars)
        _seen_at(plane, declared_px / f, v)
        B = np.zeros((3, 3))
        for k in range(m):
            if star[k] >= 0:
                for r in range(3):
                    for c in range(3):
                        B[r, c] += v[k, r] * star_vectors[star[k], c]
        rotation = wahba_rotation(B)
        for k in range(m):
            star[k] = _caught_star(v[k], rotation, star_vectors, bound, G, words, word_rank, first, stars)
    n = 0
    for k in range(m):
        n += star[k] >= 0
    return f, rotation, n


def focal_estimate(p: PreparedPattern, triangles: BrightTriangles, options: SearchOptions,
                   tolerance: float | None = None, tried_out: list[int] | None = None,
                   max_tried: int = MAX_TRIED) -> FocalEstimate | None:
    """:func:`estimate_focal_length` for a prepared pattern (seen through the declared camera), from its
    surely bright Delaunay triangles (:func:`app.identification.hypotheses.delaunay_triangles`), within
    ``tolerance`` (a fraction; the camera's declared tolerance when None) of the declared focal length;
    ``tried_out`` and ``max_tried`` as there."""
    found = delaunay_triangles(p.xy, p.camera) if p.m >= 3 else None
    if found is None:
        if tried_out is not None:
            tried_out.append(0)
        return None
    tri = found[0][found[1]]
    # A side errs by the edge window of the bright-pair lookup (systematic error + 4 sigma of its points).
    sigma = p.sigma_px[tri]
    side_sigma = np.hypot(sigma, np.roll(sigma, 1, axis=1)).max(axis=1)
    side_error = (options.edge_tolerance_px + 4 * side_sigma) * p.scale
    plane = p.vectors[:, :2] / p.vectors[:, 2:]
    radius = check_radius_px(p) * p.scale
    catch = 1.0 - np.exp(-p.field.density_per_sr * np.pi * radius * radius)
    tolerance = p.camera.focal_tolerance if tolerance is None else tolerance
    return estimate_focal_length(tri, plane, p.camera.focal_length_px, tolerance, side_error, triangles,
                                 cells_within(p.field, radius), float(chord(radius)), p.field.vectors, float(catch),
                                 tried_out, max_tried)


@warm_up_with
def _warm_up_focal_estimate() -> None:
    """Compile the shape matches' check and refit for the types the searches pass (four stars)."""
    stars = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0], [0.0, 0.1, 1.0], [0.1, 0.1, 1.0]])
    stars /= np.linalg.norm(stars, axis=1, keepdims=True)
    plane = np.ascontiguousarray(stars[:, :2] / stars[:, 2:])
    cells = NearStarCells.build(stars, 0.01).kernel_arrays()
    _caught_counts(plane, 0, 1, np.ones(1), np.array([[0, 1, 2]], dtype=np.int64), stars, 0.01, *cells)
    _refitted(plane, 1000.0, 1000.0, 0, 1, 0, 1, stars, 0.01, *cells)
