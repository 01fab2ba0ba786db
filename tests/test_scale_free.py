"""The field-of-view search (app/identification/scale_free.py, issue 26): its bands by hand-checked geometry,
and patterns seen by cameras whose optics nobody gave, against the simulator's truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from app.attitude import angle_between
from app.camera import CAMERAS
from app.extraction import extract
from app.identification import IDENTIFIED, identify
from app.identification.scale_free import (BAND_RATIO, FOV_RANGE_DEG, bands, focal_length_for_fov,
                                           fov_for_focal_length)
from app.simulate import simulate_sequence


def test_a_field_of_view_and_its_focal_length_are_the_pinholes_angle():
    # 1000 px across at f = 500 px: 2 atan(1) = 90 deg, and back.
    assert fov_for_focal_length(1000, 500.0) == pytest.approx(90.0, rel=1e-12)
    assert focal_length_for_fov(1000, 90.0) == pytest.approx(500.0, rel=1e-12)


@pytest.mark.parametrize("width", [640, 1392, 4000])
def test_the_bands_cover_the_range_without_gaps_each_at_most_the_band_ratio(width):
    found = bands(width)
    assert fov_for_focal_length(width, found[0].low_px) == pytest.approx(max(FOV_RANGE_DEG), rel=1e-9)
    assert fov_for_focal_length(width, found[-1].high_px) == pytest.approx(min(FOV_RANGE_DEG), rel=1e-9)
    for before, after in zip(found, found[1:]):
        assert after.low_px == pytest.approx(before.high_px, rel=1e-12)  # contiguous, widest field first
    for band in found:
        assert 1.0 < band.high_px / band.low_px <= BAND_RATIO + 1e-9
        # The band as a declared camera: its middle, known to +-tolerance, spans the band exactly.
        assert band.middle_px * (1 - band.tolerance) == pytest.approx(band.low_px, rel=1e-12)
        assert band.middle_px * (1 + band.tolerance) == pytest.approx(band.high_px, rel=1e-12)


def _unknown(camera):
    """The camera as a frame with no optics comes: a nominal 20 deg focal length, known to be unknown."""
    return dataclasses.replace(camera, focal_length_px=focal_length_for_fov(camera.width, 20.0),
                               focal_length_unknown=True, focal_length_tolerance=None, mag_limit=None)


@pytest.mark.parametrize("name, seed", [("narrow-1024x1024-12deg", 3), ("liebe-576x604-30deg", 4),
                                        ("tubsat-752x582-20deg", 5)])
def test_a_single_snapshot_of_unknown_optics_is_identified_with_its_focal_length(sky, name, seed):
    camera = CAMERAS[name]
    sequence, truth = simulate_sequence(np.random.default_rng([seed, 2626]), camera, "single")
    extraction = extract(sequence)
    t = sequence.snapshots[extraction.reference].time
    unknown = _unknown(camera)
    pattern = dataclasses.replace(extraction.pattern, vectors=unknown.pixels_to_vectors(extraction.pattern.xy))
    solution = identify(pattern, unknown, t, sky)
    assert solution.status == IDENTIFIED, solution.notes
    best = solution.candidates[0]
    assert best.camera is not None and not best.camera.focal_length_unknown
    assert abs(best.camera.focal_length_px / camera.focal_length_px - 1) < 0.005
    R = np.asarray(truth["rotation_matrices"][extraction.reference])
    assert math.degrees(angle_between(best.rotation_matrix[2], R[2])) < 0.1
    assert "field of view was not given" in solution.notes[0]


def test_random_points_of_unknown_optics_are_not_identified_and_the_search_is_bounded(sky):
    """Ten points where no stars are: every band is searched, none fits, within the time-out."""
    camera = _unknown(CAMERAS["tubsat-752x582-20deg"])
    rng = np.random.default_rng(2626)
    xy = np.column_stack([rng.uniform(20, camera.width - 20, 10), rng.uniform(20, camera.height - 20, 10)])
    sequence, _ = simulate_sequence(np.random.default_rng([1, 2626]), CAMERAS["tubsat-752x582-20deg"], "single")
    extraction = extract(sequence)
    pattern = dataclasses.replace(extraction.pattern, xy=xy, vectors=camera.pixels_to_vectors(xy),
                                  track_ids=np.arange(10), brightness=rng.uniform(100, 1000, 10),
                                  sightings=np.ones(10, int), sigma_px=np.full(10, 0.3))
    solution = identify(pattern, camera, sequence.snapshots[0].time, sky)
    assert solution.status != IDENTIFIED
    assert solution.elapsed_s < 2 * 5.0  # the search's time-out (SearchOptions.timeout_s) and one band's worth
    assert "field of view was not given" in solution.notes[0]


def test_each_search_after_the_shapes_counts_every_hypothesis_tried_before_it(sky):
    """Random points fit no shape: every band is then searched by bright pairs, and each search is told the
    hypotheses of all before it (the shapes checked, then each earlier band's), so that its false-match
    probability pays for the whole search over scales. A stand-in engine records what it is told."""
    from app.identification.result import NO_MATCH, Solution
    from app.identification.scale_free import bands, identify_unknown_scale

    camera = _unknown(CAMERAS["tubsat-752x582-20deg"])
    rng = np.random.default_rng(2727)
    xy = np.column_stack([rng.uniform(20, camera.width - 20, 10), rng.uniform(20, camera.height - 20, 10)])
    sequence, _ = simulate_sequence(np.random.default_rng([1, 2727]), CAMERAS["tubsat-752x582-20deg"], "single")
    pattern = dataclasses.replace(extract(sequence).pattern, xy=xy, vectors=camera.pixels_to_vectors(xy),
                                  track_ids=np.arange(10), brightness=rng.uniform(100, 1000, 10),
                                  sightings=np.ones(10, int), sigma_px=np.full(10, 0.3))
    told = []

    def engine(pattern, known, t, sky, *, hypotheses_before, **_):
        told.append(hypotheses_before)
        return Solution(status=NO_MATCH, candidates=(), n_hypotheses=hypotheses_before + 1000)

    solution = identify_unknown_scale(pattern, camera, sequence.snapshots[0].time, sky, identify=engine)
    assert solution.status == NO_MATCH
    assert len(told) == len(bands(camera.width))
    assert told[0] > 0  # the shape matches checked in every band
    assert told == [told[0] + 1000 * k for k in range(len(told))]
    assert solution.n_hypotheses == told[-1] + 1000
    assert "by bright pairs: no_match" in solution.notes[0]

