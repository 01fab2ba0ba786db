"""Attitude hypotheses from the bright-pair index (seed 004, "The Query").

1. Triangulate the pattern in the image plane (Delaunay), after a tiny
   deterministic perturbation: integer pixels make co-circular points common,
   and the degeneracy is an artefact of the grid, not of the sky.
2. Edges of triangles whose circumcircle lies inside the sensor "surely" are
   bright pairs: that circle holds no pattern point, and the pattern holds the
   brightest sources of the field.  They are tried first; the other Delaunay
   edges follow, so a pattern polluted by a planet or a missed star still
   finds a clean edge.  A pair that is no Delaunay edge (a pattern point lies
   in every circle through the two) is not tried: see
   :func:`ordered_pattern_edges`.
3. Each edge is looked up by length in the index (tolerance from the pixel
   scale and the points' noise), both orientations of every catalogue pair
   give one rotation (the seed's two-vector construction).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay, QhullError

from app.attitude import angle_between, rotation_from_pair
from app.camera import Camera
from app.compiled import njit, warm_up_with
from app.identification.candidates import PreparedPattern
from app.identification.cells import check_pairs_kernel
from app.identification.options import SearchOptions
from app.identification.sky import Sky
from app.identification.verify import StarField, cells_within, chord
from app.index import BrightPairIndex


@dataclass(frozen=True, eq=False)
class Hypotheses:
    """A stack of candidate rotations (ICRS -> camera) and where each came from."""

    rotations: np.ndarray  # (H, 3, 3)
    pattern_edge: np.ndarray  # (H, 2) pattern rows i, j
    catalogue_pair: np.ndarray  # (H, 2) index rows mapped onto i, j
    edge_number: np.ndarray  # (H,) position of the generating edge in the edge list

    def __len__(self) -> int:
        return int(self.rotations.shape[0])


@dataclass(frozen=True, eq=False)
class PairHypotheses:
    """Hypotheses each mapping a catalogue pair onto a pattern edge (:func:`app.attitude.rotation_from_pair`),
    given by their rows: a search makes the rotations where it checks them and keeps the few it refines
    (:func:`check_pair_hypotheses`); :attr:`rotations` makes them all."""

    pattern_vectors: np.ndarray  # (S, m, 3) the pattern as seen at each focal length of these hypotheses
    index_vectors: np.ndarray  # (n, 3) the index's stars
    pattern_edge: np.ndarray  # (H, 2) pattern rows i, j
    catalogue_pair: np.ndarray  # (H, 2) index rows mapped onto i, j
    edge_number: np.ndarray  # (H,) position of the generating edge in the edge list
    steps: np.ndarray  # (H,) the focal length each is seen at: its position in ``pattern_vectors``

    def __len__(self) -> int:
        return int(self.pattern_edge.shape[0])

    @functools.cached_property
    def rotations(self) -> np.ndarray:
        """(H, 3, 3) every hypothesis's rotation (ICRS -> camera)."""
        (i, j), (a, b) = self.pattern_edge.T, self.catalogue_pair.T
        return rotation_from_pair(self.pattern_vectors[self.steps, i], self.pattern_vectors[self.steps, j],
                                  self.index_vectors[a], self.index_vectors[b])


