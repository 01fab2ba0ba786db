"""Geometry of the 3D view, as plain numpy: no viser, no database.

The scene is the celestial sphere of radius :data:`SPHERE_RADIUS` around the
origin, in ICRS axes (world x = vernal equinox, z = north celestial pole).  A
direction ``v`` (unit ICRS vector) is drawn at ``SPHERE_RADIUS * v``.

A candidate's rotation ``R`` maps ICRS to the camera frame (``v_cam = R v``),
so the camera's axes in the world are the rows of ``R``, and the frustum's
orientation (viser frustums use the same +x right, +y down, +z forward frame
as our camera) is the local-to-world rotation ``R^T``.  A pattern point at
pixel ``(x, y)`` looks along ``R^T camera.pixels_to_vectors((x, y))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.camera import Camera
from app.workflow.documents import PatternDefinition

#: Radius of the celestial sphere in scene units.
SPHERE_RADIUS = 10.0
#: Upper edges of the magnitude classes drawn as separate point clouds (one size each),
#: with the point size of each class in scene units: brighter stars are bigger dots.
MAG_CLASS_EDGES = (1.0, 2.0, 3.0, 4.0, 5.0, 99.0)
MAG_CLASS_SIZES = (0.11, 0.085, 0.065, 0.048, 0.036, 0.026)
#: A constellation is labelled where it has at least this many stars of at most this magnitude.
LABEL_MIN_STARS = 3
LABEL_MAG_LIMIT = 4.5


def magnitude_classes(mag: np.ndarray, mag_limit: float) -> list[np.ndarray]:
    """Indices of the stars of each class of :data:`MAG_CLASS_EDGES`, dropping stars fainter than ``mag_limit``.

    Class k holds ``edge[k-1] < mag <= edge[k]`` (class 0: ``mag <= edge[0]``).
    """
    mag = np.asarray(mag, dtype=float)
    shown = mag <= mag_limit
    lower = -np.inf
    classes = []
    for upper in MAG_CLASS_EDGES:
        classes.append(np.flatnonzero(shown & (mag > lower) & (mag <= upper)))
        lower = upper
    return classes


def constellation_anchors(vectors: np.ndarray, mag: np.ndarray,
                          labels: list[str]) -> list[tuple[str, np.ndarray]]:
    """One label position per well-populated constellation: the mean direction of its bright stars.

    Only stars of magnitude <= :data:`LABEL_MAG_LIMIT` count, and only
    constellations with :data:`LABEL_MIN_STARS` of them get a label, so the
    sky carries a few dozen labels rather than one per star.  Returns
    ``[(abbreviation, unit vector)]`` sorted by abbreviation.
    """
    vectors = np.asarray(vectors, dtype=float)
    bright = np.asarray(mag, dtype=float) <= LABEL_MAG_LIMIT
    groups: dict[str, list[int]] = {}
    for i in np.flatnonzero(bright):
        groups.setdefault(labels[i], []).append(int(i))
    anchors = []
    for name, members in sorted(groups.items()):
        if len(members) < LABEL_MIN_STARS:
            continue
        mean = vectors[members].sum(axis=0)
        norm = np.linalg.norm(mean)
        if norm > 1e-9:  # stars spread over a great circle would cancel out: no sensible anchor
            anchors.append((name, mean / norm))
    return anchors


@dataclass(frozen=True)
class FrustumPose:
    """A camera frustum in the scene: orientation (w, x, y, z), vertical fov (rad), aspect (w/h)."""

    wxyz: np.ndarray
    fov_rad: float
    aspect: float


def rotation_to_wxyz(matrix: np.ndarray) -> np.ndarray:
    """Scalar-first unit quaternion of a proper rotation matrix (Shepperd's method, sign w >= 0)."""
    m = np.asarray(matrix, dtype=float)
    trace = np.trace(m)
    candidates = np.array([trace, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(candidates))
    if k == 0:
        s = math.sqrt(1.0 + trace) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def frustum_pose(rotation: np.ndarray, camera: Camera) -> FrustumPose:
    """The frustum of a candidate: local (camera) to world (ICRS) is ``R^T``."""
    rotation = np.asarray(rotation, dtype=float)
    fov_v = 2.0 * math.atan(camera.height / 2.0 / camera.focal_length_px)
    return FrustumPose(wxyz=rotation_to_wxyz(rotation.T), fov_rad=fov_v, aspect=camera.width / camera.height)


def pixel_directions(rotation: np.ndarray, camera: Camera, xy: np.ndarray) -> np.ndarray:
    """ICRS unit vectors ``R^T pixels_to_vectors(xy)`` of (N, 2) pixels seen under ``rotation``."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(xy) == 0:
        return np.zeros((0, 3))
    return camera.pixels_to_vectors(xy) @ np.asarray(rotation, dtype=float)


def ray_segments(directions: np.ndarray, radius: float = SPHERE_RADIUS) -> np.ndarray:
    """(N, 2, 3) line segments from the origin to ``radius * direction``."""
    directions = np.asarray(directions, dtype=float).reshape(-1, 3)
    segments = np.zeros((len(directions), 2, 3))
    segments[:, 1] = radius * directions
    return segments


def toggle_track(definition: PatternDefinition, track: int) -> PatternDefinition:
    """The pattern definition with ``track`` taken out if it is in, put back if it is out.

    With ``include_tracks`` null (every track) membership is ``exclude_tracks``;
    with an explicit list it is that list.
    """
    track = int(track)
    exclude = sorted(set(definition.exclude_tracks))
    include = definition.include_tracks
    if include is None:
        exclude = sorted(set(exclude) ^ {track})
    else:
        include = sorted(set(include) ^ {track})
        exclude = [t for t in exclude if t != track]
    return definition.model_copy(update={"exclude_tracks": exclude, "include_tracks": include})


def remove_manual_point(definition: PatternDefinition, index: int) -> PatternDefinition:
    """The pattern definition without its ``index``-th hand-picked point."""
    manual = list(definition.manual_points)
    if not 0 <= index < len(manual):
        raise ValueError(f"the pattern has no hand-picked point {index}")
    del manual[index]
    return definition.model_copy(update={"manual_points": manual})
