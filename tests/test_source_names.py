"""Naming every reported source (``source_stars``): a name only where it is certain.

The rules are pinned on cases built by hand around a simulated sequence: a
ghost laid beside a faint star that no source reports, which the old rule
(the nearest star within 2 px) named; a star that only one snapshot reports,
which keeps its name; a bright star with a fainter one beside it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.camera import CAMERAS
from app.identification import solve_sequence, source_stars
from app.identification.__init__ import CHANCE_NAME_PROBABILITY, chance_of_falling_near
from app.identification.candidates import named_by_brightest
from app.identification.sightings import sources_field, stars_at
from app.identification.verify import StarField
from app.simulate import simulate_sequence

CAMERA = CAMERAS["tubsat-752x582-20deg"]


def _field_at(camera, pixels, mags) -> StarField:
    """Stars placed where ``camera`` (identity attitude) sees ``pixels``, with magnitudes ``mags``."""
    return StarField.from_vectors(camera.pixels_to_vectors(np.asarray(pixels, dtype=float)),
                                  np.arange(len(pixels)), mag=np.asarray(mags, dtype=float))


def test_a_source_between_a_bright_and_a_faint_star_is_the_bright_one():
    # The faint star (mag 6) lies 0.3 px from the source, the bright one (mag 3) 0.7 px: a sensor that
    # sees the bright one puts their blend in its place, so the nearest star is the wrong name.
    field = _field_at(CAMERA, [[300.0, 200.0], [301.0, 200.0], [500.0, 400.0]], [3.0, 6.0, 4.0])
    seen = stars_at(np.array([[300.7, 200.0], [500.2, 400.0], [100.0, 100.0]]), CAMERA, np.eye(3), field,
                    2 * CAMERA.pixel_scale_rad)
    assert seen.tolist() == [0, 2, -1]


def test_a_candidates_point_matched_to_a_faint_neighbour_takes_the_bright_star_unless_another_point_has_it():
    # Refinement matched point 0 to its nearest star, the faint one (row 1); the bright one (row 0) lies
    # within the point's match tolerance.  Point 1 is matched to row 2 and has no brighter star near.
    field = _field_at(CAMERA, [[300.0, 200.0], [301.0, 200.0], [500.0, 400.0]], [3.0, 6.0, 4.0])
    directions = CAMERA.pixels_to_vectors(np.array([[300.7, 200.0], [500.2, 400.0]]))
    tolerance = np.full(2, 2 * CAMERA.pixel_scale_rad)
    near = np.array([0.3, 0.2]) * CAMERA.pixel_scale_rad
    stars, residuals = named_by_brightest(np.array([1, 2]), near, directions, field, tolerance)
    assert stars.tolist() == [0, 2]
    assert residuals[0] == pytest.approx(np.arccos(directions[0] @ field.vectors[0]))
    assert residuals[1] == near[1]
    # When another point (a second source 0.5 px on the other side) names the bright star, the faint one
    # stays: two points never name one star.
    beside = CAMERA.pixels_to_vectors(np.array([[300.7, 200.0], [299.5, 200.0]]))
    stars, _ = named_by_brightest(np.array([1, 0]), near, beside, field, tolerance)
    assert stars.tolist() == [1, 0]


def test_the_chance_of_falling_near_a_star_is_its_disc_times_the_density_of_as_bright_stars():
    # 1,000 stars of magnitudes 0.0, 0.01, ..., 9.99 over the sky; the source lies 3 px from the one of
    # magnitude 5.0, so 501 stars are as bright: p = pi d^2 * 501 / (4 pi).
    mags = np.arange(1000) / 100.0
    rng = np.random.default_rng(3)
    vectors = rng.normal(size=(1000, 3))
    vectors /= np.linalg.norm(vectors, axis=1)[:, None]
    vectors[500] = CAMERA.pixels_to_vectors(np.array([[200.0, 150.0]]))[0]
    field = StarField.from_vectors(vectors, np.arange(1000), mag=mags)
    a, b = CAMERA.pixels_to_vectors(np.array([[200.0, 150.0], [203.0, 150.0]]))
    d_rad = np.arccos(a @ b)  # 3 px off the axis: a little less than 3 pixel scales
    chance = chance_of_falling_near(np.array([[203.0, 150.0], [10.0, 10.0]]), CAMERA, np.eye(3), field,
                                    np.array([500, -1]), noise_rad=0.1 * CAMERA.pixel_scale_rad)
    assert chance[0] == pytest.approx(np.pi * d_rad ** 2 * 501 / (4 * np.pi), rel=1e-3)
    assert chance[1] == np.inf


@pytest.fixture(scope="module")
def clean_sequence(sky):
    """A 16-snapshot sequence of the 20 deg camera, its truth, and its solved attitudes."""
    rng = np.random.default_rng(2024)
    sequence, truth = simulate_sequence(rng, CAMERA, "clean")
    solved = solve_sequence(sequence, sky)
    assert solved.solution.status == "identified"
    return sequence, truth, solved


def _with_source(sequence, position: int, xy) -> tuple:
    """``sequence`` with one source added at the end of snapshot ``position``."""
    snaps = list(sequence.snapshots)
    snap = snaps[position]
    snaps[position] = replace(snap, xy=np.vstack([snap.xy, xy]), brightness=np.append(snap.brightness, 1.0))
    return replace(sequence, snapshots=tuple(snaps))


def test_a_ghost_beside_a_faint_unreported_star_is_left_unnamed(sky, clean_sequence):
    sequence, truth, solved = clean_sequence
    fit = solved.sequence_fits[1]
    R = fit.attitude_at((sequence.snapshots[5].time - solved.reference_time).total_seconds())
    field = sources_field(sky.for_camera(CAMERA), sequence, solved.reference_time, CAMERA)
    reported = {src["hip"] for snap in truth["sources"] for src in snap if src["kind"] == "star"}
    xy, front = CAMERA.vectors_to_pixels(field.vectors @ R.T)
    inside = front & CAMERA.on_sensor(xy) & np.all((xy > 20) & (xy < [CAMERA.width - 21, CAMERA.height - 21]), axis=1)
    faint = [k for k in np.flatnonzero(inside) if field.mag[k] > CAMERA.limiting_magnitude
             and int(sky.index.hip[field.rows[k]]) not in reported]
    assert faint, "the field has faint stars on the sensor that the sensor did not report"
    star = faint[0]
    ghost = xy[star] + [1.5, 0.0]
    # The case the old rule got wrong: the star is the only one within 2 px of the ghost.
    assert stars_at(ghost[None], CAMERA, R, field, 2 * CAMERA.pixel_scale_rad).tolist() == [star]
    assert chance_of_falling_near(ghost[None], CAMERA, R, field, np.array([star]), 0.0)[0] > CHANCE_NAME_PROBABILITY

    with_ghost = _with_source(sequence, 5, ghost)
    named = source_stars(solve_sequence(with_ghost, sky), sky)
    names = named.names
    assert names[5][-1] is None
    # ... while the reported stars keep their names.
    truth_hips = [src["hip"] for src in truth["sources"][5]]
    assert names[5][:-1] == truth_hips
    assert named.uncertain == 1 and "1 source(s) near a star left unnamed" in named.note


def test_a_bright_star_reported_by_one_snapshot_only_keeps_its_name(sky, clean_sequence):
    sequence, truth, solved = clean_sequence
    # The brightest star: drop its sightings from every snapshot but the last, so tracking cannot vouch for it.
    hips = [src["hip"] for snap in truth["sources"] for src in snap]
    brightest = min(set(hips), key=lambda h: sky.index.mag[np.flatnonzero(sky.index.hip == h)[0]])
    last = len(sequence.snapshots) - 1
    snaps, kept_truth = [], []
    for pos, (snap, labels) in enumerate(zip(sequence.snapshots, truth["sources"])):
        keep = np.array([pos == last or src["hip"] != brightest for src in labels])
        snaps.append(replace(snap, xy=snap.xy[keep], brightness=snap.brightness[keep]))
        kept_truth.append([src for src, k in zip(labels, keep) if k])
    once = replace(sequence, snapshots=tuple(snaps))
    names = source_stars(solve_sequence(once, sky), sky).names
    at = [src["hip"] for src in kept_truth[last]].index(brightest)
    assert names[last][at] == brightest
    named = [n for snap in names for n in snap if n is not None]
    right = [n == src["hip"] for snap_n, snap_t in zip(names, kept_truth) for n, src in zip(snap_n, snap_t)
             if n is not None]
    assert all(right) and len(named) >= 0.97 * sum(len(s) for s in kept_truth)
