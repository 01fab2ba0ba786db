"""Rotation conventions and Wahba's problem against hand-checked geometry."""

from __future__ import annotations

import numpy as np
import pytest

from app.attitude import (angle_between, boresight_and_roll_error, quaternion_from_rotation,
                          radec_roll_from_rotation, rotation_from_pair, rotation_from_quaternion,
                          rotation_from_radec_roll, solve_wahba)
from app.camera import CAMERAS
from app.catalogue import radec_to_vectors


def test_boresight_maps_to_plus_z_and_north_is_up_east_left_at_roll_zero():
    R = rotation_from_radec_roll(100.0, 20.0, 0.0)
    bore, north, east = radec_to_vectors(np.radians([100.0, 100.0, 101.0]), np.radians([20.0, 21.0, 20.0]))
    assert np.allclose(R @ bore, [0, 0, 1], atol=1e-12)
    cam = CAMERAS["tubsat-752x582-20deg"]
    (centre, up, left), _ = cam.vectors_to_pixels(np.array([R @ bore, R @ north, R @ east]))
    assert up[1] < centre[1] - 30 and abs(up[0] - centre[0]) < 1  # north: smaller row, same column
    assert left[0] < centre[0] - 30  # east: smaller column


def test_roll_is_position_angle_of_image_up_from_north_through_east():
    R = rotation_from_radec_roll(100.0, 20.0, 90.0)  # image up points east
    east = radec_to_vectors(np.radians([101.0]), np.radians([20.0]))[0]
    assert (R @ east)[1] < -0.01  # east lies towards smaller rows


@pytest.mark.parametrize("radec_roll", [(0.0, 0.0, 0.0), (165.9, 61.7, 12.3), (359.5, -89.0, 300.0),
                                        (42.0, 45.0, 180.0)])
def test_radec_roll_round_trip(radec_roll):
    R = rotation_from_radec_roll(*radec_roll)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(radec_roll_from_rotation(R), radec_roll, atol=1e-9)


