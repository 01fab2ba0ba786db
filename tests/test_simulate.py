"""The simulator against its own truth, re-derived independently here.

Truth is checked by re-projecting: the catalogue star (or the planet) named
by the truth, seen with the truth rotation, must land on the reported pixel
within the position noise plus the integer rounding.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.attitude import rotation_from_quaternion, rotation_from_radec_roll
from app.camera import CAMERAS
from app.catalogue import load_catalogue
from app.cli import main as cli_main
from app.planets import planet_vectors, sun_vector
from app.simulate import (
    SCENARIOS, SensorModel, brightness_from_magnitude, detection_probability, simulate_sequence,
    write_simulation,
)
from app.telemetry.formats import load_telemetry_file

SAMPLES = Path(__file__).resolve().parent.parent / "sample_telemetry"
CAMERA_LIST = list(CAMERAS.values())
# Position noise sigma 0.3 px: 5 sigma plus half a pixel of rounding per axis.
PIXEL_TOLERANCE = 0.5 + 5 * 0.3


def parse_time(text: str) -> datetime:
    return datetime.fromisoformat(text.replace("Z", "+00:00"))


def true_pixel(camera, label: dict, R: np.ndarray, t: datetime, hip_index: dict, star_vectors) -> np.ndarray:
    """Where the truth says the source is: its catalogue or ephemeris place projected with R."""
    if label["kind"] == "star":
        v = star_vectors(t)[hip_index[label["hip"]]]
    else:
        v = planet_vectors(t)[label["planet"]]
    xy, front = camera.vectors_to_pixels(v @ R.T)
    assert front[0]
    return xy[0]


@pytest.fixture(scope="module")
def catalogue():
    return load_catalogue()


@pytest.fixture(scope="module")
def sims():
    """A few sequences of every scenario on every camera (~0.3 s in all)."""
    out = []
    for k, scenario in enumerate(SCENARIOS):
        for j, camera in enumerate(CAMERA_LIST):
            for rep in range(2):
                rng = np.random.default_rng([1234, k, j, rep])
                out.append((camera, *simulate_sequence(rng, camera, scenario)))
    return out


def check_truth_matches(camera, sequence, truth, catalogue, tolerance=PIXEL_TOLERANCE) -> int:
    """Assert every star/planet source sits at its truth place; return how many were checked."""
    hip_index = catalogue.index_of_hip()
    cache = {}

    def star_vectors(t):
        if t not in cache:
            cache[t] = catalogue.apparent_vectors(t)
        return cache[t]

    checked = 0
    for snap, labels, R, t_text in zip(sequence.snapshots, truth["sources"],
                                       truth["rotation_matrices"], truth["times"]):
        assert snap.n_sources == len(labels)
        t = parse_time(t_text)
        assert snap.time == t
        for xy, label in zip(snap.xy, labels):
            if label["kind"] in ("star", "planet"):
                expected = true_pixel(camera, label, np.array(R), t, hip_index, star_vectors)
                assert np.all(np.abs(xy - expected) <= tolerance), (label, xy, expected)
                checked += 1
    return checked


def test_same_seed_same_sequence_other_seed_differs():
    camera = CAMERAS["tubsat-752x582-20deg"]
    a_seq, a_truth = simulate_sequence(np.random.default_rng(7), camera, "ghosts")
    b_seq, b_truth = simulate_sequence(np.random.default_rng(7), camera, "ghosts")
    c_seq, _ = simulate_sequence(np.random.default_rng(8), camera, "ghosts")
    assert a_seq.to_json_dict() == b_seq.to_json_dict()
    assert a_truth == b_truth
    assert a_seq.to_json_dict()["snapshots"] != c_seq.to_json_dict()["snapshots"]


def test_write_simulation_is_byte_for_byte_deterministic(tmp_path):
    first = write_simulation(tmp_path / "a", 2, 42, None, "nominal")
    second = write_simulation(tmp_path / "b", 3, 42, None, "nominal")
    assert [p.name for p in first] == [p.name for p in second[:4]]
    for p, q in zip(first, second):
        assert p.read_bytes() == q.read_bytes()
    # Cameras cycle when none is named.
    cams = [json.loads(p.read_text())["camera"] for p in second if p.name.endswith(".truth.json")]
    assert cams == list(CAMERAS)


def test_sources_are_on_sensor_integer_and_at_most_ten(sims):
    for camera, sequence, truth in sims:
        for snap in sequence.snapshots:
            assert snap.n_sources <= 10
            assert np.all(snap.xy == np.round(snap.xy))
            assert np.all(camera.on_sensor(snap.xy))
            assert np.all((snap.brightness >= 1) & (snap.brightness <= 255))


def test_truth_places_match_reported_pixels(sims, catalogue):
    checked = sum(check_truth_matches(camera, seq, truth, catalogue) for camera, seq, truth in sims)
    assert checked > 1000


def test_noise_free_sensor_reproduces_projection_exactly(catalogue):
    exact = SensorModel(position_sigma_px=0.0, integer_pixels=False)
    for camera in CAMERA_LIST:
        seq, truth = simulate_sequence(np.random.default_rng(5), camera, "planet", sensor=exact)
        assert check_truth_matches(camera, seq, truth, catalogue, tolerance=1e-6) > 50
        assert not np.all(seq.snapshots[0].xy == np.round(seq.snapshots[0].xy))


def test_attitude_truth_is_consistent(sims):
    for _, sequence, truth in sims:
        rotations = [np.array(R) for R in truth["rotation_matrices"]]
        w = np.array(truth["body_rate_rad_s"])
        times = [parse_time(t) for t in truth["times"]]
        for R, q, (ra, dec, roll) in zip(rotations, truth["quaternions"], truth["radec_roll_deg"]):
            assert np.allclose(R @ R.T, np.eye(3), atol=1e-10)
            assert np.allclose(rotation_from_quaternion(q), R, atol=1e-9)
            assert np.allclose(rotation_from_radec_roll(ra, dec, roll), R, atol=1e-8)
        # Constant body rate: R_{i+1} R_i^T = exp(-[w]x dt).
        for i in range(len(rotations) - 1):
            dt = (times[i + 1] - times[i]).total_seconds()
            assert 1.0 <= dt <= 3.0
            step = Rotation.from_rotvec(-w * dt).as_matrix()
            assert np.allclose(rotations[i + 1] @ rotations[i].T, step, atol=1e-9)


def test_stars_move_a_few_to_thirty_pixels_per_snapshot(sims):
    """Median displacement of the same star between consecutive snapshots."""
    moves = []
    for _, sequence, truth in sims:
        for i in range(len(sequence.snapshots) - 1):
            here = {lab["object"]: xy for xy, lab in zip(sequence.snapshots[i].xy, truth["sources"][i])
                    if lab["kind"] == "star"}
            there = {lab["object"]: xy for xy, lab in zip(sequence.snapshots[i + 1].xy, truth["sources"][i + 1])
                     if lab["kind"] == "star"}
            common = here.keys() & there.keys()
            if common:
                moves.append(np.median([np.linalg.norm(here[k] - there[k]) for k in common]))
    moves = np.array(moves)
    assert 1.0 < np.median(moves) < 30.0
    assert moves.max() < 45.0


def test_earth_has_no_stars_and_incoherent_blobs(sims):
    earth = [(c, s, t) for c, s, t in sims if t["scenario"] == "earth"]
    assert earth
    for _, sequence, truth in earth:
        kinds = {lab["kind"] for labels in truth["sources"] for lab in labels}
        assert kinds <= {"earth", "ghost"}
        assert sum(s.n_sources for s in sequence.snapshots) > 50
        # Blob velocities differ: the spread of per-blob displacements is large.
        first = {lab["object"]: xy for xy, lab in zip(sequence.snapshots[0].xy, truth["sources"][0])}
        last = {lab["object"]: xy for xy, lab in zip(sequence.snapshots[-1].xy, truth["sources"][-1])}
        shifts = np.array([last[k] - first[k] for k in first.keys() & last.keys() if k.count(":") == 1])
        if len(shifts) >= 3:
            assert np.max(np.linalg.norm(shifts - np.median(shifts, axis=0), axis=1)) > 20.0


def test_sparse_has_four_or_five_stars(sims):
    sparse = [(s, t) for _, s, t in sims if t["scenario"] == "sparse"]
    for _, truth in sparse:
        stars = {lab["object"] for labels in truth["sources"] for lab in labels if lab["kind"] == "star"}
        assert len(stars) in (4, 5)


def test_ghost_scenario_counts(sims):
    for _, sequence, truth in [x for x in sims if x[2]["scenario"] == "ghosts"]:
        hot_objects = set()
        for labels in truth["sources"]:
            kinds = Counter(lab["kind"] for lab in labels)
            assert 1 <= kinds["ghost"] <= 3
            hot_objects |= {lab["object"] for lab in labels if lab["kind"] == "hot_pixel"}
        assert len(hot_objects) <= 2
        ghosts = Counter(lab["object"] for labels in truth["sources"] for lab in labels if lab["kind"] == "ghost")
        assert set(ghosts.values()) == {1}
        # A hot pixel stays on the same integer pixel.
        for obj in hot_objects:
            places = {tuple(xy) for snap, labels in zip(sequence.snapshots, truth["sources"])
                      for xy, lab in zip(snap.xy, labels) if lab["object"] == obj}
            assert len(places) == 1


def test_nominal_has_at_most_one_ghost_and_no_hot_pixel(sims):
    for _, _, truth in [x for x in sims if x[2]["scenario"] == "nominal"]:
        for labels in truth["sources"]:
            kinds = Counter(lab["kind"] for lab in labels)
            assert kinds["ghost"] <= 1 and kinds["hot_pixel"] == 0


def test_planet_scenario_shows_the_planet_at_its_ephemeris_place(sims):
    for camera, sequence, truth in [x for x in sims if x[2]["scenario"] == "planet"]:
        name = truth["target_planet"]
        t_mid = parse_time(truth["times"][len(truth["times"]) // 2])
        elongation = math.degrees(math.acos(planet_vectors(t_mid)[name] @ sun_vector(t_mid)))
        assert elongation >= 40.0
        sightings = 0
        for snap, labels, R, t in zip(sequence.snapshots, truth["sources"], truth["rotation_matrices"],
                                      truth["times"]):
            for xy, lab in zip(snap.xy, labels):
                if lab["planet"] == name:
                    expected, _ = camera.vectors_to_pixels(planet_vectors(parse_time(t))[name] @ np.array(R).T)
                    assert np.all(np.abs(xy - expected[0]) <= PIXEL_TOLERANCE)
                    sightings += 1
        assert sightings >= len(sequence.snapshots) // 2


def test_single_and_big_dipper(sims):
    for _, sequence, truth in sims:
        if truth["scenario"] == "single":
            assert len(sequence.snapshots) == 1
        if truth["scenario"] == "big-dipper":
            ra, dec, _ = truth["radec_roll_deg"][len(truth["times"]) // 2]
            assert abs(ra - 178.0) < 1e-6 and abs(dec - 56.0) < 1e-6
            dipper = {54061, 53910, 58001, 59774, 62956, 65378, 67301}  # Dubhe ... Alkaid
            seen = {lab["hip"] for labels in truth["sources"] for lab in labels}
            assert len(dipper & seen) >= 2


def test_pointing_and_start_time_are_honoured():
    camera = CAMERAS["liebe-576x604-30deg"]
    start = datetime(1994, 3, 12, 21, 4, 10, tzinfo=timezone.utc)
    seq, truth = simulate_sequence(np.random.default_rng(1), camera, "nominal", n_snapshots=5,
                                   pointing=(83.8, -5.4, 30.0), start_time=start, sequence_id="orion")
    assert seq.sequence_id == truth["sequence_id"] == "orion"
    assert seq.snapshots[0].time == start and len(seq.snapshots) == 5
    assert np.allclose(truth["radec_roll_deg"][2], [83.8, -5.4, 30.0], atol=1e-6)


def test_dropout_and_brightness_laws():
    assert detection_probability(5.5, 5.5, 0.15) == pytest.approx(0.5)
    assert detection_probability(5.0, 5.5, 0.15) > 0.95
    assert detection_probability(6.0, 5.5, 0.15) < 0.05
    b = brightness_from_magnitude(np.array([-1.0, 1.5, 4.0]), 1.5)
    assert b[0] == 255.0 and b[1] == 255.0
    assert b[2] == pytest.approx(255.0 / 10.0)


def test_bad_arguments_raise_value_error():
    camera = CAMERAS["tubsat-752x582-20deg"]
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError):
        simulate_sequence(rng, camera, "moon")
    with pytest.raises(ValueError):
        simulate_sequence(rng, camera, n_snapshots=0)
    with pytest.raises(ValueError):
        simulate_sequence(rng, camera, "planet", planet="pluto")
    with pytest.raises(ValueError):
        simulate_sequence(rng, camera, start_time=datetime(2000, 1, 1))
    with pytest.raises(ValueError):
        simulate_sequence(rng, camera, start_time=datetime(1850, 1, 1, tzinfo=timezone.utc))


def test_cli_writes_parseable_files(tmp_path, catalogue, capsys):
    assert cli_main(["simulate", str(tmp_path), "--n", "2", "--seed", "3", "--scenario", "ghosts"]) == 0
    assert cli_main(["simulate", str(tmp_path), "--seed", "3", "--name", "c", "--csv"]) == 0
    printed = capsys.readouterr().out.split()
    assert len(printed) == 6
    for data in sorted(tmp_path.glob("*.json")) + sorted(tmp_path.glob("*.csv")):
        if data.name.endswith(".truth.json"):
            continue
        truth = json.loads(data.with_name(data.name.rsplit(".", 1)[0] + ".truth.json").read_text())
        sequence = load_telemetry_file(data)
        assert check_truth_matches(CAMERAS[truth["camera"]], sequence, truth, catalogue) > 10
    with pytest.raises(SystemExit):  # argparse rejects an unknown camera with status 2
        cli_main(["simulate", str(tmp_path), "--camera", "nope"])


def test_cli_reports_unwritable_outdir(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert cli_main(["simulate", str(blocker / "sub")]) == 2
    assert "error" in capsys.readouterr().err
    assert cli_main(["simulate", str(tmp_path), "--name", "../escape"]) == 2
    assert not (tmp_path.parent / "escape.json").exists()
    assert cli_main(["simulate", str(tmp_path), "--start-time", "1850-01-01T00:00:00Z"]) == 2
    with pytest.raises(SystemExit):  # not a time at all: argparse's usage error
        cli_main(["simulate", str(tmp_path), "--start-time", "yesterday"])


def test_sample_files_parse_and_match_their_truth(catalogue):
    data_files = sorted(p for p in SAMPLES.iterdir()
                        if p.suffix in (".json", ".csv") and not p.name.endswith(".truth.json"))
    assert len(data_files) >= 8
    assert any(p.suffix == ".csv" for p in data_files)
    readme = (SAMPLES / "README.md").read_text()
    scenarios = set()
    for path in data_files:
        assert path.stat().st_size < 20_000
        assert path.name in readme
        truth_path = path.with_name(path.name.rsplit(".", 1)[0] + ".truth.json")
        truth = json.loads(truth_path.read_text())
        sequence = load_telemetry_file(path)
        assert sequence.sequence_id == truth["sequence_id"]
        check_truth_matches(CAMERAS[truth["camera"]], sequence, truth, catalogue)
        scenarios.add(truth["scenario"])
    assert {"nominal", "ghosts", "planet", "big-dipper", "earth", "sparse", "single"} <= scenarios


def test_sample_readme_commands_regenerate_the_files(tmp_path):
    """The README's commands, run into a scratch directory, give the checked-in bytes."""
    commands = [line.split()[5:] for line in (SAMPLES / "README.md").read_text().splitlines()
                if line.startswith("python -m app simulate sample_telemetry ")]
    assert len(commands) >= 8
    for args in commands:
        assert cli_main(["simulate", str(tmp_path), *args]) == 0
    written = sorted(p.name for p in tmp_path.iterdir())
    assert written == sorted(p.name for p in SAMPLES.iterdir() if p.name != "README.md")
    for name in written:
        assert (tmp_path / name).read_bytes() == (SAMPLES / name).read_bytes(), name
