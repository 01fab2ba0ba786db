"""The identification context: the catalogue and the bright-pair index, loaded once per process."""

from __future__ import annotations

from collections import OrderedDict
from datetime import datetime

import numpy as np

from app.catalogue import Catalogue, load_catalogue, star_names
from app.identification.verify import StarField
from app.index import BrightPairIndex, load_index


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

    def star_mask(self, mag_limit: float) -> np.ndarray:
        return self.index.mag <= mag_limit

    def apparent_vectors(self, t: datetime, velocity_km_s=None) -> np.ndarray:
        """Apparent places of every catalogue star in the index, for the hour of ``t``."""
        key = (t.replace(minute=0, second=0, microsecond=0),
               None if velocity_km_s is None else tuple(np.round(velocity_km_s, 3)))
        if key not in self._apparent:
            self._apparent[key] = self.catalogue.apparent_vectors(key[0], velocity_km_s)
            while len(self._apparent) > 32:
                self._apparent.popitem(last=False)
        return self._apparent[key]

    def field(self, t: datetime, mag_limit: float, velocity_km_s=None) -> StarField:
        """The stars down to ``mag_limit`` (a prefix: stars are sorted brightest first) with a KD-tree."""
        n = int(self.star_mask(mag_limit).sum())
        key = (t.replace(minute=0, second=0, microsecond=0), n,
               None if velocity_km_s is None else tuple(np.round(velocity_km_s, 3)))
        if key not in self._fields:
            vectors = self.apparent_vectors(t, velocity_km_s)[:n]
            self._fields[key] = StarField.from_vectors(vectors, np.arange(n))
            while len(self._fields) > 32:
                self._fields.popitem(last=False)
        return self._fields[key]

    def apparent_vectors_of(self, hips, t: datetime, velocity_km_s=None) -> np.ndarray:
        """Apparent places (unit vectors) of the stars with these HIP numbers at ``t``."""
        rows = np.array([self._row_of_hip[int(h)] for h in hips], dtype=int)
        return self.apparent_vectors(t, velocity_km_s)[rows]

    def name(self, row: int) -> str | None:
        entry = self.names.get(int(self.index.hip[row]))
        return entry[0] if entry else None
