"""Issue 12, items 1 and 2 at the stage level: physical camera bounds in the parser, bounded extraction.

Truth here is either the parser's contract (a located problem at the field
that is out of bounds) or the simulator's truth (which sources are stars),
and the uncapped extraction as the reference for the capped one.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from app.bench.load import WORST_CASE_SHAPES, worst_case_telemetry
from app.camera import CAMERAS
from app.extraction import ExtractionParameters, extract
from app.extraction.motion import _brightest_first, _hypotheses, _pair_chords
from app.identification import SearchOptions, solve_sequence
from app.simulate import SensorModel, simulate_sequence
from app.telemetry import TelemetryError, parse_telemetry
from app.telemetry.formats import MAX_FIELD_OF_VIEW_DEG, MIN_FIELD_OF_VIEW_DEG

CAMERA = {"width": 752, "height": 582, "focal_length_px": 2132.4, "cx": 375.5, "cy": 290.5}
SOURCES = [{"x": 100.0 + 40 * k, "y": 80.0 + 30 * k, "brightness": 200.0 - 10 * k} for k in range(8)]


def document(**camera_changes) -> dict:
    camera = {**CAMERA, **camera_changes}
    return {"format": "tubsat-snapshots/1", "sequence_id": "B", "camera": camera,
            "snapshots": [{"index": i, "time": f"2020-01-01T00:00:0{i}Z", "sources": SOURCES} for i in range(3)]}


def focal_for_diagonal_fov(width: int, height: int, fov_deg: float) -> float:
    return math.hypot(width, height) / 2 / math.tan(math.radians(fov_deg) / 2)


# ---------------------------------------------------------------------------
# Item 1: every camera field has physical bounds, refused where it is
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("changes, location, words", [
    ({"focal_length_px": 1e-300}, "camera.focal_length_px", "field of view"),   # was an OverflowError (500)
    ({"focal_length_px": 1e9}, "camera.focal_length_px", "field of view"),      # was a math domain error (500)
    ({"focal_length_px": 10.0}, "camera.focal_length_px", "178 deg"),
    ({"focal_length_px": -5.0}, "camera.focal_length_px", "> 0"),
    ({"width": 100_000, "height": 100_000}, "camera.focal_length_px", "field of view"),
    ({"cx": 1e300}, "camera.cx", "principal point"),
    ({"cy": -1e9}, "camera.cy", "principal point"),
    ({"k1": 9.9}, "camera.k1", "sensor corner"),
    ({"focal_length_px": 399.0, "k1": 0.5, "k2": -0.35}, "camera.k1", "fold"),  # 100 deg: corner 0.3 %, folds
    ({"mag_limit": -100}, "camera.mag_limit", "between 0 and 12"),             # was a 500 in a tf search
    ({"mag_limit": 1e300}, "camera.mag_limit", "between 0 and 12"),
])
def test_camera_out_of_physical_bounds_is_refused_at_its_field(changes, location, words):
    with pytest.raises(TelemetryError) as caught:
        parse_telemetry(json.dumps(document(**changes)))
    problems = {p.location: p.message for p in caught.value.problems}
    assert location in problems, problems
    assert words in problems[location]


def test_non_finite_camera_values_are_refused_at_their_field():
    for key in ("focal_length_px", "cx", "k2", "mag_limit"):
        text = json.dumps(document(**{key: 1.5})).replace(f'"{key}": 1.5', f'"{key}": NaN')
        with pytest.raises(TelemetryError) as caught:
            parse_telemetry(text)
        assert [p.location for p in caught.value.problems] == [f"camera.{key}"]


def test_csv_camera_bounds_are_located_at_the_header_line():
    text = ("# sequence_id: B\n# camera: width=752 height=582 focal_length_px=1e9 cx=375.5 cy=290.5 mag_limit=-3\n"
            "snapshot,time,x,y,brightness\n0,2020-01-01T00:00:00Z,10,10,5\n")
    with pytest.raises(TelemetryError) as caught:
        parse_telemetry(text)
    assert {p.location for p in caught.value.problems} == {"line 2, camera.focal_length_px", "line 2, camera.mag_limit"}


def test_stored_text_stays_readable_when_bounds_tighten():
    """An archive reads what it once accepted: the bounds apply to new input only."""
    text = json.dumps(document(mag_limit=-100, cx=-1e6))
    sequence = parse_telemetry(text, physical_bounds=False)
    assert sequence.camera.mag_limit == -100 and sequence.camera.cx == -1e6
    with pytest.raises(TelemetryError):
        parse_telemetry(text)


@pytest.mark.parametrize("fov_deg", [MIN_FIELD_OF_VIEW_DEG * 1.0001, 20.0, MAX_FIELD_OF_VIEW_DEG * 0.9999])
@pytest.mark.parametrize("mag_limit", [0.0, 12.0])
def test_cameras_at_the_bounds_are_accepted_and_solved_without_error(sky, fov_deg, mag_limit):
    """The bounds are where the pipeline still works: extraction and both identifiers run to a status."""
    focal = focal_for_diagonal_fov(752, 582, fov_deg)
    sequence = parse_telemetry(json.dumps(document(focal_length_px=focal, mag_limit=mag_limit, cx=-376.5,
                                                   cy=872.5)))
    methods = ("bright_pair", "tf") if fov_deg < 100 else ("bright_pair",)  # tf's database for 120 deg: see report
    for method in methods:
        solved = solve_sequence(sequence, sky, options=SearchOptions(timeout_s=2.0), method=method)
        assert solved.solution.status in ("identified", "ambiguous", "no_match")


# ---------------------------------------------------------------------------
# Item 2: extraction's work is capped, brightest first, and changes nothing below the cap
# ---------------------------------------------------------------------------

def test_brightest_first_keeps_whole_groups_that_fit_and_cuts_the_rest_by_rank():
    group = np.array([0, 0, 0, 1, 1, 1, 1])
    rank = np.array([5, 1, 3, 2, 2, 0, 9])
    count = np.array([4, 4, 4, 1, 1, 1, 1])
    kept = _brightest_first(group, rank, count, cap=np.array([6, 10]))
    # group 0: rank 1 (4 of 4), then rank 3 (2 of 4), then rank 5 nothing; group 1 fits whole
    assert kept.tolist() == [0, 4, 2, 1, 1, 1, 1]


def test_the_hypothesis_cap_holds_per_link_and_takes_the_brightest_sources():
    rng = np.random.default_rng(4)
    vectors = rng.normal(size=(3, 20, 3)) * [0.1, 0.1, 1.0] + [0, 0, 1]
    vectors /= np.linalg.norm(vectors, axis=-1, keepdims=True)
    chords, pi, pj = _pair_chords(vectors)
    links = np.array([[0, 1], [1, 2]])
    everything = _hypotheses(chords, pi, pj, links, pair_tol=0.01, min_baseline=0.0)
    capped = _hypotheses(chords, pi, pj, links, pair_tol=0.01, min_baseline=0.0, cap=np.array([50, 50]))
    all_per_link = np.bincount(everything[0], minlength=2)
    assert np.all(all_per_link > 50)  # the cap really cuts here
    assert np.bincount(capped[0], minlength=2).tolist() == [50, 50]
    for link in (0, 1):
        rank_all = np.max(np.stack(everything[1:]), axis=0)[everything[0] == link]
        rank_kept = np.max(np.stack(capped[1:]), axis=0)[capped[0] == link]
        assert rank_kept.max() <= np.sort(rank_all)[49]  # none fainter than the 50th brightest
    generous = _hypotheses(chords, pi, pj, links, pair_tol=0.01, min_baseline=0.0, cap=all_per_link + 1)
    assert all(np.array_equal(a, b) for a, b in zip(generous, everything))  # below the cap: the same, same order


def test_capped_extraction_equals_the_uncapped_one_on_ordinary_sequences():
    uncapped = ExtractionParameters(max_link_work=1 << 60)
    cameras = list(CAMERAS.values())
    for i, scenario in enumerate(("nominal", "ghosts3", "planet", "earth", "sparse", "big-dipper")):
        sequence, _ = simulate_sequence(np.random.default_rng([12, i]), cameras[i % 3], scenario)
        a, b = extract(sequence), extract(sequence, uncapped)
        assert all(np.array_equal(x, y) for x, y in zip(a.track_of_source, b.track_of_source)), scenario
        assert a.noise_px == b.noise_px and a.notes == b.notes


def test_capped_extraction_tracks_dense_real_star_fields_as_well_as_uncapped():
    """64 sources per snapshot of real stars (and ghosts): the cap must not cost tracked stars."""
    camera = dataclasses.replace(CAMERAS["liebe-576x604-30deg"], mag_limit=6.5)
    uncapped = ExtractionParameters(max_link_work=1 << 60)
    for i in range(2):
        sequence, truth = simulate_sequence(np.random.default_rng([3, i]), camera, "ghosts",
                                            sensor=SensorModel(max_sources=64))
        assert max(s.n_sources for s in sequence.snapshots) == 64
        kept = {}
        for name, parameters in (("capped", ExtractionParameters()), ("uncapped", uncapped)):
            extraction = extract(sequence, parameters)
            stars = [(s, k) for s, labels in enumerate(truth["sources"]) for k, label in enumerate(labels)
                     if label["kind"] == "star"]
            kept[name] = np.mean([extraction.track_of_source[s][k] >= 0 for s, k in stars])
        assert kept["capped"] >= 0.95 and kept["capped"] >= kept["uncapped"] - 0.005, kept


@pytest.mark.parametrize("shape", WORST_CASE_SHAPES)
def test_worst_case_files_extract_without_error(shape):
    """Files that crashed (a rounding error below zero into a square root) or took seconds and gigabytes."""
    sequence = parse_telemetry(worst_case_telemetry(7, shape))
    assert sum(s.n_sources for s in sequence.snapshots) == 64 * 64
    extraction = extract(sequence)
    assert len(extraction.track_of_source) == 64
    if shape == "one_pixel":
        # the sky cannot be seen moving: everything stays on one pixel
        assert not any(np.any(t >= 0) for t in extraction.track_of_source) or extraction.notes


def test_a_static_grid_of_sources_no_longer_crashes_the_noise_estimate():
    """Exact matches give squared chords a rounding error below zero (was: math domain error, a 500)."""
    snapshots = [{"index": i, "time": f"2020-01-01T00:00:{i:02d}Z",
                  "sources": [{"x": 40.0 + (k % 8) * 90, "y": 30.0 + (k // 8) * 70, "brightness": float(k)}
                              for k in range(64)]} for i in range(8)]
    sequence = parse_telemetry(json.dumps({"sequence_id": "G", "camera": "tubsat-752x582-20deg",
                                           "snapshots": snapshots}))
    extraction = extract(sequence)
    assert len(extraction.tracks) == 64 and all(t.n_sightings == 8 for t in extraction.tracks)


@pytest.mark.parametrize("field", ["sequence_id", "spacecraft"])
def test_a_bidirectional_override_in_a_telemetry_name_is_refused_at_its_field(field):
    """U+202E in a name would make it read as another one in the console and CCSDS files: refused, named."""
    doc = {"format": "tubsat-snapshots/1", "sequence_id": "seq", "spacecraft": "SAT", "camera": "tubsat-752x582-20deg",
           "snapshots": [{"index": 0, "time": "2026-01-01T00:00:00Z", "sources": [{"x": 10, "y": 20, "brightness": 5}]}]}
    doc[field] = "SAT\u202e1-TUBSAT"
    with pytest.raises(TelemetryError) as refused:
        parse_telemetry(json.dumps(doc))
    assert [(p.location, p.message) for p in refused.value.problems] == [
        (field, "must not contain the bidirectional control U+202E")]
    doc[field] = "שמש-1 ☀"  # a right-to-left script and an emoji are names like any other
    assert parse_telemetry(json.dumps(doc)) is not None
