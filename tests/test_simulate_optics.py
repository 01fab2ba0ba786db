"""The simulator with true optics that differ from the declared camera (issue 11).

Truth is re-derived here: each source the truth labels as star HIP N must sit
where the *true* camera (written out from the truth file's ``true_camera``)
puts that catalogue star seen with the truth rotation, and not where the
declared camera would put it.
"""

from __future__ import annotations

import json
import math
from datetime import datetime

import numpy as np
import pytest

from scipy.spatial.transform import Rotation

from app.camera import CAMERAS, Camera
from app.camera_fit import Observation, calibrate
from app.catalogue import load_catalogue
from app.cli import main as cli_main
from app.simulate import (
    SensorModel, k1_for_corner_distortion, simulate_sequence, true_optics, truth_matched_stars,
    write_simulation,
)
from app.telemetry.formats import load_telemetry_file

DECLARED = CAMERAS["tubsat-752x582-20deg"]
PIXEL_TOLERANCE = 0.5 + 5 * 0.3  # rounding plus 5 sigma of noise, per axis


@pytest.fixture(scope="module")
def catalogue():
    return load_catalogue()


def camera_from_truth(declared: Camera, truth: dict) -> Camera:
    t = truth["true_camera"]
    return Camera(declared.width, declared.height, t["focal_length_px"], t["cx"], t["cy"], k1=t["k1"], k2=t["k2"])


def star_offsets(sequence, truth, camera, catalogue) -> np.ndarray:
    """|reported - projected| per axis for every (unblended) star source, projected with ``camera``."""
    rows = catalogue.index_of_hip()
    out = []
    for snap, labels, R, t in zip(sequence.snapshots, truth["sources"], truth["rotation_matrices"], truth["times"]):
        vectors = catalogue.apparent_vectors(datetime.fromisoformat(t.replace("Z", "+00:00")))
        for xy, label in zip(snap.xy, labels):
            if label["kind"] != "star" or "blend_of" in label:
                continue
            projected, front = camera.vectors_to_pixels(vectors[rows[label["hip"]]] @ np.asarray(R).T)
            assert front[0]
            out.append(np.abs(xy - projected[0]))
    return np.array(out)


def test_noise_free_sources_are_exactly_where_the_true_camera_puts_the_truth_stars(catalogue):
    true = true_optics(DECLARED, focal_error=0.03, k1=k1_for_corner_distortion(DECLARED, 0.01),
                       k2=0.05, cx_offset=3.0, cy_offset=-2.0)
    exact = SensorModel(position_sigma_px=0.0, integer_pixels=False, blend_radius_px=0.0)
    sequence, truth = simulate_sequence(np.random.default_rng(7), DECLARED, "clean", sensor=exact,
                                        true_camera=true)
    assert sequence.camera == DECLARED  # the telemetry declares the nominal camera
    truth_camera = camera_from_truth(DECLARED, truth)
    assert truth_camera.optics() == true.optics()
    offsets = star_offsets(sequence, truth, truth_camera, catalogue)
    assert len(offsets) > 50
    assert offsets.max() < 1e-6
    # ...and the declared camera puts them elsewhere: 3 % of the distance from the centre and more.
    declared_offsets = star_offsets(sequence, truth, DECLARED, catalogue)
    assert np.percentile(np.hypot(*declared_offsets.T), 90) > 6.0


def test_barrel_distortion_brings_no_star_from_beyond_the_field_onto_the_sensor(catalogue):
    """With k1 < 0 the radial polynomial folds far off-axis directions back onto the sensor (a star 60 deg
    away would be drawn among the field's): every star source of a sequence simulated with barrel
    distortion lies within the sensor's half diagonal of the boresight, where the true camera puts it."""
    true = true_optics(DECLARED, k1=k1_for_corner_distortion(DECLARED, -0.01))
    exact = SensorModel(position_sigma_px=0.0, integer_pixels=False, blend_radius_px=0.0)
    rows = catalogue.index_of_hip()
    limit = math.cos(1.01 * true.diagonal_fov_rad / 2)
    for seed in range(3):
        sequence, truth = simulate_sequence(np.random.default_rng(seed), DECLARED, "single", sensor=exact,
                                            true_camera=true)
        vectors = catalogue.apparent_vectors(datetime.fromisoformat(truth["times"][0].replace("Z", "+00:00")))
        R = np.asarray(truth["rotation_matrices"][0])
        boresight_cos = [float((vectors[rows[label["hip"]]] @ R.T)[2]) for label in truth["sources"][0]
                         if label["kind"] == "star"]
        assert len(boresight_cos) >= 5 and min(boresight_cos) >= limit
        offsets = star_offsets(sequence, truth, true, catalogue)
        assert offsets.max() < 1e-6


