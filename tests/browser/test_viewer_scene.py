"""The 3D view's geometry and the shared view state, without a browser (fast, exact checks)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.camera import Camera
from app.viewer import scene as geo
from app.workflow.documents import PatternDefinition
from app.workflow.view_state import ViewStateStore


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def matrix_of_wxyz(q) -> np.ndarray:
    """Active rotation matrix of a scalar-first unit quaternion (textbook formula)."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_quaternion_round_trips_random_rotations():
    rng = np.random.default_rng(5)
    for _ in range(200):
        rotation = random_rotation(rng)
        q = geo.rotation_to_wxyz(rotation)
        assert q[0] >= 0 and math.isclose(np.linalg.norm(q), 1.0, rel_tol=1e-12)
        assert np.allclose(matrix_of_wxyz(q), rotation, atol=1e-12)


def test_frustum_axis_and_pixel_rays_agree_with_the_camera_model():
    camera = Camera(width=752, height=582, focal_length_px=2132.4, cx=375.5, cy=290.5)
    rotation = random_rotation(np.random.default_rng(7))
    pose = geo.frustum_pose(rotation, camera)
    # The frustum's local +z (boresight) lands on the ICRS direction R^T z = third row of R.
    assert np.allclose(matrix_of_wxyz(pose.wxyz) @ [0, 0, 1], rotation[2], atol=1e-12)
    assert math.isclose(pose.fov_rad, math.radians(camera.fov_deg[1]), rel_tol=1e-12)
    assert math.isclose(pose.aspect, 752 / 582)
    # A ray through a pixel, seen back through the camera, hits that pixel again.
    xy = np.array([[10.0, 20.0], [700.5, 560.25], [375.5, 290.5]])
    directions = geo.pixel_directions(rotation, camera, xy)
    back, front = camera.vectors_to_pixels(directions @ rotation.T)
    assert front.all() and np.allclose(back, xy, atol=1e-9)
    segments = geo.ray_segments(directions)
    assert np.allclose(segments[:, 0], 0) and np.allclose(np.linalg.norm(segments[:, 1], axis=1), geo.SPHERE_RADIUS)


def test_magnitude_classes_partition_the_stars_shown():
    mag = np.array([-1.4, 0.9, 1.0, 1.5, 2.7, 3.3, 4.9, 5.2, 6.4, 6.9])
    classes = geo.magnitude_classes(mag, 6.5)
    together = np.sort(np.concatenate(classes))
    assert together.tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 8]  # 6.9 is fainter than the limit
    assert classes[0].tolist() == [0, 1, 2] and classes[1].tolist() == [3]


def test_constellation_anchors_need_enough_bright_stars():
    vectors = np.array([[1, 0, 0], [0.99, 0.1, 0], [0.99, -0.1, 0], [0, 0, 1], [0, 0.1, 0.99]], dtype=float)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    anchors = geo.constellation_anchors(vectors, np.array([1, 2, 3, 1, 2]), ["Ori", "Ori", "Ori", "UMa", "UMa"])
    assert [name for name, _ in anchors] == ["Ori"]
    assert np.allclose(anchors[0][1], [1, 0, 0], atol=1e-12)


def test_toggle_track_both_ways_and_with_an_explicit_list():
    automatic = PatternDefinition.model_validate(
        {"exclude_tracks": [], "include_tracks": None, "manual_points": [{"snapshot": 1, "x": 2, "y": 3}]})
    out = geo.toggle_track(automatic, 4)
    assert out.exclude_tracks == [4] and out.include_tracks is None and out.manual_points == automatic.manual_points
    assert geo.toggle_track(out, 4).exclude_tracks == []
    chosen = PatternDefinition(exclude_tracks=[4], include_tracks=[1, 2])
    assert geo.toggle_track(chosen, 2).include_tracks == [1]
    back = geo.toggle_track(chosen, 4)
    assert back.include_tracks == [1, 2, 4] and back.exclude_tracks == []
    assert geo.remove_manual_point(automatic, 0).manual_points == []
    with pytest.raises(ValueError):
        geo.remove_manual_point(automatic, 1)


def test_view_state_changes_only_what_is_given_and_counts_writes():
    store = ViewStateStore()
    first = store.update(sequence=3, rank=2, updated_by="console")
    second = store.update(mag=4.5, updated_by="viewer")
    assert (second.sequence, second.rank, second.mag) == (3, 2, 4.5)
    assert second.revision == first.revision + 1 and second.updated_by == "viewer"
    assert store.update(rank=None).rank is None
    for bad in ({"rank": 0}, {"sequence": True}, {"mag": float("nan")}, {"mag": 9}):
        with pytest.raises(ValueError):
            store.update(**bad)
    assert store.get().revision == second.revision + 1  # refused writes change nothing