def check_pair_hypotheses(hypotheses: PairHypotheses, field: StarField, tolerance_rad: np.ndarray,
                          min_matches: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`app.identification.verify.check_hypotheses` of :class:`PairHypotheses` (at one focal length or
    several), keeping those that match ``min_matches`` points or more: (their rows (K,), matches (K,), capped
    deviations (K,), rotations (K, 3, 3)).

    Why.  A search that finds nothing makes and checks 50,000-70,000 such
    rotations; one compiled loop makes each where it checks it
    (:func:`app.identification.cells.check_pairs_kernel`) and keeps only those
    that caught a third point, the only ones a search refines (a candidate
    has 3 matches at least): no (H, 3, 3) array of them all.  The same numbers
    as making them all and checking those of each focal length with
    ``check_hypotheses``; the stars come from the field's cell map for the
    largest tolerance (:func:`app.identification.verify.cells_within`: any
    map that covers a tolerance gives its nearest star exactly).
    """
    tol = np.ascontiguousarray(tolerance_rad, dtype=float).reshape(-1)
    if len(tol) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 3, 3))
    steps = np.ascontiguousarray(hypotheses.steps, dtype=np.int64)
    cap = np.zeros(len(hypotheses.pattern_vectors))  # the largest tolerance at each focal length
    np.maximum.at(cap, steps, tol)
    return check_pairs_kernel(np.ascontiguousarray(hypotheses.pattern_vectors, dtype=float), steps,
                              np.ascontiguousarray(hypotheses.pattern_edge, dtype=np.int64),
                              np.ascontiguousarray(hypotheses.catalogue_pair, dtype=np.int64),
                              np.ascontiguousarray(hypotheses.index_vectors, dtype=float), tol, int(min_matches),
                              field.vectors, chord(cap), *cells_within(field, float(np.max(cap))).kernel_arrays())


def perturbed(xy: np.ndarray) -> np.ndarray:
    """Deterministic sub-milli-pixel perturbation that breaks grid degeneracies."""
    i = np.arange(len(xy))
    return xy + 1e-4 * np.column_stack([np.sin(1.0 + 2.3999 * i), np.cos(0.5 + 1.6180 * i)])


def ordered_pattern_edges(xy: np.ndarray, camera: Camera, min_separation_px: float = 2.0) -> list[tuple[int, int]]:
    """Pattern edges, the surest bright pairs first: the edges of the Delaunay triangles whose circumcircle
    lies inside the sensor, then the other Delaunay edges, shorter edges first within each group (fewer
    catalogue pairs share a short length).

    The pairs that are no Delaunay edge are left out (every pair when the
    points are fewer than three or all on a line): another pattern point lies
    in every circle through the two, so they are a bright pair only if such
    a point is fainter than both or no star, and a pattern with stars enough to
    be identified has Delaunay edges between them.  Measured on the search
    that still tried them (2026-11-25): every one of 738 right answers came
    from a Delaunay edge (a sure one but for 35, all in sparse or
    ghost-ridden patterns), over 240 single snapshots with 3 ghosts and up to 2 hot pixels
    among their 10 sources, 480 other simulated cases (3 cameras, every
    scenario, 0-5 % off) and the 25 real frames at 3 focal lengths; the
    other pairs (24 of a 10-point pattern's 45) were a quarter of the
    declared camera's search of 10 random points.

    An identification asks for the same pattern's edges several times (the
    declared camera's search, the focal scan, the notes): the last few
    patterns' are kept.
    """
    xy = np.ascontiguousarray(xy, dtype=float).reshape(-1, 2)
    return list(_ordered_edges_of(xy.tobytes(), len(xy), int(camera.width), int(camera.height),
                                  float(min_separation_px)))


@functools.lru_cache(maxsize=16)
def _ordered_edges_of(xy_bytes: bytes, m: int, width: int, height: int,
                      min_separation_px: float) -> tuple[tuple[int, int], ...]:
    """:func:`ordered_pattern_edges` of the points ``xy_bytes`` ((m, 2) floats) on a sensor of that size."""
    xy = np.frombuffer(xy_bytes).reshape(m, 2)
    # Points too close give no usable direction (and may be one star twice).
    ii, jj = np.triu_indices(m, k=1)
    usable_mask = np.hypot(*(xy[ii] - xy[jj]).T) >= min_separation_px
    all_pairs = tuple(zip(ii[usable_mask].tolist(), jj[usable_mask].tolist()))
    if m < 3:
        return all_pairs
    p = perturbed(xy)
    triangles = _delaunay_of(xy_bytes, m, width, height)
    if triangles is None:  # all points on a line
        return all_pairs
    tri, inside = triangles
    sure: set[tuple[int, int]] = set()
    delaunay: set[tuple[int, int]] = set()
    for t, is_inside in zip(np.sort(tri, axis=1).tolist(), inside.tolist()):
        (sure if is_inside else delaunay).update(((t[0], t[1]), (t[0], t[2]), (t[1], t[2])))
    usable = set(all_pairs)
    sure &= usable
    delaunay = (delaunay - sure) & usable
    length = np.zeros((m, m))
    length[ii, jj] = np.hypot(*(p[ii] - p[jj]).T)

    def by_length(edges):
        return tuple(sorted(edges, key=lambda e: (length[e], e)))

    return by_length(sure) + by_length(delaunay)


def delaunay_triangles(xy: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray] | None:
    """The pattern's Delaunay triangles (T, 3) and whether each is surely bright (T,) bool (read-only);
    None when the points are all on a line.

    Surely bright: its circumcircle lies inside the sensor, so it holds no
    pattern point and no star brighter than the pattern's faintest (the
    pattern is the field's brightest sources); its edges are then bright
    pairs (:mod:`app.index`).  One identification asks for the same
    pattern's triangles several times (its edges at each focal length
    searched, the bright triangles' two lookups), and Qhull costs ~0.5 ms a
    call: the last few patterns' are kept.
    """
    xy = np.ascontiguousarray(xy, dtype=float).reshape(-1, 2)
    return _delaunay_of(xy.tobytes(), len(xy), int(camera.width), int(camera.height))


@functools.lru_cache(maxsize=16)
def _delaunay_of(xy_bytes: bytes, m: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`delaunay_triangles` of the points ``xy_bytes`` ((m, 2) floats) on a sensor of that size."""
    p = perturbed(np.frombuffer(xy_bytes).reshape(m, 2))
    try:
        tri = Delaunay(p).simplices
    except (QhullError, ValueError):
        return None
    centre, radius = _circumcircles(p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]])
    inside = ((centre[:, 0] - radius >= -0.5) & (centre[:, 0] + radius <= width - 0.5)
              & (centre[:, 1] - radius >= -0.5) & (centre[:, 1] + radius <= height - 0.5))
    tri.setflags(write=False)
    inside.setflags(write=False)
    return tri, inside