def test_cli_true_optics_files_declare_the_nominal_camera(tmp_path, catalogue, capsys):
    code = cli_main(["simulate", str(tmp_path), "--n", "2", "--seed", "5", "--camera", DECLARED.name,
                     "--focal-error", "0.03", "--corner-distortion", "0.01", "--cx-offset", "2.5"])
    assert code == 0
    for i in range(2):
        sequence = load_telemetry_file(tmp_path / f"sim-5-{i:04d}.json")
        truth = json.loads((tmp_path / f"sim-5-{i:04d}.truth.json").read_text())
        assert sequence.camera.optics() == DECLARED.optics()
        true = camera_from_truth(DECLARED, truth)
        assert true.focal_length_px == pytest.approx(DECLARED.focal_length_px * 1.03, rel=1e-12)
        assert true.k1 * true.corner_radius ** 2 == pytest.approx(0.01, rel=1e-9)
        assert true.cx == DECLARED.cx + 2.5 and true.cy == DECLARED.cy and true.k2 == 0.0
        offsets = star_offsets(sequence, truth, true, catalogue)
        assert len(offsets) > 20 and offsets.max() <= PIXEL_TOLERANCE
        assert star_offsets(sequence, truth, DECLARED, catalogue).max() > 3 * PIXEL_TOLERANCE


def test_k1_for_corner_distortion_moves_the_corner_by_that_fraction():
    for camera in CAMERAS.values():
        true = camera.with_optics(k1=k1_for_corner_distortion(camera, 0.01))
        corner = np.array([[-0.5, -0.5]])  # farthest corner of a centred principal point
        ray = camera.pixels_to_vectors(corner)
        moved, _ = true.vectors_to_pixels(ray)
        centre = np.array([camera.cx, camera.cy])
        ratio = np.linalg.norm(moved - centre) / np.linalg.norm(corner - centre)
        assert ratio == pytest.approx(1.01, abs=1e-9)
    assert k1_for_corner_distortion(DECLARED, 0.01) == pytest.approx(0.2011, abs=1e-4)


def test_exact_optics_leave_files_unchanged(tmp_path):
    """No flag, or flags that change nothing, give the same bytes and no true_camera in the truth."""
    plain = write_simulation(tmp_path / "a", 2, 3, None, "nominal")
    zero = write_simulation(tmp_path / "b", 2, 3, None, "nominal", focal_error=0.0, cx_offset=0.0)
    for p, q in zip(plain, zero):
        assert p.read_bytes() == q.read_bytes()
    assert all("true_camera" not in json.loads(p.read_text()) for p in plain if p.name.endswith(".truth.json"))


def test_same_seed_same_sky_other_projection():
    """True optics draw nothing random: the same stars are reported, only moved."""
    true = true_optics(DECLARED, focal_error=0.001)
    a, ta = simulate_sequence(np.random.default_rng(9), DECLARED, "clean")
    b, tb = simulate_sequence(np.random.default_rng(9), DECLARED, "clean", true_camera=true)
    assert ta["rotation_matrices"] == tb["rotation_matrices"] and ta["times"] == tb["times"]
    assert "true_camera" not in ta and tb["true_camera"]["focal_length_px"] == true.focal_length_px
    assert ta["sources"] != tb["sources"] or any(
        not np.array_equal(sa.xy, sb.xy) for sa, sb in zip(a.snapshots, b.snapshots))


LIEBE = CAMERAS["liebe-576x604-30deg"]


