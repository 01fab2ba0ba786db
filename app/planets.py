"""Planets: where they are on the sky, for the simulator and for labelling.

Planets move with the stars inside a snapshot sequence but are not in the
star catalogue, so identification must tolerate them and the simulator must
put them at their true places.  Directions come from astropy's ``builtin``
ephemeris (no download): ``get_body(name, t)`` returns the apparent
geocentric place in GCRS, whose axes are the ICRS axes; it includes light
time and the aberration of the Earth's motion, like
:meth:`app.catalogue.Catalogue.apparent_vectors` does for stars.

Places are cached per whole minute: the fastest-moving planet, Mercury,
shifts by at most ~5 arcsec per minute against the stars, so taking the
place at the nearest minute errs by < 3 arcsec (a tenth of a pixel for the
narrowest camera here).
"""

from __future__ import annotations

import functools
from datetime import datetime, timedelta, timezone
from types import MappingProxyType

import numpy as np

from app.catalogue import AU_KM, SPEED_OF_LIGHT_KM_S, tt_julian_date

PLANETS = ("mercury", "venus", "mars", "jupiter", "saturn", "uranus", "neptune")

#: Typical visual magnitudes (rough, fixed): a planet's real brightness varies
#: with its distance and phase (Mars from -2.9 to +1.8), but a star sensor's
#: brightness is unreliable anyway and only the rank among the ~10 brightest
#: sources matters.  Mercury and Venus are only seen away from the Sun.
TYPICAL_MAGNITUDES = MappingProxyType({
    "mercury": 0.0,
    "venus": -4.0,
    "mars": 0.5,
    "jupiter": -2.2,
    "saturn": 0.7,
    "uranus": 5.7,
    "neptune": 7.8,
})


def planet_magnitudes() -> dict[str, float]:
    """Rough visual magnitude of each planet (the fixed :data:`TYPICAL_MAGNITUDES`)."""
    return dict(TYPICAL_MAGNITUDES)


def _nearest_minute(t: datetime) -> datetime:
    """``t`` (timezone-aware) rounded to the nearest whole minute, in UTC."""
    t = t.astimezone(timezone.utc)
    floor = t.replace(second=0, microsecond=0)
    return floor + timedelta(minutes=1) if (t - floor) >= timedelta(seconds=30) else floor


def _require_aware(t: datetime) -> None:
    if not isinstance(t, datetime) or t.tzinfo is None:
        raise ValueError("time must be a timezone-aware datetime (UTC)")




#: ERFA's plan94 numbers of the planets (the model behind astropy's "builtin" ephemeris).
PLAN94_INDEX = MappingProxyType({"mercury": 1, "venus": 2, "mars": 4, "jupiter": 5, "saturn": 6,
                                 "uranus": 7, "neptune": 8})


def _barycentric_au(name: str, jd_tt: float, epv=None) -> np.ndarray:
    """Barycentric position (au, ICRS axes) of the Sun, the Earth or a planet, as astropy's
    ``get_body_barycentric(name, time, ephemeris="builtin")`` computes it (TDB ~ TT).

    ``epv``: ``erfa.epv00(jd_tt, 0.0)`` when the caller has it already (the same numbers, once).
    """
    import erfa

    earth_helio, earth_bary = erfa.epv00(jd_tt, 0.0) if epv is None else epv
    if name == "earth":
        return np.asarray(earth_bary["p"], dtype=float)
    sun = np.asarray(earth_bary["p"], dtype=float) - np.asarray(earth_helio["p"], dtype=float)
    if name == "sun":
        return sun
    return np.asarray(erfa.plan94(jd_tt, 0.0, PLAN94_INDEX[name])["p"], dtype=float) + sun


@functools.lru_cache(maxsize=512)
def _body_vectors_at_minute(t_minute: datetime, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Apparent geocentric directions from the built-in (ERFA) ephemeris.

    The body's barycentric position at ``t - light time`` minus the Earth's at
    ``t``, then the annual aberration ``normalize(u + v_earth / c)``: the
    steps of ``astropy.coordinates.get_body`` without its frame machinery
    (20x faster), leaving out only light deflection (< 0.01").
    """
    import erfa

    jd = tt_julian_date(t_minute)
    epv = erfa.epv00(jd, 0.0)
    _, earth_bary = epv
    earth = np.asarray(earth_bary["p"], dtype=float) * AU_KM
    beta = np.asarray(earth_bary["v"], dtype=float) * AU_KM / 86400.0 / SPEED_OF_LIGHT_KM_S
    out = {}
    for name in names:
        d = _barycentric_au(name, jd, epv) * AU_KM - earth
        light_time_days = np.linalg.norm(d) / SPEED_OF_LIGHT_KM_S / 86400.0
        d = _barycentric_au(name, jd - light_time_days) * AU_KM - earth
        v = d / np.linalg.norm(d) + beta
        out[name] = v / np.linalg.norm(v)
        out[name].setflags(write=False)  # shared through the cache: keep it immutable
    return out


def planet_vectors(t: datetime) -> dict[str, np.ndarray]:
    """Apparent geocentric unit vector (ICRS/GCRS axes) of each planet at UTC ``t``.

    Taken at the nearest whole minute (see the module docstring).  The
    arrays are read-only; the dict is a fresh copy.
    """
    _require_aware(t)
    return dict(_body_vectors_at_minute(_nearest_minute(t), PLANETS))


def sun_vector(t: datetime) -> np.ndarray:
    """Apparent geocentric unit vector of the Sun at UTC ``t`` (nearest minute)."""
    _require_aware(t)
    return _body_vectors_at_minute(_nearest_minute(t), ("sun",))["sun"]
