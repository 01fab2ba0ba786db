"""Patterns for identification: tracks carried into the reference frame and averaged.

A track's sightings are unit vectors in their own snapshots' camera frames;
``motion[i]`` carries snapshot i's frame into the reference snapshot's
(``v_ref = motion[i] v_i``).  The averaged point is the normalised sum of
the carried vectors (the mean direction, which for the sub-degree spreads
here equals the least-squares point on the sphere) projected through the
camera.  Its noise falls as sigma / sqrt(k) for k sightings.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence as SequenceOf

import numpy as np

from app.camera import Camera
from app.extraction.model import DEFAULT_SIGHTING_SIGMA_PX, Extraction, Pattern, Track
from app.telemetry.model import Sequence

#: A hand-picked point takes the brightness of a reported source this close (pixels).
MANUAL_BRIGHTNESS_RADIUS_PX = 3.0


class PatternError(ValueError):
    """An operator's pattern that cannot be built, and which entry is at fault.

    ``field`` is ``include_tracks`` or ``manual_points``; ``key`` the track id
    or the manual point's position in the list given, so that an interface
    can point at the entry the user sent.
    """

    def __init__(self, field: str, key: int, message: str) -> None:
        super().__init__(message)
        self.field = field
        self.key = key


def average_into_reference(camera: Camera, motion: np.ndarray, snapshot_of: np.ndarray,
                           vectors: np.ndarray, group: np.ndarray,
                           n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean direction of each group of sightings in the reference frame.

    ``vectors`` (K, 3) in their snapshots' frames, ``snapshot_of`` and
    ``group`` (K,) ints.  Returns ((m, 3) unit vectors, (m, 2) reference
    pixels; NaN for a direction behind the camera).
    """
    carried = np.einsum("kij,kj->ki", motion[snapshot_of], vectors)
    # per coordinate, as np.add.at would add them (in order) but without its overhead
    sums = np.column_stack([np.bincount(group, carried[:, k], n_groups) for k in range(3)]).reshape(n_groups, 3)
    # numpy's norm, the same numbers, without its reduction over an axis of three
    mean = sums / np.sqrt(sums[:, 0] * sums[:, 0] + sums[:, 1] * sums[:, 1] + sums[:, 2] * sums[:, 2])[:, None]
    xy, _ = camera.vectors_to_pixels(mean)
    return mean, xy


def tracks_pattern(camera: Camera, extraction_motion: np.ndarray, tracks: SequenceOf[Track],
                   noise_px: float) -> Pattern:
    """The averaged pattern of ``tracks`` (all must have finite motion)."""
    if not tracks:
        return Pattern.empty()
    snapshot_of = np.concatenate([t.snapshots for t in tracks])
    xy = np.concatenate([t.xy for t in tracks])
    sightings = np.array([t.n_sightings for t in tracks], dtype=int)
    group = np.repeat(np.arange(len(tracks)), sightings)
    vectors, ref_xy = average_into_reference(camera, extraction_motion, snapshot_of,
                                             camera.pixels_to_vectors(xy), group, len(tracks))
    return Pattern(track_ids=np.array([t.id for t in tracks], dtype=int), xy=ref_xy, vectors=vectors,
                   brightness=np.array([t.mean_brightness for t in tracks]), sightings=sightings,
                   sigma_px=noise_px / np.sqrt(sightings))


def seed_pattern(camera: Camera, reference: int, tracks: SequenceOf[Track], noise_px: float) -> Pattern:
    """The seed's pattern: the reference snapshot's tracked sources where they were seen."""
    rows = []
    for t in tracks:
        seen_in = t.snapshots.tolist()  # a track has one sighting per snapshot at most
        if reference in seen_in:
            rows.append((t, seen_in.index(reference)))
    if not rows:
        return Pattern.empty()
    xy = np.array([t.xy[k] for t, k in rows])
    n = len(rows)
    return Pattern(track_ids=np.array([t.id for t, _ in rows], dtype=int), xy=xy,
                   vectors=camera.pixels_to_vectors(xy),
                   brightness=np.array([t.mean_brightness for t, _ in rows]),
                   sightings=np.ones(n, dtype=int), sigma_px=np.full(n, noise_px))


def carried_tracks(tracks: SequenceOf[Track], motion: np.ndarray) -> list[Track]:
    """The tracks that can be carried into the reference frame: their first snapshot's motion is known.

    (Extraction knows the motion of every snapshot linked to the reference
    and of no other, so one sighting decides for the whole track.)
    """
    known = np.isfinite(motion).all(axis=(1, 2)).tolist()
    return [t for t in tracks if known[t.snapshots[0]]]


def describe_track_ids(ids) -> str:
    """"tracks are 0..15" (extraction numbers its tracks 0..T-1), or that there are none."""
    ids = sorted(ids)
    if not ids:
        return "this sequence has no tracks"
    if ids == list(range(ids[0], ids[-1] + 1)):
        return f"tracks are {ids[0]}..{ids[-1]}"
    return "tracks are " + ", ".join(map(str, ids))


def _motion_known(motion: np.ndarray, snapshots: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(motion[snapshots])))