@pytest.mark.parametrize("camera, kwargs, message", [
    (DECLARED, {"focal_error": 0.3}, "focal_error must be between -0.2 and 0.2"),
    (DECLARED, {"focal_error": -0.25}, "focal_error must be between -0.2 and 0.2"),
    (DECLARED, {"focal_error": math.nan}, "focal_error must be a finite number"),
    (DECLARED, {"k1": 1.5}, r"k1 must be within \+-1"),
    (DECLARED, {"k2": -1.01}, r"k2 must be within \+-1"),
    (LIEBE, {"k1": 0.9}, r"move the sensor corner by 13.6 % of its radius; at most 10 % is simulated "
                         r"\(1 % is k1 = 0.0663 for this camera\)"),
    (LIEBE, {"k1": -0.7}, "move the sensor corner by -10.6 %"),
    (DECLARED, {"cx_offset": 200.0}, "cx_offset must be within"),
    (DECLARED, {"cy_offset": -146.0}, "cy_offset must be within"),
])
def test_true_optics_validation(camera, kwargs, message):
    with pytest.raises(ValueError, match=message):
        true_optics(camera, **kwargs)


def test_true_optics_within_limits():
    true = true_optics(DECLARED, focal_error=-0.2, k1=0.5, k2=-1.0, cx_offset=188.0, cy_offset=-145.5)
    assert true.focal_length_px == pytest.approx(0.8 * DECLARED.focal_length_px)
    assert (true.k1, true.k2, true.cx, true.cy) == (0.5, -1.0, DECLARED.cx + 188.0, DECLARED.cy - 145.5)
    assert true.name == DECLARED.name and true.mag_limit == DECLARED.mag_limit


def test_true_camera_of_another_size_is_refused():
    other = CAMERAS["liebe-576x604-30deg"]
    with pytest.raises(ValueError, match="sensor size"):
        simulate_sequence(np.random.default_rng(1), DECLARED, "clean", true_camera=other)


def test_cli_rejects_bad_optics(tmp_path, capsys):
    assert cli_main(["simulate", str(tmp_path / "x"), "--focal-error", "3"]) == 2
    assert "focal_error must be between -0.2 and 0.2 (a fraction: 0.03 is 3 %)" in capsys.readouterr().err
    assert cli_main(["simulate", str(tmp_path / "x"), "--camera", "liebe-576x604-30deg", "--k1", "0.9"]) == 2
    assert "at most 10 % is simulated" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # validated before anything is written
    with pytest.raises(SystemExit):
        cli_main(["simulate", str(tmp_path / "x"), "--k1", "0.1", "--corner-distortion", "0.01"])


def test_calibration_from_simulated_sequences_finds_the_true_optics():
    """End to end through the simulator: 20 sequences, stars matched by the truth, Wahba start."""
    true = true_optics(DECLARED, focal_error=0.03, k1=k1_for_corner_distortion(DECLARED, 0.01),
                       cx_offset=4.0, cy_offset=-3.0)
    observations = []
    for i in range(20):
        sequence, truth = simulate_sequence(np.random.default_rng([77, i]), DECLARED, "nominal", true_camera=true)
        for position, xy, vectors in truth_matched_stars(sequence, truth):
            assert np.all(vectors @ np.asarray(truth["rotation_matrices"][position])[2] > 0.9)  # in view
            if len(xy) >= 3:
                start, _ = Rotation.align_vectors(DECLARED.pixels_to_vectors(xy), vectors)
                observations.append(Observation(xy, vectors, start.as_matrix(), 0.3, sequence.sequence_id))
    cal = calibrate(observations, DECLARED, parameters=("f", "k1", "cx", "cy"))
    fitted = cal.camera.optics()
    assert abs(fitted["focal_length_px"] / true.focal_length_px - 1) < 0.0005
    assert abs(fitted["k1"] / true.k1 - 1) < 0.10
    assert abs(fitted["cx"] - true.cx) < 2.0 and abs(fitted["cy"] - true.cy) < 2.0
    assert cal.sequences_used == 20 and cal.rms_px_before > 5 > 0.7 > cal.rms_px_after
