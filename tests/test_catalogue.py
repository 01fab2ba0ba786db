"""Catalogue places against astropy's full astrometry, and the bundled star names."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np

from app.catalogue import constellations, load_catalogue, radec_to_vectors, star_names
from app.config import configure_astropy


def test_brightest_first_and_known_stars():
    cat = load_catalogue()
    assert np.all(np.diff(cat.mag) >= 0)
    assert int(cat.hip[0]) == 32349  # Sirius
    row = cat.index_of_hip()[54061]  # Dubhe
    ra, dec = np.degrees(cat.ra_rad[row]), np.degrees(cat.dec_rad[row])
    assert abs(ra - 165.93) < 0.01 and abs(dec - 61.75) < 0.01


def test_apparent_places_agree_with_astropy_gcrs():
    """Proper motion + annual aberration vs astropy (ICRS -> GCRS, which adds light deflection)."""
    configure_astropy()
    import astropy.units as u
    from astropy.coordinates import GCRS, SkyCoord
    from astropy.time import Time

    cat = load_catalogue().brighter_than(3.0)
    t = datetime(1994, 3, 12, 21, 4, 10, tzinfo=timezone.utc)
    ours = cat.apparent_vectors(t)
    c = SkyCoord(ra=cat.ra_rad * u.rad, dec=cat.dec_rad * u.rad, pm_ra_cosdec=cat.pm_ra_cosdec_mas_yr * u.mas / u.yr,
                 pm_dec=cat.pm_dec_mas_yr * u.mas / u.yr, distance=1e6 * u.pc,  # no parallax: star places only
                 radial_velocity=0 * u.km / u.s, obstime=Time(1991.25, format="jyear", scale="tcb"), frame="icrs")
    g = c.apply_space_motion(new_obstime=Time(t)).transform_to(GCRS(obstime=Time(t)))
    theirs = radec_to_vectors(g.ra.rad, g.dec.rad)
    sep = np.degrees(np.arccos(np.clip(np.sum(ours * theirs, axis=1), -1, 1))) * 3600
    # Gravitational light deflection (< 0.05" away from the Sun) and the
    # hour-rounded Earth velocity are all that differ.
    assert np.max(sep) < 0.1
    # And aberration itself is the ~20" effect that makes this test meaningful:
    mean = cat.mean_vectors(1994.2)
    shift = np.degrees(np.arccos(np.clip(np.sum(mean * theirs, axis=1), -1, 1))) * 3600
    assert np.max(shift) > 15


def test_star_names_are_in_their_constellations_and_bright():
    cat = load_catalogue()
    names = star_names()
    assert names[54061][0] == "Dubhe"
    index = cat.index_of_hip()
    rows = [index[h] for h in names]
    assert all(cat.mag[r] < 4.5 for r in rows)
    vectors = cat.mean_vectors(2000.0)[rows]
    assert constellations(vectors) == [names[h][1] for h in names]


def test_constellations_agree_with_astropy_everywhere():
    """The ERFA shortcut against astropy's get_constellation on random directions (all 88 are hit)."""
    configure_astropy()
    import astropy.units as u
    from astropy.coordinates import SkyCoord, get_constellation

    rng = np.random.default_rng(11)
    v = rng.normal(size=(5000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    ra, dec = np.arctan2(v[:, 1], v[:, 0]), np.arcsin(v[:, 2])
    theirs = get_constellation(SkyCoord(ra=ra * u.rad, dec=dec * u.rad, frame="icrs"), short_name=True)
    ours = constellations(v)
    assert ours == [str(c) for c in theirs]
    assert len(set(ours)) == 88


def test_rows_near_is_the_brute_force_cone():
    cat = load_catalogue()
    centre = radec_to_vectors(np.radians([83.8]), np.radians([-5.4]))[0]  # Orion
    radius = np.radians(12.0)
    near = cat.rows_near(centre, radius)
    v = cat.mean_vectors(2026.0)
    angle = np.arccos(np.clip(v @ centre, -1, 1))
    assert set(np.flatnonzero(angle <= radius)) <= set(near.tolist())
    assert np.all(angle[near] <= radius + np.radians(0.31))
    assert np.all(np.diff(near) > 0)


def test_the_parsed_catalogue_is_cached_and_a_damaged_cache_is_parsed_again(tmp_path, monkeypatch):
    """load_catalogue keeps the parsed text as .npz (issue 16: a fifth of the start-up); the cached columns
    are the parsed ones, bit for bit, and a damaged file is never trusted."""
    from app.catalogue import catalogue_cache_path, parse_catalogue

    monkeypatch.setenv("STARID_CACHE_DIR", str(tmp_path))
    path = catalogue_cache_path()
    assert path.parent == tmp_path and not path.exists()
    parsed = parse_catalogue()
    first = load_catalogue.__wrapped__()  # parses and writes the cache
    assert path.exists()
    cached = load_catalogue.__wrapped__()  # reads it
    for c in (first, cached):
        assert np.array_equal(c.hip, parsed[:, 0].astype(np.int64)) and np.array_equal(c.mag, parsed[:, 5])
        assert np.array_equal(c.ra_rad, parsed[:, 1]) and np.array_equal(c.pm_dec_mas_yr, parsed[:, 4])
    path.write_bytes(b"\x00 not an npz")
    again = load_catalogue.__wrapped__()
    assert np.array_equal(again.dec_rad, parsed[:, 2])
    with np.load(path) as z:  # rewritten
        assert np.array_equal(z["columns"], parsed)