def test_quaternion_is_scalar_last_with_non_negative_scalar():
    # A rotation of +90 deg about z: q = (0, 0, sin 45, cos 45).
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    q = quaternion_from_rotation(Rz)
    assert np.allclose(q, [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    assert np.allclose(rotation_from_quaternion(q), Rz)


def test_wahba_recovers_a_rotation_from_noisy_vectors():
    rng = np.random.default_rng(3)
    R = rotation_from_radec_roll(10.0, -30.0, 77.0)
    ref = rng.normal(size=(20, 3))
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    body = ref @ R.T + rng.normal(scale=1e-5, size=(20, 3))
    body /= np.linalg.norm(body, axis=1, keepdims=True)
    est = solve_wahba(body, ref)
    assert np.degrees(np.arccos((np.trace(est @ R.T) - 1) / 2)) * 3600 < 5.0


def test_pair_rotation_maps_first_point_exactly_and_second_onto_its_great_circle():
    R = rotation_from_radec_roll(200.0, 10.0, 33.0)
    r1, r2 = radec_to_vectors(np.radians([200.0, 201.5]), np.radians([10.0, 11.0]))
    b1, b2 = R @ r1, R @ r2
    est = rotation_from_pair(b1, b2, r1, r2)
    assert np.allclose(est, R, atol=1e-12)
    # Tiny separations stay accurate (the seed's numerically stable construction).
    r2_close = radec_to_vectors(np.radians([200.0 + 1e-6]), np.radians([10.0]))[0]
    est = rotation_from_pair(R @ r1, R @ r2_close, r1, r2_close)
    assert np.allclose(est, R, atol=1e-6)


def test_boresight_and_roll_error_separate_the_two():
    R = rotation_from_radec_roll(50.0, 20.0, 10.0)
    R_roll = rotation_from_radec_roll(50.0, 20.0, 10.5)
    bore, roll = boresight_and_roll_error(R_roll, R)
    assert bore < 1e-12 and np.isclose(np.degrees(roll), 0.5)
    R_moved = rotation_from_radec_roll(50.0, 20.1, 10.0)
    bore, _ = boresight_and_roll_error(R_moved, R)
    assert np.isclose(np.degrees(bore), 0.1, atol=1e-6)
    assert np.isclose(float(angle_between(R[2], R_moved[2])), bore)


def test_wahba_with_two_vectors_is_a_proper_rotation_in_stacks():
    """Two vectors make B rank 2: the sign of det B is rounding noise and must not pick a reflection."""
    rng = np.random.default_rng(5)
    truth = np.stack([rotation_from_radec_roll(*r) for r in zip(rng.uniform(0, 360, 200),
                                                                 rng.uniform(-89, 89, 200),
                                                                 rng.uniform(0, 360, 200))])
    ref = rng.normal(size=(200, 2, 3))
    ref /= np.linalg.norm(ref, axis=2, keepdims=True)
    body = np.einsum("sij,snj->sni", truth, ref)
    R = solve_wahba(body, ref, np.ones((200, 2)))
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(R, truth, atol=1e-9)
    assert np.allclose(solve_wahba(body[7], ref[7]), truth[7], atol=1e-9)


def test_left_jacobian_matches_finite_differences():
    from scipy.spatial.transform import Rotation

    from app.attitude.sequence import left_jacobian

    rng = np.random.default_rng(2)
    phi = np.vstack([rng.normal(size=(5, 3)) * 0.3, [[1e-8, 0, 0]]])
    J = np.stack([left_jacobian(*p) for p in phi])
    h = 1e-7
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        # exp(phi + d) exp(phi)^T ~ exp([J_l d]x): its rotation vector / h is column k of J_l.
        moved = Rotation.from_rotvec(phi + step) * Rotation.from_rotvec(phi).inv()
        assert np.allclose(moved.as_rotvec() / h, J[:, :, k], atol=1e-6)


@pytest.mark.parametrize("kind", ["random", "rank 2", "rank 1", "zero", "narrow field"])
def test_the_jacobi_svd_is_an_svd_and_lapacks_where_that_is_well_defined(kind):
    """U S V^T = B with U, V orthonormal and S descending (LAPACK's singular values), also for the
    rank-deficient matrices Wahba's problem meets (two stars; one); and Wahba's rotation from it."""
    from scipy.spatial.transform import Rotation

    from app.attitude.rotations import svd_3x3

    rng = np.random.default_rng(len(kind))
    for _ in range(200):
        if kind == "random":
            B = rng.normal(size=(3, 3))
        elif kind == "rank 2":
            B = np.outer(rng.normal(size=3), rng.normal(size=3)) + np.outer(rng.normal(size=3), rng.normal(size=3))
        elif kind == "rank 1":
            B = np.outer(rng.normal(size=3), rng.normal(size=3))
        elif kind == "zero":
            B = np.zeros((3, 3))
        else:  # a profile matrix of stars 0.5 deg apart, seen through a random rotation
            ref = np.column_stack([rng.normal(scale=0.01, size=(6, 2)), np.ones(6)])
            ref /= np.linalg.norm(ref, axis=1, keepdims=True)
            truth = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
            B = (ref @ truth.T).T @ ref
        U, S, Vt = svd_3x3(B)
        assert np.allclose(U @ U.T, np.eye(3), atol=1e-14) and np.allclose(Vt @ Vt.T, np.eye(3), atol=1e-14)
        assert np.all(np.diff(S) <= 0) and np.allclose(S, np.linalg.svd(B)[1], atol=1e-13)
        assert np.allclose(U @ np.diag(S) @ Vt, B, atol=1e-13)
        if kind == "narrow field":
            R = U @ np.diag([1, 1, np.linalg.det(U) * np.linalg.det(Vt)]) @ Vt
            assert np.allclose(R, truth, atol=1e-11)
