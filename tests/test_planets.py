"""app.planets against well-known published events (not against astropy itself)."""

from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from app.planets import PLANETS, TYPICAL_MAGNITUDES, planet_magnitudes, planet_vectors, sun_vector

OBLIQUITY_J2000_DEG = 23.4393


def utc(*args) -> datetime:
    return datetime(*args, tzinfo=timezone.utc)


def separation_deg(u: np.ndarray, v: np.ndarray) -> float:
    return math.degrees(math.atan2(np.linalg.norm(np.cross(u, v)), float(u @ v)))


def ecliptic_longitude_deg(v: np.ndarray) -> float:
    """Longitude in the J2000 ecliptic: rotate the equatorial vector about x by the obliquity."""
    e = math.radians(OBLIQUITY_J2000_DEG)
    y = v[1] * math.cos(e) + v[2] * math.sin(e)
    return math.degrees(math.atan2(y, v[0])) % 360.0


def test_all_planets_are_unit_vectors():
    places = planet_vectors(utc(2001, 5, 17, 3, 4, 5))
    assert sorted(places) == sorted(PLANETS)
    for v in places.values():
        assert v.shape == (3,)
        assert abs(np.linalg.norm(v) - 1.0) < 1e-12


def test_great_conjunction_2020():
    """Jupiter and Saturn 6.1 arcmin apart on 2020-12-21 ~18 UTC, at about RA 20h10m, Dec -20.5 deg."""
    places = planet_vectors(utc(2020, 12, 21, 18, 0))
    sep_arcmin = separation_deg(places["jupiter"], places["saturn"]) * 60
    assert 5.6 < sep_arcmin < 6.6
    jupiter = places["jupiter"]
    ra = math.degrees(math.atan2(jupiter[1], jupiter[0])) % 360
    dec = math.degrees(math.asin(jupiter[2]))
    assert abs(ra - 302.5) < 0.3
    assert abs(dec - (-20.55)) < 0.3


def test_transit_of_venus_2012():
    """Mid-transit 2012-06-06 01:29 UTC: Venus 9.2 arcmin from the Sun's centre, inside the 15.8' disk."""
    t = utc(2012, 6, 6, 1, 29)
    sep_arcmin = separation_deg(planet_vectors(t)["venus"], sun_vector(t)) * 60
    assert 8.4 < sep_arcmin < 10.0
    # Six hours later the transit was over: Venus had left the disk.
    later = t + timedelta(hours=6)
    assert separation_deg(planet_vectors(later)["venus"], sun_vector(later)) * 60 > 15.8


def test_jupiter_opposition_2022():
    """Jupiter at opposition on 2022-09-26 ~20 UTC: ecliptic longitudes 180 deg apart."""
    t = utc(2022, 9, 26, 20, 0)
    diff = (ecliptic_longitude_deg(planet_vectors(t)["jupiter"]) - ecliptic_longitude_deg(sun_vector(t))) % 360
    assert abs(diff - 180.0) < 0.3
    # A month earlier it was not: the Sun moves ~1 deg a day.
    t = utc(2022, 8, 26, 20, 0)
    diff = (ecliptic_longitude_deg(planet_vectors(t)["jupiter"]) - ecliptic_longitude_deg(sun_vector(t))) % 360
    assert abs(diff - 180.0) > 20.0


def test_cached_per_minute_and_read_only():
    a = planet_vectors(utc(2015, 3, 1, 12, 0, 10))
    b = planet_vectors(utc(2015, 3, 1, 12, 0, 25))  # same nearest minute
    c = planet_vectors(utc(2015, 3, 1, 12, 0, 40))  # next minute
    assert all(np.array_equal(a[p], b[p]) for p in PLANETS)
    assert not np.array_equal(a["mercury"], c["mercury"])
    with pytest.raises(ValueError):
        a["mars"][0] = 0.0
    # The returned dict is a copy: changing it does not touch the cache.
    a["mars"] = np.zeros(3)
    assert np.linalg.norm(planet_vectors(utc(2015, 3, 1, 12, 0, 10))["mars"]) > 0.99


def test_naive_time_is_refused():
    with pytest.raises(ValueError):
        planet_vectors(datetime(2015, 3, 1, 12, 0))


def test_magnitudes():
    mags = planet_magnitudes()
    assert set(mags) == set(PLANETS)
    assert mags["venus"] < mags["jupiter"] < mags["mars"] < mags["saturn"] < mags["uranus"] < mags["neptune"]
    mags["venus"] = 99.0
    assert TYPICAL_MAGNITUDES["venus"] == -4.0
