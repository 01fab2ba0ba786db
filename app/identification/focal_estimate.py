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

from app.attitude import rotation_from_pair, solve_wahba
from app.identification.candidates import PreparedPattern
from app.identification.hypotheses import delaunay_triangles
from app.identification.options import SearchOptions
from app.identification.triangle_index import BrightTriangles, sense_of, shape_matches, sides_of
from app.identification.verify import StarField, chord, chord_to_angle

#: Expected number of chance matches as good as the estimate's, at most (see the module doc).
CHANCE_LIMIT = 1e-3
#: Shape matches checked at most: a true triangle is usually among the first few (20-350 matches in all for
#: the 20 deg camera); a pattern of ghosts or the Earth must not check them all.
MAX_TRIED = 1500
#: A point of a shape match's pattern is caught when a star lies within this many pixels: the match's
#: rotation and focal length err by its sides' errors (a few pixels across the pattern), far less than the
#: distance between stars (~100 px for the 20 deg camera).
CHECK_RADIUS_PX = 5.0
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


def _directions(plane: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(H, m, 3) unit vectors of the points ``plane`` (m, 2) (normalised coordinates at the declared focal
    length) seen at each of the focal lengths ``declared / scale`` (``scale`` (H,))."""
    xy = plane[None] * np.asarray(scale, dtype=float)[:, None, None]
    v = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=2)
    return v / np.linalg.norm(v, axis=2, keepdims=True)


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
                          matched_within, nearest_star, star_vectors: np.ndarray,
                          catch_probability: float, tried_out: list[int] | None = None,
                          max_tried: int = MAX_TRIED) -> FocalEstimate | None:
    """The focal length of the first shape match of a pattern triangle that chance does not explain.

    ``pattern_triangles`` (K, 3) pattern rows (bright triangles of the
    pattern); ``plane`` (m, 2) the pattern's undistorted normalised
    coordinates at the declared ``focal_length_px`` (a direction is
    ``(plane, 1)`` normalised, and at focal length ``f'`` it is
    ``(plane f / f', 1)``); ``tolerance`` the declared focal tolerance
    (fraction); ``side_error_rad`` (K,) how far a side of each triangle may
    be off; ``matched_within(points (N, 3)) -> (N,) bool`` whether a sky
    point has a star within the check radius, ``nearest_star(points (N, 3))
    -> (N,)`` the row of that star (-1: none); ``star_vectors`` the places of
    the index rows now; ``catch_probability`` the chance that a point lands
    within the check radius of a star.

    The triangles are taken in order of their shape tolerance (the most
    telling first), all shape matches of one at once, and the search stops
    at the first match that passes the chance test, counting every match
    checked until then (or once ``max_tried``, :data:`MAX_TRIED` by default, are checked, or once a match
    catching every point would no longer pass: a few points pass only among few matches).  The best
    match of each triangle has its focal length (:func:`_fitted_focal_length`)
    and rotation (Wahba) fitted on the points it caught, twice, before the
    pattern is checked again and the chance test is made.  ``tried_out``, when given, gets the number of
    shape matches checked appended (also when none passes: a search over scales counts them all).
    """
    m = plane.shape[0]
    v = _directions(plane, np.ones(1))[0]
    named = [(c, sides, float(err))
             for t, s, err in zip(pattern_triangles, sides_of(v[pattern_triangles]), side_error_rad)
             for c, sides in _namings(t, s, float(err))]
    if not named:
        return None
    shape_tolerance = [2 * err / sides[2] + SHAPE_MARGIN for _, sides, err in named]
    # The best a match can do is to catch every point: once that would not pass the chance test, none will.
    all_caught = float(bdtrc(m - 4, m - 3, catch_probability)) if m > 3 else np.inf
    senses = sense_of(v[np.array([c for c, _, _ in named])]).astype(int).tolist()
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
        seen = _directions(plane, focal_length_px / f_new)  # (H, m, 3)
        h = np.arange(len(rows))
        stars = triangles.corners[rows]
        R = rotation_from_pair(seen[h, c[0]], seen[h, c[1]], star_vectors[stars[:, 0]], star_vectors[stars[:, 1]])
        caught = matched_within(np.matmul(seen, R).reshape(-1, 3)).reshape(len(rows), m).sum(axis=1)  # rows R^T p
        best = int(np.argmax(caught))
        if caught[best] <= 3:
            continue
        # The match's focal length and rotation fitted on the points it caught, then the pattern checked
        # again: one side's focal length errs by ~1 %, enough to miss the far points of a pattern seen
        # 10-20 % off the declared focal length.
        f, rotation = float(f_new[best]), R[best]
        star = nearest_star(seen[best] @ rotation)
        for _ in range(2):
            ok = star >= 0
            if np.count_nonzero(ok) < 3:  # a refit lost its points: no estimate from this match
                break
            f = _fitted_focal_length(plane[ok], focal_length_px, f, star_vectors[star[ok]])
            v_f = _directions(plane, np.array([focal_length_px / f]))[0]
            rotation = solve_wahba(v_f[ok], star_vectors[star[ok]])
            star = nearest_star(v_f @ rotation)
        n = int(np.count_nonzero(star >= 0))
        # The corners are caught by construction: P[Binomial(m - 3, p) >= n - 3] = P[... > n - 4].
        if n > 3 and tried * float(bdtrc(n - 4, m - 3, catch_probability)) <= CHANCE_LIMIT:
            if tried_out is not None:
                tried_out.append(tried)
            return FocalEstimate(f, n, m, tried, rotation, (int(c[0]), int(c[1])),
                                 (int(stars[best, 0]), int(stars[best, 1])))
    if tried_out is not None:
        tried_out.append(tried)
    return None


def _fitted_focal_length(plane: np.ndarray, declared_px: float, start_px: float, stars: np.ndarray) -> float:
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
    i, j = np.triu_indices(len(plane), k=1)
    star_angle = chord_to_angle(np.linalg.norm(stars[i] - stars[j], axis=1))
    f = start_px
    for _ in range(3):
        v = _directions(plane, np.array([declared_px / f]))[0]
        seen_angle = chord_to_angle(np.linalg.norm(v[i] - v[j], axis=1))
        f *= float(seen_angle @ star_angle / (star_angle @ star_angle))
    return f


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
    radius = CHECK_RADIUS_PX * p.scale
    catch = 1.0 - np.exp(-p.field.density_per_sr * np.pi * radius * radius)
    within, nearest = _star_within(p.field, radius)
    tolerance = p.camera.focal_tolerance if tolerance is None else tolerance
    return estimate_focal_length(tri, plane, p.camera.focal_length_px, tolerance, side_error,
                                 triangles, within, nearest, p.field.vectors, float(catch), tried_out, max_tried)


def _star_within(field: StarField, radius_rad: float):
    """Two functions of sky points (N, 3): whether a star of ``field`` lies within ``radius_rad`` of each
    (its cell map, else its KD-tree), and that star's row (-1: none; the KD-tree)."""
    bound = float(chord(radius_rad))

    def nearest(points):
        d, row = field.tree.query(points, k=1, distance_upper_bound=bound)
        return np.where(d <= bound, row, -1)

    cells = field.cells(radius_rad) if field.cells is not None else None
    if cells is not None:
        return (lambda points: cells.nearest_within(points, field.vectors, bound) <= bound), nearest
    return (lambda points: nearest(points) >= 0), nearest