def _circumcircles(a, b, c) -> tuple[np.ndarray, np.ndarray]:
    """Centres (n, 2) and radii (n,) of the circles through a, b, c (each (n, 2)); inf when collinear."""
    d = 2 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - b[:, 1]))
    a2, b2, c2 = (a * a).sum(1), (b * b).sum(1), (c * c).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / d
        uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / d
    centre = np.column_stack([ux, uy])
    radius = np.hypot(*(a - centre).T)
    degenerate = np.abs(d) < 1e-12
    centre[degenerate] = np.inf
    radius[degenerate] = np.inf
    return centre, radius


def bright_pair_hypotheses(pattern_vectors: np.ndarray, edges: list[tuple[int, int]],
                           edge_tolerance_rad: np.ndarray, index: BrightPairIndex,
                           star_mask: np.ndarray | None = None) -> PairHypotheses:
    """Each catalogue pair of matching length onto each pattern edge, both orientations: the rotation mapping
    the pair onto the edge is a hypothesis.

    ``edge_tolerance_rad[e]`` is the half-width of the length window of edge
    ``e``; ``star_mask`` (n_stars,) restricts the catalogue pairs to stars the
    camera can see.  Each edge's pairs are a run of the index (sorted by
    length): all edges' runs are found at once, and one compiled loop
    (:func:`_edge_pairs`) lists their pairs, edge after edge, both orientations (a -> i, b -> j) then
    (b -> i, a -> j).
    """
    edge = np.array(edges, dtype=np.int64).reshape(-1, 2)
    length = angle_between(pattern_vectors[edge[:, 0]], pattern_vectors[edge[:, 1]])
    tolerance = np.asarray(edge_tolerance_rad, dtype=float)
    first = np.searchsorted(index.length_rad, length - tolerance, side="left")
    stop = np.searchsorted(index.length_rad, length + tolerance, side="right")
    mask = np.ones(index.n_stars, dtype=np.bool_) if star_mask is None else star_mask
    pattern_edge, catalogue_pair, edge_number = _edge_pairs(edge, first, stop, index.star_a, index.star_b, mask)
    return PairHypotheses(pattern_vectors[None], index.vectors, pattern_edge, catalogue_pair, edge_number,
                          np.zeros(len(edge_number), dtype=np.int64))


@njit
def _edge_pairs(edge, first, stop, star_a, star_b, star_mask):
    """(pattern edges (H, 2), catalogue pairs (H, 2), edge numbers (H,)) of every index pair in rows
    ``first[e]:stop[e]`` whose stars are both in ``star_mask``, for each edge ``e`` in turn: the pairs (a, b)
    onto the edge, then (b, a)."""
    total = 0
    for e in range(edge.shape[0]):
        for row in range(first[e], stop[e]):
            total += star_mask[star_a[row]] and star_mask[star_b[row]]
    pattern_edge = np.empty((2 * total, 2), dtype=np.int64)
    catalogue_pair = np.empty((2 * total, 2), dtype=np.int64)
    edge_number = np.empty(2 * total, dtype=np.int64)
    h = 0
    for e in range(edge.shape[0]):
        start = h
        for row in range(first[e], stop[e]):
            if star_mask[star_a[row]] and star_mask[star_b[row]]:
                catalogue_pair[h, 0], catalogue_pair[h, 1] = star_a[row], star_b[row]
                h += 1
        n = h - start
        for k in range(start, h):
            catalogue_pair[k + n, 0], catalogue_pair[k + n, 1] = catalogue_pair[k, 1], catalogue_pair[k, 0]
        for k in range(start, h + n):
            pattern_edge[k, 0], pattern_edge[k, 1] = edge[e, 0], edge[e, 1]
            edge_number[k] = e
        h += n
    return pattern_edge, catalogue_pair, edge_number


