"""The joint attitude + camera fit and the calibration against known simulated optics.

Matched stars are simulated here directly (numpy and the catalogue, not
app.simulate): a true camera (focal length 3 % longer than declared, k1
moving the sensor corner by 1 % of its radius, optionally an offset principal
point) projects catalogue stars; Gaussian noise of 0.3 px is added (and, for
the sensor's integer pixels, rounding); the initial attitude is Wahba's
solution with the *declared* camera, as identification would give it.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.camera import CAMERAS, DEFAULT_FOCAL_LENGTH_TOLERANCE, Camera
from app.camera_fit import (
    Observation, calibrate, default_priors, fit_attitude_and_camera, parameter_names, parameters_for,
    project_with_jacobians, robust_scale,
)
from app.catalogue import load_catalogue
from app.telemetry.errors import TelemetryError
from app.telemetry.formats import dump_csv, dump_json, parse_telemetry

DECLARED = CAMERAS["tubsat-752x582-20deg"]
SIGMA_PX = 0.3
MAG_LIMIT = 5.5
STARS_PER_SNAPSHOT = 8


def true_camera(focal_error=0.03, corner_fraction=0.01, cx_offset=0.0, cy_offset=0.0) -> Camera:
    """Written out independently of app.simulate.true_optics: k1 r_corner^2 = corner_fraction."""
    f = DECLARED.focal_length_px * (1 + focal_error)
    half_diagonal = math.hypot(DECLARED.width / 2, DECLARED.height / 2)
    k1 = corner_fraction / (half_diagonal / f) ** 2
    return Camera(DECLARED.width, DECLARED.height, f, DECLARED.cx + cx_offset, DECLARED.cy + cy_offset, k1=k1)


TRUE = true_camera()


@pytest.fixture(scope="module")
def sky():
    """Unit vectors and magnitudes of the stars a 20 deg camera sees, brightest first."""
    catalogue = load_catalogue().brighter_than(MAG_LIMIT)
    return catalogue.mean_vectors(), catalogue.mag


def random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()


def snapshot_stars(rng, sky, camera, R, n_max, *, rounding=False):
    """(measured xy, star vectors, true xy) of the n_max brightest stars on the sensor, or None."""
    vectors, mag = sky
    front = vectors @ R[2] > 0.9
    idx = np.flatnonzero(front)
    xy, _ = camera.vectors_to_pixels(vectors[idx] @ R.T)
    on = camera.on_sensor(xy, margin=1.0)
    idx, xy = idx[on][:n_max], xy[on][:n_max]  # the catalogue is sorted brightest first
    if len(idx) < 3:
        return None
    measured = xy + rng.normal(0.0, SIGMA_PX, xy.shape)
    if rounding:
        measured = np.round(measured)
    return measured, vectors[idx], xy


def wahba(declared, xy, star_vectors) -> np.ndarray:
    rotation, _ = Rotation.align_vectors(declared.pixels_to_vectors(xy), star_vectors)
    return rotation.as_matrix()


def simulated_observations(seed, sky, n_sequences, camera=TRUE, *, snapshots=16, rounding=True,
                           stated_sigma_px=SIGMA_PX):
    """Sequences of snapshots turning slowly (~0.3 deg per snapshot); one Observation per snapshot.

    The noise is 0.3 px (plus rounding); each observation states ``stated_sigma_px``.
    """
    rng = np.random.default_rng(seed)
    observations, truth_rotations = [], []
    for s in range(n_sequences):
        R0 = random_rotation(rng)
        axis = rng.normal(size=3)
        step = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(0.3)).as_matrix()
        R = R0
        for _ in range(snapshots):
            R = step @ R
            got = snapshot_stars(rng, sky, camera, R, STARS_PER_SNAPSHOT, rounding=rounding)
            if got is None:
                continue
            xy, vectors, _ = got
            observations.append(Observation(xy, vectors, wahba(DECLARED, xy, vectors), stated_sigma_px,
                                            f"seq-{s}"))
            truth_rotations.append(R)
    return observations, truth_rotations


# --- the declared uncertainty (camera block) ---------------------------------------

def telemetry_with_camera(**camera_fields) -> str:
    camera = {"width": 752, "height": 582, "focal_length_px": 2132.4, "cx": 375.5, "cy": 290.5, **camera_fields}
    return json.dumps({"sequence_id": "u", "camera": camera, "snapshots": [
        {"index": 0, "time": "2000-01-01T00:00:00Z", "sources": [{"x": 10, "y": 20, "brightness": 5}]}]})


def test_camera_declares_its_uncertainty_and_round_trips():
    seq = parse_telemetry(telemetry_with_camera(focal_length_tolerance=0.02, k1_bound=0.3, k2_bound=0.05))
    camera = seq.camera
    assert (camera.focal_length_tolerance, camera.k1_bound, camera.k2_bound) == (0.02, 0.3, 0.05)
    assert camera.focal_tolerance == 0.02
    for text in (dump_json(seq), dump_csv(seq)):
        assert parse_telemetry(text, filename="u.csv" if text.startswith("#") else "u.json").camera == camera
    assert camera.to_dict()["focal_length_tolerance"] == 0.02
    plain = parse_telemetry(telemetry_with_camera(focal_length_tolerance=None)).camera  # null: absent
    assert plain.focal_length_tolerance is None and plain.focal_tolerance == DEFAULT_FOCAL_LENGTH_TOLERANCE
    assert set(plain.to_dict()) == {"width", "height", "focal_length_px", "cx", "cy"}
    assert CAMERAS["tubsat-752x582-20deg"].focal_tolerance == 0.05


@pytest.mark.parametrize("fields, location, message", [
    ({"focal_length_tolerance": 0.5}, "camera.focal_length_tolerance", "must be between 0 and 0.2, got 0.5"),
    ({"focal_length_tolerance": -0.01}, "camera.focal_length_tolerance", "must be between 0 and 0.2"),
    ({"k1_bound": 2}, "camera.k1_bound", "must be between 0 and 1, got 2"),
    ({"k2_bound": "0.1"}, "camera.k2_bound", "must be a number"),
])
def test_camera_uncertainty_errors_are_located(fields, location, message):
    with pytest.raises(TelemetryError) as err:
        parse_telemetry(telemetry_with_camera(**fields))
    assert [(p.location, p.message) for p in err.value.problems if p.location == location]
    assert any(message in p.message for p in err.value.problems if p.location == location)


def test_with_optics_changes_only_the_optics():
    camera = Camera(752, 582, 2000.0, 375.5, 290.5, name="x", mag_limit=5.0, focal_length_tolerance=0.01)
    moved = camera.with_optics(focal_length_px=2010.0, k1=0.1)
    assert moved.optics() == {"focal_length_px": 2010.0, "cx": 375.5, "cy": 290.5, "k1": 0.1, "k2": 0.0}
    assert (moved.name, moved.mag_limit, moved.focal_length_tolerance) == ("x", 5.0, 0.01)
    assert camera.with_optics() == camera


# --- the model -------------------------------------------------------------------

def test_projection_is_the_camera_model_and_jacobians_match_finite_differences():
    camera = TRUE.with_optics(k2=0.4, cx=380.2, cy=285.9)
    rng = np.random.default_rng(3)
    v = np.column_stack([rng.uniform(-0.2, 0.2, 30), rng.uniform(-0.15, 0.15, 30), np.ones(30)])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    names = ("focal_length_px", "k1", "k2", "cx", "cy")
    xy, j_theta, j_cam = project_with_jacobians(v, camera, names)
    expected, _ = camera.vectors_to_pixels(v)
    np.testing.assert_allclose(xy, expected, atol=1e-9)
    for k in range(3):  # a left rotation exp([theta]x) about camera axis k
        h = 1e-7
        theta = np.zeros(3)
        theta[k] = h
        moved, _ = camera.vectors_to_pixels(v @ Rotation.from_rotvec(theta).as_matrix().T)
        np.testing.assert_allclose((moved - xy) / h, j_theta[:, :, k], rtol=1e-5, atol=1e-3)
    for k, name in enumerate(names):
        h = 1e-6 * max(1.0, abs(camera.optics()[name]))
        moved, _ = camera.with_optics(**{name: camera.optics()[name] + h}).vectors_to_pixels(v)
        np.testing.assert_allclose((moved - xy) / h, j_cam[:, :, k], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("corner_fraction", [0.01, 0.2, -0.1])
def test_pixels_to_vectors_inverts_the_projection_to_rounding(corner_fraction):
    """Undistortion is the projection's exact inverse, also for strong barrel or pincushion distortion
    (a lens moving its corner by 20 %): every pixel of the sensor, its corners and the principal point."""
    half_diagonal = math.hypot(DECLARED.width / 2, DECLARED.height / 2)
    camera = DECLARED.with_optics(k1=corner_fraction / (half_diagonal / DECLARED.focal_length_px) ** 2)
    xy = np.vstack([np.random.default_rng(14).uniform([-0.5, -0.5], [751.5, 581.5], (2000, 2)),
                    [[-0.5, -0.5], [751.5, 581.5], [DECLARED.cx, DECLARED.cy]]])
    back, front = camera.vectors_to_pixels(camera.pixels_to_vectors(xy))
    assert front.all()
    assert np.abs(back - xy).max() < 1e-10


@pytest.mark.parametrize("k1, k2", [(-0.2, 0.0), (0.0, -1.0), (0.1, -0.5), (-0.4, 0.05), (0.2, 0.0), (0.0, 0.3)])
def test_the_fold_radius_is_where_the_radial_map_first_stops_increasing(k1, k2):
    """The closed form (the smallest positive root of ``1 + 3 k1 u + 5 k2 u^2``, ``u = r^2``) against a
    brute-force scan of the radial map ``r (1 + k1 r^2 + k2 r^4)`` on a fine grid."""
    camera = DECLARED.with_optics(k1=k1, k2=k2)
    r = np.linspace(0.0, 10.0, 2_000_001)
    mapped = r * (1 + k1 * r * r + k2 * r ** 4)
    falling = np.flatnonzero(np.diff(mapped) <= 0)
    expected = r[falling[0]] if len(falling) else math.inf
    assert camera.fold_radius == pytest.approx(expected, abs=1e-5)


def test_a_direction_beyond_the_fold_is_not_imaged_where_the_model_would_fold_it_onto_the_sensor():
    """Barrel distortion of 1 % at the corner of the 20 deg camera (k1 = -0.2) folds the image over at a
    normalised radius of 1/sqrt(0.6) (52 deg off axis): a star 65 deg off axis (r = 2.2) would land
    0.07 f = 150 px from the centre, on the sensor, by the polynomial; it is not imaged.  A star inside the
    fold still projects and comes back."""
    camera = DECLARED.with_optics(k1=-0.2)
    far = np.array([[2.2, 0.0, 1.0]]) / math.hypot(2.2, 1.0)
    folded = camera.cx + camera.focal_length_px * 2.2 * (1 - 0.2 * 2.2 ** 2)
    assert -0.5 < folded < DECLARED.width - 0.5  # the polynomial puts it on the sensor ...
    xy, imaged = camera.vectors_to_pixels(far)
    assert not imaged[0] and np.isnan(xy).all()  # ... the camera does not
    near = np.array([[0.15, -0.1, 1.0]]) / math.hypot(0.15, 0.1, 1.0)
    xy, imaged = camera.vectors_to_pixels(near)
    assert imaged[0]
    np.testing.assert_allclose(camera.pixels_to_vectors(xy), near, atol=1e-12)


def test_parameter_choice_by_star_count_and_names():
    assert parameters_for(2) == ()
    assert parameters_for(3) == parameters_for(5) == ("focal_length_px",)
    assert parameters_for(6) == parameters_for(40) == ("focal_length_px", "k1")
    assert parameter_names(["cy", "f", "k1"]) == ("focal_length_px", "k1", "cy")
    with pytest.raises(ValueError, match="unknown camera parameter 'k3'"):
        parameter_names(["f", "k3"])


def test_default_priors_come_from_the_declaration():
    priors = default_priors(DECLARED, ("f", "k1", "cx"))
    assert priors == {"focal_length_px": (DECLARED.focal_length_px,
                                          DEFAULT_FOCAL_LENGTH_TOLERANCE * DECLARED.focal_length_px)}
    bounded = Camera(752, 582, 2000.0, 375.5, 290.5, focal_length_tolerance=0.01, k1_bound=0.3)
    assert default_priors(bounded, ("f", "k1")) == {"focal_length_px": (2000.0, 20.0), "k1": (0.0, 0.3)}


# --- one snapshot ------------------------------------------------------------------

def test_single_snapshot_fit_recovers_focal_length_and_k1_within_a_few_sigma(sky):
    rng = np.random.default_rng(11)
    pulls, angle_pulls = [], []
    for _ in range(30):
        got = None
        while got is None:
            R = random_rotation(rng)
            got = snapshot_stars(rng, sky, TRUE, R, 10)
            got = got if got is not None and len(got[0]) == 10 else None
        xy, vectors, _ = got
        R0 = wahba(DECLARED, xy, vectors)
        fit = fit_attitude_and_camera(xy, vectors, R0, DECLARED, SIGMA_PX)
        assert fit.parameters == ("focal_length_px", "k1")
        assert fit.covariance.shape == (5, 5) and fit.covariance_names[:3] == ("rot_x", "rot_y", "rot_z")
        for name in fit.parameters:
            pulls.append((fit.camera.optics()[name] - TRUE.optics()[name]) / fit.sigma[name])
        # The attitude: the rotation between fit and truth, in units of its sigma.
        residual = Rotation.from_matrix(R @ fit.rotation.T).as_rotvec()
        angle_pulls.extend(residual / fit.rotation_sigma_rad)
        assert 0.2 < fit.rms_px < 0.8
    pulls, angle_pulls = np.array(pulls), np.array(angle_pulls)
    # The declared focal length is 3 % (64 px) off; the fit lands within a few sigma (~2.3 px).
    assert np.max(np.abs(pulls)) < 4.5
    assert 0.6 < np.sqrt(np.mean(pulls ** 2)) < 1.5
    assert 0.6 < np.sqrt(np.mean(angle_pulls ** 2)) < 1.5


def test_single_snapshot_fit_without_distortion_term_sees_the_focal_error(sky):
    """Fitting f only: the 3 % error is found (to within the distortion's bias, ~0.5 %)."""
    rng = np.random.default_rng(12)
    R = random_rotation(rng)
    got = snapshot_stars(rng, sky, TRUE, R, 10)
    while got is None or len(got[0]) < 5:
        R = random_rotation(rng)
        got = snapshot_stars(rng, sky, TRUE, R, 10)
    xy, vectors, _ = got
    fit = fit_attitude_and_camera(xy, vectors, wahba(DECLARED, xy, vectors), DECLARED, SIGMA_PX, fit=("f",))
    assert abs(fit.camera.focal_length_px / TRUE.focal_length_px - 1) < 0.006
    assert fit.to_dict().keys() == {"focal_length_px", "sigma", "rms_px"}


def test_the_compiled_one_snapshot_fit_is_the_numpy_fit_with_the_attitude_eliminated(sky):
    """Two routes to one snapshot's fit: the compiled Gauss-Newton over its (3 + p) system
    (:func:`app.camera_fit._fit_one_kernel`, every candidate's optics fit) and the numpy Gauss-Newton with the
    attitude eliminated by the Schur complement (a calibration's, module docstring), on the same stars: the
    same optics, attitude and covariance to rounding, for every set of fitted parameters."""
    from app.camera_fit import _gauss_newton, _stars_from

    rng = np.random.default_rng(13)
    cases = 0
    for names in [("focal_length_px",), ("focal_length_px", "k1"), ("focal_length_px", "k1", "cx", "cy")]:
        for _ in range(6):
            got = None
            while got is None or len(got[0]) < 8:
                got = snapshot_stars(rng, sky, TRUE, random_rotation(rng), 10)
            xy, vectors, _ = got
            R0 = wahba(DECLARED, xy, vectors)
            priors = default_priors(DECLARED, names)
            fit = fit_attitude_and_camera(xy, vectors, R0, DECLARED, SIGMA_PX, fit=names, priors=priors)
            stars, rotations, _ = _stars_from([Observation(xy, vectors, R0, SIGMA_PX)])
            reference = _gauss_newton(stars, rotations, DECLARED, names, np.ones(len(xy)), np.ones(1, bool), priors)
            assert abs(fit.camera.focal_length_px - DECLARED.focal_length_px) > 1.0  # 3 % off: a real fit
            for name in names:
                assert fit.camera.optics()[name] == pytest.approx(reference.camera.optics()[name], rel=1e-9, abs=1e-12)
            np.testing.assert_allclose(fit.rotation, reference.rotations[0], atol=1e-12)
            np.testing.assert_allclose(fit.covariance[3:, 3:], reference.camera_covariance, rtol=1e-6)
            assert fit.chi2 == pytest.approx(reference.chi2, rel=1e-9)
            cases += 1
    assert cases == 18


def test_a_strong_prior_holds_and_too_few_stars_are_refused(sky):
    rng = np.random.default_rng(13)
    got = None
    while got is None:
        got = snapshot_stars(rng, sky, TRUE, random_rotation(rng), 6)
    xy, vectors, _ = got
    R0 = wahba(DECLARED, xy, vectors)
    held = fit_attitude_and_camera(xy, vectors, R0, DECLARED, SIGMA_PX, fit=("f",),
                                   priors={"f": (DECLARED.focal_length_px, 1e-6)})
    assert abs(held.camera.focal_length_px - DECLARED.focal_length_px) < 1e-3
    free = fit_attitude_and_camera(xy, vectors, R0, DECLARED, SIGMA_PX, fit=("f",), priors={})
    assert abs(free.camera.focal_length_px - DECLARED.focal_length_px) > 30  # it moves towards the truth
    with pytest.raises(ValueError, match="cannot fix"):
        fit_attitude_and_camera(xy[:2], vectors[:2], R0, DECLARED, SIGMA_PX, fit=("f", "k1", "cx"), priors={})


# --- calibration ---------------------------------------------------------------------

def test_calibration_from_50_sequences_recovers_the_optics(sky):
    camera = true_camera(cx_offset=4.0, cy_offset=-3.0)
    observations, _ = simulated_observations(21, sky, 50, camera)
    cal = calibrate(observations, DECLARED, parameters=("f", "cx", "cy", "k1", "k2"))
    fitted = cal.camera.optics()
    assert abs(fitted["focal_length_px"] / camera.focal_length_px - 1) < 0.0005
    assert abs(fitted["k1"] / camera.k1 - 1) < 0.10
    assert abs(fitted["cx"] - camera.cx) < 2.0 and abs(fitted["cy"] - camera.cy) < 2.0
    for name in cal.parameters:  # and each within 4 of its own sigmas
        assert abs(fitted[name] - camera.optics()[name]) < 4 * cal.sigma[name], name
    assert cal.sequences_used == 50 and cal.observations_used == len(observations)
    assert cal.rms_px_before > 5.0 and 0.35 < cal.rms_px_after < 0.7  # 0.3 px noise + rounding
    # Integer rounding adds variance 1/12 px^2: chi2 per degree of freedom ~ (0.09 + 0.083) / 0.09.
    assert 1.7 < cal.chi2_reduced < 2.2
    assert cal.camera.width == DECLARED.width and cal.camera.name == DECLARED.name
    doc = cal.to_dict()
    assert doc["camera"]["focal_length_px"] == fitted["focal_length_px"]
    assert set(doc["sigma"]) == {"focal_length_px", "k1", "k2", "cx", "cy"}


def test_calibration_sigmas_are_honest_over_seeded_trials(sky):
    """RMS of (error / sigma) over 20 independent calibrations, per parameter, near 1.

    The observations understate their noise (0.2 px for 0.3 px plus integer
    rounding, ~0.42 px): the reduced chi-square (~4) must scale the sigmas,
    which would otherwise be half what they should.
    """
    pulls = {name: [] for name in ("focal_length_px", "k1", "cx", "cy")}
    for trial in range(20):
        observations, _ = simulated_observations(100 + trial, sky, 6, stated_sigma_px=0.2)
        cal = calibrate(observations, DECLARED, parameters=("f", "k1", "cx", "cy"))
        assert 3.6 < cal.chi2_reduced < 5.0
        for name in pulls:
            pulls[name].append((cal.camera.optics()[name] - TRUE.optics()[name]) / cal.sigma[name])
    for name, values in pulls.items():
        rms = float(np.sqrt(np.mean(np.square(values))))
        assert 0.6 <= rms <= 1.5, (name, rms)


def test_outliers_are_rejected(sky):
    rng = np.random.default_rng(5)
    observations, _ = simulated_observations(31, sky, 20, rounding=False)
    # Spoil ~3 % of the stars: wrong matches 15-60 px away, as a misidentified neighbour would be.
    spoiled = []
    for j, obs in enumerate(observations):
        if rng.random() < 0.25:
            k = int(rng.integers(len(obs.xy)))
            xy = obs.xy.copy()
            xy[k] += rng.uniform(15, 60) * np.array([math.cos(a := rng.uniform(0, 2 * np.pi)), math.sin(a)])
            observations[j] = Observation(xy, obs.star_vectors, obs.rotation, obs.sigma_px, obs.sequence)
            spoiled.append((j, k))
    cal = calibrate(observations, DECLARED, parameters=("f", "k1"))
    for j, k in spoiled:
        assert not cal.inliers[j][k]
    assert cal.stars_rejected <= len(spoiled) + 3  # hardly any good star lost
    assert abs(cal.camera.focal_length_px / TRUE.focal_length_px - 1) < 0.0005
    assert abs(cal.camera.k1 / TRUE.k1 - 1) < 0.10
    assert 0.9 < cal.chi2_reduced < 1.15  # Gaussian noise only, once the outliers are out
    naive = calibrate(observations, DECLARED, parameters=("f", "k1"), reject_sigma=None)
    assert naive.stars_rejected == 0 and naive.rms_px_after > 2 * cal.rms_px_after


def test_robust_scale_of_rayleigh_lengths():
    rng = np.random.default_rng(0)
    lengths = np.linalg.norm(rng.normal(0, 2.0, (20000, 2)), axis=1)
    lengths[:2000] += 100.0  # 10 % outliers move it little
    assert 1.9 < robust_scale(lengths) < 2.4


def test_calibration_refuses_bad_input():
    with pytest.raises(ValueError, match="no observations"):
        calibrate([], DECLARED)
    xy = np.zeros((2, 2))
    with pytest.raises(ValueError, match="3 or more stars"):
        calibrate([(xy, np.array([[0, 0, 1.0], [0.01, 0, 1]]), np.eye(3), 0.3)], DECLARED)
    with pytest.raises(ValueError, match="2 pixel positions but 1 star vectors"):
        calibrate([(xy, np.array([[0, 0, 1.0]]), np.eye(3), 0.3)], DECLARED)
    with pytest.raises(ValueError, match="sigma_px"):
        calibrate([(xy, np.array([[0, 0, 1.0], [0.01, 0, 1]]), np.eye(3), 0.0)], DECLARED)
