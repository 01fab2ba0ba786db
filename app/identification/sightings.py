"""The sightings of a candidate's identified stars, snapshot by snapshot: what the sequence fit and the
camera calibration are made from.

A candidate matches pattern points, i.e. tracks, to catalogue stars; every
track was seen in several snapshots.  Here each snapshot's sightings of
those tracks are gathered with their stars' apparent places, as raw pixels:
no camera model is involved yet, so the same sightings serve a fit through
the declared camera, through optics fitted with the attitude, or a fit of
the optics themselves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.attitude import propagate
from app.camera_fit import Observation
from app.extraction import DEFAULT_SIGHTING_SIGMA_PX
from app.identification.options import SearchOptions
from app.identification.verify import StarField, brightest_within

#: A snapshot needs this many identified sightings to fix its own attitude robustly.
MIN_SIGHTINGS = 3
#: A reported source is that star when it lies within max(this, 5 sigma) pixels of it.
SOURCE_MATCH_PX = 2.0


@dataclass(frozen=True, eq=False)
class SnapshotSightings:
    position: int  # of the snapshot in the sequence
    dt_s: float  # since the reference snapshot
    xy: np.ndarray  # (n, 2) pixels where the identified tracks were seen
    star_vectors: np.ndarray  # (n, 3) apparent places of their stars at the reference time, ICRS


def identified_sightings(sequence, extraction, star_of_track: dict[int, int], sky) -> list[SnapshotSightings]:
    """The snapshots with at least :data:`MIN_SIGHTINGS` sightings of tracks in ``star_of_track`` (track -> HIP)."""
    if not star_of_track:
        return []
    t_ref = sequence.snapshots[extraction.reference].time
    hips = sorted(set(star_of_track.values()))
    star_vector = dict(zip(hips, sky.apparent_vectors_of(hips, t_ref, sequence.observer)))
    by_snapshot: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for track in extraction.tracks:
        if track.id in star_of_track:
            star = star_vector[star_of_track[track.id]]
            for position, xy in zip(track.snapshots.tolist(), track.xy):
                by_snapshot.setdefault(position, []).append((xy, star))
    return [SnapshotSightings(position=position,
                              dt_s=(sequence.snapshots[position].time - t_ref).total_seconds(),
                              xy=np.array([s[0] for s in found], dtype=float),
                              star_vectors=np.array([s[1] for s in found], dtype=float))
            for position, found in sorted(by_snapshot.items()) if len(found) >= MIN_SIGHTINGS]


def sighting_noise_px(extraction) -> float:
    """Extraction's estimate of one sighting's 1-sigma noise (the default where it could not measure it)."""
    return extraction.noise_px if math.isfinite(extraction.noise_px) else DEFAULT_SIGHTING_SIGMA_PX


def source_match_tolerance_rad(camera, extraction) -> float:
    """How far (angle) a reported source may lie from a star to be that star: max(:data:`SOURCE_MATCH_PX`,
    5 sigma of one sighting) pixels."""
    return max(SOURCE_MATCH_PX, 5 * sighting_noise_px(extraction)) * camera.pixel_scale_rad


def sources_field(sky, sequence, t_ref, camera, mag_margin: float = SearchOptions().mag_margin) -> StarField:
    """The stars a reported source of ``sequence`` may be: those down to ``camera``'s limiting magnitude
    plus the search's margin, at their apparent places at ``t_ref`` (the reference snapshot's time)."""
    return sky.field(t_ref, sky.depth_for(camera, mag_margin),
                     sequence.observer)


def stars_at(xy: np.ndarray, camera, rotation: np.ndarray, field: StarField, tolerance_rad: float) -> np.ndarray:
    """(n,) position in ``field`` of the star each pixel sees within ``tolerance_rad``, else -1.

    The pixels go through ``camera`` into the camera frame and through
    ``rotation`` (ICRS to camera: (3, 3), or (n, 3, 3) one per pixel, e.g.
    the attitudes of the snapshots they were seen in) back to the sky.  A
    pixel sees the brightest star within the tolerance, not the nearest: a
    fainter star beside a bright one is seldom seen at all, and where both
    are, their blend is named by its brighter member.  Two pixels may name
    the same star (:func:`claimed_once` tells).
    """
    if len(xy) == 0:
        return np.zeros(0, dtype=int)
    body = camera.pixels_to_vectors(np.asarray(xy, dtype=float))
    rotation = np.asarray(rotation, dtype=float)
    directions = body @ rotation if rotation.ndim == 2 else np.einsum("ni,nij->nj", body, rotation)  # R^T v
    return brightest_within(directions, field, tolerance_rad)


def claimed_once(stars: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
    """(n,) True where ``stars`` (from :func:`stars_at`) names a star that no other entry names (of the
    same group, when ``groups`` (n,) non-negative ints are given: e.g. the snapshot each entry is from)."""
    named = stars >= 0
    if not np.any(named):
        return named
    key = stars if groups is None else np.asarray(groups) * (int(stars.max()) + 1) + stars
    counts = np.bincount(key[named])
    return named & (counts[np.where(named, key, 0)] == 1)


def observations(sightings: list[SnapshotSightings], extraction, rotation_ref: np.ndarray,
                 rate_rad_s: np.ndarray | None, label: str | None = None) -> list[Observation]:
    """The sightings as :class:`app.camera_fit.Observation` (one per snapshot) with starting attitudes.

    A snapshot's starting attitude is the reference attitude propagated at
    ``rate_rad_s`` when given, else carried by extraction's motion
    (``R_i = M_i^T R_ref``); snapshots with neither are left out.
    """
    noise = sighting_noise_px(extraction)
    out = []
    for s in sightings:
        if rate_rad_s is not None:
            rotation = propagate(rotation_ref, rate_rad_s, s.dt_s)
        elif np.all(np.isfinite(extraction.motion[s.position])):
            rotation = extraction.motion[s.position].T @ rotation_ref
        else:
            continue
        out.append(Observation(xy=s.xy, star_vectors=s.star_vectors, rotation=rotation, sigma_px=noise,
                               sequence=label, snapshot=s.position))
    return out