@dataclass(frozen=True, eq=False)
class EdgeWindows:
    """A pattern's edges, surest first (:func:`ordered_pattern_edges`), and what their lookup and check need."""

    edges: list[tuple[int, int]]
    length: np.ndarray  # (E,) each edge's angle, radians
    tolerance: np.ndarray  # (E,) half-width of its length window, radians
    check_tol: np.ndarray  # (E,) the check tolerance of the hypotheses it generates, radians


def edge_windows(p: PreparedPattern, options: SearchOptions,
                 edges: list[tuple[int, int]] | None = None) -> EdgeWindows:
    """The edges of ``p`` (``edges``, else :func:`ordered_pattern_edges`) with their length windows and check
    tolerances (:func:`stacked_edge_windows` of ``p`` alone)."""
    if edges is None:
        edges = ordered_pattern_edges(p.xy, p.camera, options.min_pair_separation_px)
    if not edges:
        empty = np.empty(0)
        return EdgeWindows([], empty, empty, empty)
    length, tolerance, check_tol = stacked_edge_windows([p], options, edges)
    return EdgeWindows(list(edges), length[0], tolerance[0], check_tol[0])


def stacked_edge_windows(patterns: list[PreparedPattern], options: SearchOptions,
                         edges: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, E) each edge's angle, the half-width of its length window and the check tolerance of the
    hypotheses it generates, for each of ``patterns`` (one pattern seen at several focal lengths; the
    same numbers as one at a time, in one set of numpy calls).

    The window is the edge's systematic error (``options.edge_tolerance_px``)
    plus 4 sigma of its two points' noise, and ~1e-4 of its length for the
    aberration's difference across the field.  A rotation made from one
    edge errs at distance ``D`` from its first point by ~``window D / L``,
    so the check tolerance is the largest match tolerance plus that at the
    pattern's farthest point, capped at 10 pixels.
    """
    v = np.stack([q.vectors for q in patterns])  # (S, m, 3)
    sigma = np.stack([q.sigma_px for q in patterns])
    scale = np.array([q.scale for q in patterns])[:, None]
    largest_match_tol = np.array([np.max(q.match_tol) for q in patterns])[:, None]
    first, second = np.array(edges).T
    edge_sigma_px = np.hypot(sigma[:, first], sigma[:, second])
    length = angle_between(v[:, first], v[:, second])
    tolerance = (options.edge_tolerance_px + 4 * edge_sigma_px) * scale + 1.1e-4 * length
    reach = np.arccos(np.clip(v @ np.swapaxes(v, 1, 2), -1, 1)).max(axis=2)[:, first]
    check_tol = np.minimum(largest_match_tol + tolerance * np.maximum(1.0, reach / np.maximum(length, 1e-9)),
                           10 * scale)
    return length, tolerance, check_tol


def edge_batches(n_edges: int):
    """(start, stop) of the edge batches, of growing size 1, 2, 4, ...: the first edges usually settle a
    pattern, and a batch's numpy calls cost the same whatever its size."""
    e, batch = 0, 1
    while e < n_edges:
        stop = min(n_edges, e + batch)
        yield e, stop
        e, batch = stop, batch * 2


def bright_pair_batches(p: PreparedPattern, sky: Sky, options: SearchOptions):
    """Hypotheses from the bright-pair index, edge batches of growing size (see :mod:`.hypotheses`)."""
    w = edge_windows(p, options)
    for e, stop in edge_batches(len(w.edges)):
        hyp = bright_pair_hypotheses(p.vectors, w.edges[e:stop], w.tolerance[e:stop], sky.index, p.star_mask)
        yield hyp, w.check_tol[e + hyp.edge_number], stop


@warm_up_with
def _warm_up_edge_pairs() -> None:
    """Compile the listing of an edge's pairs for the types the searches pass."""
    rows = np.array([0], dtype=np.int64)
    _edge_pairs(np.array([[0, 1]], dtype=np.int64), rows, rows + 1, rows, rows + 1, np.ones(2, dtype=np.bool_))