def _select_tracks(extraction: Extraction, exclude_tracks: Iterable[int],
                   include_tracks: Iterable[int] | None) -> list[Track]:
    by_id = {t.id: t for t in extraction.tracks}
    exclude = {int(i) for i in exclude_tracks}
    if include_tracks is None:
        # all tracks that can be carried into the reference frame
        return [t for t in extraction.tracks if t.id not in exclude
                and _motion_known(extraction.motion, t.snapshots)]
    chosen = []
    for raw in include_tracks:
        track_id = int(raw)
        if track_id not in by_id:
            raise PatternError("include_tracks", track_id, f"track {track_id} does not exist ({describe_track_ids(by_id)})")
        track = by_id[track_id]
        if not _motion_known(extraction.motion, track.snapshots):
            raise PatternError("include_tracks", track_id,
                               f"track {track_id} cannot be carried into reference snapshot "
                               f"{extraction.reference}: the motion between them could not be estimated")
        if track_id not in exclude and track not in chosen:
            chosen.append(track)
    return sorted(chosen, key=lambda t: t.id)


def _manual_pattern(sequence: Sequence, extraction: Extraction, manual_points) -> Pattern:
    camera = sequence.camera
    n_snapshots = len(sequence.snapshots)
    rows = []
    for k, point in enumerate(manual_points):
        try:
            position, x, y = point
            position, x, y = int(position), float(x), float(y)
        except (TypeError, ValueError):
            raise PatternError("manual_points", k, f"manual point {k}: expected (snapshot position, x, y), "
                                                   f"got {point!r}") from None
        if not 0 <= position < n_snapshots:
            raise PatternError("manual_points", k, f"manual point {k}: snapshot position {position} is not in "
                                                   f"0..{n_snapshots - 1}")
        if not (math.isfinite(x) and math.isfinite(y)) or not camera.on_sensor(np.array([x, y]))[0]:
            raise PatternError("manual_points", k, f"manual point {k}: ({x}, {y}) is not a pixel of the "
                                                   f"{camera.width}x{camera.height} sensor")
        if not _motion_known(extraction.motion, np.array([position])):
            raise PatternError("manual_points", k, f"manual point {k}: the motion from snapshot {position} into "
                                                   f"reference snapshot {extraction.reference} could not be "
                                                   f"estimated; pick the point in a snapshot linked to the reference")
        rows.append((position, x, y))
    if not rows:
        return Pattern.empty()
    positions = np.array([r[0] for r in rows], dtype=int)
    xy = np.array([[r[1], r[2]] for r in rows])
    vectors, ref_xy = average_into_reference(camera, extraction.motion, positions,
                                             camera.pixels_to_vectors(xy), np.arange(len(rows)), len(rows))
    brightness = np.zeros(len(rows))
    for k, (position, x, y) in enumerate(rows):
        snapshot = sequence.snapshots[position]
        if snapshot.n_sources:
            d = np.hypot(snapshot.xy[:, 0] - x, snapshot.xy[:, 1] - y)
            if d.min() <= MANUAL_BRIGHTNESS_RADIUS_PX:
                brightness[k] = float(snapshot.brightness[np.argmin(d)])
    noise = extraction.noise_px if math.isfinite(extraction.noise_px) else DEFAULT_SIGHTING_SIGMA_PX
    return Pattern(track_ids=np.full(len(rows), -1, dtype=int), xy=ref_xy, vectors=vectors,
                   brightness=brightness, sightings=np.ones(len(rows), dtype=int),
                   sigma_px=np.full(len(rows), noise))


def _concat(a: Pattern, b: Pattern) -> Pattern:
    return Pattern(*(np.concatenate([getattr(a, f), getattr(b, f)]) for f in
                     ("track_ids", "xy", "vectors", "brightness", "sightings", "sigma_px")))


def unknown_tracks(extraction: Extraction, track_ids: Iterable[int]) -> list[int]:
    """The ids among ``track_ids`` that are not tracks of ``extraction``, in the order given."""
    known = {t.id for t in extraction.tracks}
    return [int(t) for t in track_ids if int(t) not in known]


def build_pattern(sequence: Sequence, extraction: Extraction, *, exclude_tracks: Iterable[int] = (),
                  include_tracks: Iterable[int] | None = None, manual_points=()) -> Pattern:
    """The averaged pattern after an operator's edits.

    ``include_tracks`` None keeps every track that can be carried into the
    reference frame; otherwise exactly those ids (minus ``exclude_tracks``).
    ``manual_points`` are ``(snapshot_position, x, y)`` picked by hand in any
    snapshot; they are carried into the reference frame with ``motion`` and
    get track id -1, one sighting, the brightness of a reported source within
    3 px (else 0).  Raises :class:`PatternError` (a ValueError), with the
    reason and the entry at fault, for an unknown included track, a bad
    point, or a track/point whose snapshot has no estimated motion.
    Excluding a track that does not exist changes nothing here (stored
    patterns stay buildable); new edits are checked for that by
    :func:`unknown_tracks`.
    """
    tracks = _select_tracks(extraction, exclude_tracks, include_tracks)
    noise = extraction.noise_px if math.isfinite(extraction.noise_px) else DEFAULT_SIGHTING_SIGMA_PX
    pattern = tracks_pattern(sequence.camera, extraction.motion, tracks, noise)
    manual = _manual_pattern(sequence, extraction, list(manual_points))
    return _concat(pattern, manual) if len(manual) else pattern
