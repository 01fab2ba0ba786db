"""The identification context: the catalogue and the bright-pair index, loaded once per process."""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections import OrderedDict
from datetime import datetime
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from app.attitude import angle_between
from app.catalogue import Catalogue, is_mean_place, julian_year, load_catalogue, star_names
from app.identification.cells import MAX_SPACECRAFT_SPEED_KM_S, MAX_YEARS, NearStarCells, motion_margin_rad
from app.identification.triangle_index import BrightTriangles, bright_triangles
from app.identification.verify import StarField, chord
from app.index import BrightPairIndex, load_index
from app.cache import exclusive, keep_arrays, kept_arrays

log = logging.getLogger(__name__)

#: Cell maps (1-5 MB each) kept on disk, the most recently made.
MAX_CACHED_FILES = 12
#: The catalogue depths, each an index of its own: (faintest Hp, longest edge in degrees, the
#: faintest camera limiting magnitude it serves).  The default index (Hp 6.5, ~8,000 stars) holds ~15 stars in
#: a 10 x 7.5 deg field, enough for the method (it needs 4-6); a narrower field (2-8 deg: a limiting magnitude
#: past 7, see :attr:`app.camera.Camera.limiting_magnitude`) needs fainter stars, and its longest edge is
#: the diagonal of the widest field it serves (10 x 7.5 deg: 12.5 deg).  Hipparcos-2 is complete to Hp
#: ~7.3-9 depending on the sky: Hp 8 is its depth where it is still nearly complete everywhere.
DEPTHS = ((6.5, 45.0, 7.0), (8.0, 15.0, float("inf")))


def _observer_key(velocity_km_s):
    """The observer of cached places: None (the Earth's centre), :data:`MEAN_PLACE` (no aberration), or
    the spacecraft's velocity to 1 m/s (which moves the aberration by < 0.001 arcsec)."""
    if velocity_km_s is None or is_mean_place(velocity_km_s):
        return velocity_km_s
    return tuple(np.round(velocity_km_s, 3))


class Sky:
    """The catalogue and the bright-pair index, loaded once (the identification context).

    Apparent star fields are cached per hour of observation time: the
    aberration changes by < 0.02 arcsec in an hour.
    """

    def __init__(self, index: BrightPairIndex | None = None, catalogue: Catalogue | None = None):
        self.index = index or load_index()
        cat = (catalogue or load_catalogue()).brighter_than(self.index.mag_limit)
        if len(cat) != self.index.n_stars or not np.array_equal(cat.hip, self.index.hip):
            raise ValueError("the bright-pair index was built from another catalogue")
        self.catalogue = cat
        self.names = star_names()
        self._fields: OrderedDict[tuple, StarField] = OrderedDict()
        self._apparent: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._row_of_hip = self.catalogue.index_of_hip()
        self._cells: dict[tuple[int, int], NearStarCells] = {}
        self._epoch_trees: dict[int, cKDTree] = {}
        self._motion_margins = None
        self._alone_within = None
        self._digest = None
        self._triangles = None
        self._depths: dict[tuple[float, float], Sky] = {}

    def for_camera(self, camera) -> "Sky":
        """The sky of the catalogue depth that ``camera``'s field needs (:data:`DEPTHS`): this one, or a
        deeper one (built on first use, and kept on disk like the default index)."""
        limit = camera.limiting_magnitude
        for mag, edge, serves in DEPTHS:
            if limit <= serves:
                return self.at_depth(mag, edge)
        return self

    def with_every_depth(self) -> "Sky":
        """This sky with every depth of :data:`DEPTHS` loaded, and their bright triangles: a server and its
        workers do it at start (0.1 s from the cache; the first time ever, the Hp 8 index is built, 15-25 s
        with a log line), so that no search pays for it (a worker's job is killed at 3 times the search's
        time-out)."""
        for mag, edge, _ in DEPTHS:
            self.at_depth(mag, edge).bright_triangles()
        return self

    def at_depth(self, mag_limit: float, max_edge_deg: float) -> "Sky":
        """The sky with an index of the stars to ``mag_limit`` (this one when it is that index).  The
        deeper skies share this one's cache of skies, so each depth is loaded once per process."""
        if abs(self.index.mag_limit - mag_limit) < 1e-9 and abs(np.degrees(self.index.max_edge_rad)
                                                                 - max_edge_deg) < 1e-6:
            return self
        key = (mag_limit, max_edge_deg)
        if key not in self._depths:
            deeper = Sky(index=load_index(mag_limit=mag_limit, max_edge_deg=max_edge_deg))
            deeper._depths = self._depths
            self._depths[key] = deeper
        return self._depths[key]

    def depth_for(self, camera, mag_margin: float) -> float:
        """The faintest magnitude a source seen by ``camera`` may be matched to here: its limiting magnitude
        plus ``mag_margin`` (brightness is unreliable, detection noisy), within this sky's index."""
        return min(camera.limiting_magnitude + mag_margin, self.index.mag_limit)

    def star_mask(self, mag_limit: float) -> np.ndarray:
        return self.index.mag <= mag_limit

    def apparent_vectors(self, t: datetime, velocity_km_s=None) -> np.ndarray:
        """Apparent places of every catalogue star in the index, for the hour of ``t`` (mean places for
        ``velocity_km_s`` :data:`app.catalogue.MEAN_PLACE`)."""
        key = (t.replace(minute=0, second=0, microsecond=0), _observer_key(velocity_km_s))
        if key not in self._apparent:
            self._apparent[key] = self.catalogue.apparent_vectors(key[0], velocity_km_s)
            while len(self._apparent) > 32:
                self._apparent.popitem(last=False)
        return self._apparent[key]

    def field(self, t: datetime, mag_limit: float, velocity_km_s=None) -> StarField:
        """The stars down to ``mag_limit`` (a prefix: stars are sorted brightest first) with a KD-tree."""
        n = int(self.star_mask(mag_limit).sum())
        key = (t.replace(minute=0, second=0, microsecond=0), n, _observer_key(velocity_km_s))
        if key not in self._fields:
            vectors = self.apparent_vectors(t, velocity_km_s)[:n]
            static = (abs(julian_year(t) - self.index.epoch_jyear) <= MAX_YEARS
                      and (velocity_km_s is None or is_mean_place(velocity_km_s)
                           or float(np.linalg.norm(velocity_km_s)) <= MAX_SPACECRAFT_SPEED_KM_S))
            cells = (lambda radius, make=True: self.near_star_cells(n, radius, make)) if static else None
            self._fields[key] = StarField.from_vectors(vectors, np.arange(n), cells=cells,
                                                       alone_within=self.alone_within()[:n] if static else None,
                                                       mag=self.index.mag[:n],
                                                       epoch_places=self._epoch_places(n, vectors))
            while len(self._fields) > 32:
                self._fields.popitem(last=False)
        return self._fields[key]

    def _epoch_places(self, n: int, vectors: np.ndarray) -> tuple[cKDTree, float]:
        """A KD-tree of the ``n`` brightest stars at the index's epoch (made once per process) and the
        largest chord between a star's place there and in ``vectors`` (see :meth:`StarField.nearest_chords`)."""
        if n not in self._epoch_trees:
            self._epoch_trees[n] = cKDTree(self.index.vectors[:n], balanced_tree=False, compact_nodes=False)
        shift = float(np.sqrt(np.max(np.sum((vectors - self.index.vectors[:n]) ** 2, axis=1)))) if n else 0.0
        return self._epoch_trees[n], shift * (1 + 1e-9)

    def near_star_cells(self, n: int, radius_rad: float, make: bool = True) -> NearStarCells | None:
        """A cell map of the ``n`` brightest stars for a radius of at least ``radius_rad`` (cached); with
        ``make`` False, the smallest one this process has already that is at least that large, or None.

        One map serves every observation time within :data:`MAX_YEARS` of
        the index epoch (see :mod:`app.identification.cells`).  A map made
        for up to twice the radius asked is used as it is (a larger radius
        only marks more cells, whose stars are then measured and found too
        far: the answer is the same); a new one is made for 1.2 to 1.7 times
        the radius (1e-4 rad times a power of sqrt 2), so that a camera's
        check tolerances, most of them near its 10 pixels, share one or two
        maps.  A map takes ~30-50 ms to make, so it is kept on disk beside
        the index (1-4 MB, a few ms to load).
        """
        if not 0 < radius_rad <= 0.1:  # wider than any check tolerance: the tree alone
            return None
        if not make:
            large_enough = [m for (k, _), m in self._cells.items() if k == n and m.radius_rad >= radius_rad]
            return min(large_enough, key=lambda m: m.radius_rad) if large_enough else None
        fitting = [m for (k, _), m in self._cells.items() if k == n and radius_rad <= m.radius_rad <= 2 * radius_rad]
        if fitting:
            return min(fitting, key=lambda m: m.radius_rad)
        step = math.ceil(2 * math.log2(1.2 * radius_rad / 1e-4) - 1e-9)
        cells = self._load_or_build_cells(n, 1e-4 * 2 ** (step / 2))
        self._cells[(n, step)] = cells
        return cells

    def _load_or_build_cells(self, n: int, radius_rad: float) -> NearStarCells:
        params = {"format": NearStarCells.FORMAT, "n": n, "radius": radius_rad, "years": MAX_YEARS,
                  "speed": MAX_SPACECRAFT_SPEED_KM_S, "stars": self._stars_digest()}
        arrays = self._cached("near-star-cells", params, lambda: NearStarCells.build(
            self.index.vectors[:n], radius_rad, self.motion_margins()[:n]).arrays())
        return NearStarCells.from_arrays(arrays)

    def _cached(self, name: str, params: dict, make) -> dict[str, np.ndarray]:
        """Arrays derived from the stars alone, from the disk cache beside the index, else ``make()``
        (then written there).  A file that cannot be read is made again, never trusted."""
        from app.config import settings

        digest = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:16]
        path = Path(settings().cache_dir) / f"{name}-{digest}.npz"
        arrays = kept_arrays(path)
        if arrays is not None:
            return arrays
        with exclusive(path.with_suffix(".lock")):  # processes wanting it at once: the first makes it
            arrays = kept_arrays(path)  # made by another process while this one waited
            return arrays if arrays is not None else self._make_and_keep(path, name, make)

    @staticmethod
    def _make_and_keep(path: Path, name: str, make) -> dict[str, np.ndarray]:
        """``make()``, kept at ``path`` (:func:`app.cache.keep_arrays`), as contiguous arrays: the form every later
        process loads them in, so that a compiled kernel called on them has one signature whoever made them (a
        column view made the shape lookup compile a second one inside the first search after an install,
        0.26 s; found 2026-11-26)."""
        arrays = {key: np.asarray(a, order="C") for key, a in make().items()}
        keep_arrays(path, **arrays)
        # The least recently made beyond MAX_CACHED_FILES go: a camera uses one or two maps, and ever new
        # cameras must not fill the disk.
        files = sorted(path.parent.glob(f"{name}-*.npz"), key=lambda f: f.stat().st_mtime, reverse=True)
        for old in files[MAX_CACHED_FILES:]:
            if old != path:
                for gone in (old, old.with_suffix(".lock")):
                    try:
                        gone.unlink()
                    except OSError:  # another process removed it first (or it had no lock file)
                        pass
        return arrays

    def _stars_digest(self) -> str:
        """What the cell maps are made from: the index's stars and their proper motions."""
        if self._digest is None:
            h = hashlib.sha256()
            for a in (self.index.hip, self.index.vectors, self.catalogue.pm_ra_cosdec_mas_yr,
                      self.catalogue.pm_dec_mas_yr):
                h.update(np.ascontiguousarray(a).tobytes())
            self._digest = h.hexdigest()[:16]
        return self._digest

    def alone_within(self) -> np.ndarray:
        """(n_stars,) chord within which a point's nearest star is certainly that star, at any epoch within
        :data:`MAX_YEARS` of the index's: half the angle to its nearest neighbour, less both stars' motion
        margins (:func:`app.identification.cells.motion_margin_rad`).  Made once (~10 ms), kept on disk."""
        if self._alone_within is None:
            params = {"format": 1, "years": MAX_YEARS, "speed": MAX_SPACECRAFT_SPEED_KM_S,
                      "stars": self._stars_digest()}
            self._alone_within = self._cached("alone-within", params, lambda: {"chord": self._make_alone_within()})["chord"]
        return self._alone_within

    def _make_alone_within(self) -> np.ndarray:
        margin = self.motion_margins()
        vectors = self.index.vectors
        reach = np.radians(1.0)
        # Beyond `reach` at the index epoch, a neighbour can come at most its margin closer.
        nearest = np.full(len(vectors), reach) - margin - margin.max()
        i, j = cKDTree(vectors).query_pairs(float(chord(reach)), output_type="ndarray").T
        if len(i):
            gap = angle_between(vectors[i], vectors[j]) - margin[i] - margin[j]
            np.minimum.at(nearest, i, gap)
            np.minimum.at(nearest, j, gap)
        return chord(np.maximum(nearest, 0.0) / 2) * (1 - 1e-9)

    def bright_triangles(self):
        """The index's :class:`app.identification.triangle_index.BrightTriangles` (made once, ~0.15 s,
        and kept on disk beside the index: a few ms to load)."""
        if self._triangles is None:
            h = hashlib.sha256()
            for a in (self.index.star_a, self.index.star_b, self.index.vectors):
                h.update(np.ascontiguousarray(a).tobytes())
            params = {"format": BrightTriangles.FORMAT, "index": h.hexdigest()[:16]}
            arrays = self._cached("bright-triangles", params, lambda: bright_triangles(self.index).arrays())
            self._triangles = BrightTriangles(**arrays)
        return self._triangles

    def motion_margins(self) -> np.ndarray:
        if self._motion_margins is None:
            self._motion_margins = motion_margin_rad(self.catalogue.pm_ra_cosdec_mas_yr,
                                                     self.catalogue.pm_dec_mas_yr)
        return self._motion_margins

    def apparent_vectors_of(self, hips, t: datetime, velocity_km_s=None) -> np.ndarray:
        """Apparent places (unit vectors) of the stars with these HIP numbers at ``t``: any star of the bundled
        catalogue, so that stars named through a deeper sky (:meth:`for_camera`) are found here too."""
        if all(int(h) in self._row_of_hip for h in hips):
            rows = np.array([self._row_of_hip[int(h)] for h in hips], dtype=int)
            return self.apparent_vectors(t, velocity_km_s)[rows]
        every = load_catalogue()
        row_of = every.index_of_hip()
        rows = np.array([row_of[int(h)] for h in hips], dtype=int)
        return every.subset(rows).apparent_vectors(t.replace(minute=0, second=0, microsecond=0), velocity_km_s)

    def name(self, row: int) -> str | None:
        entry = self.names.get(int(self.index.hip[row]))
        return entry[0] if entry else None
