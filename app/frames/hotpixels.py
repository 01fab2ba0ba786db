"""Hot-pixel maps: pixels that light up at the same place frame after frame while the stars move.

A frame's blobs flagged ``hot_pixel`` by :func:`app.frames.detect.detect` (one sharp pixel, no
point-spread function around it) are *candidates*: a hot pixel, or a cosmic-ray hit, or a noise
spike.  A camera's :class:`HotPixelMap` counts, per candidate pixel, in how many frames it was
one, and since which frame it has been seen.  A pixel is **hot** when it was a candidate in at
least ``MIN_FRAMES`` frames and in at least ``MIN_FRACTION`` of the frames taken since it was
first seen (hot pixels appear during a mission: radiation damage), which a cosmic ray (one frame)
or a star (it moves; and it is not sharp) never is.

Maps are kept per spacecraft and sensor size, versioned and append-only in the archive
(:meth:`app.storage.Storage.add_hot_pixel_map`); each upload of frames adds its candidates as a
new version.  A map is applied

* to later frames of the same camera: the hot pixels are replaced by their neighbours' median
  before detection (:func:`app.frames.detect.replace_pixels`), and any detection on one is
  dropped;
* to spot-list telemetry of the same camera: :func:`drop_hot_pixel_sources`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

#: A pixel is hot after being a candidate in this many frames...
MIN_FRAMES = 3
#: ...and in this fraction of the frames since it was first a candidate.
MIN_FRACTION = 0.3
#: Entries a stored map keeps (hot pixels first, then the most frequent candidates).
MAX_ENTRIES = 5000
#: Candidates one frame may add (the brightest; more means the frame is not a star field).
MAX_CANDIDATES_PER_FRAME = 256
#: A spot-list source this close to a hot pixel (pixels, each axis) is taken to be it.
SPOT_RADIUS_PX = 1.0


@dataclass(frozen=True)
class PixelRecord:
    count: int   # frames in which the pixel was a candidate
    first: int   # the map's frame count when it was first a candidate (0-based frame number)


@dataclass(frozen=True)
class HotPixelMap:
    """Candidate pixels of one camera with their counts; :attr:`hot` are the hot ones."""

    width: int
    height: int
    frames: int = 0
    pixels: dict[tuple[int, int], PixelRecord] = field(default_factory=dict)
    #: The archive's version of this map (None: not stored, e.g. built from one pass on the command line).
    version: int | None = None

    @property
    def sensor(self) -> str:
        return f"{self.width}x{self.height}"

    def is_hot(self, record: PixelRecord) -> bool:
        since = max(1, self.frames - record.first)
        return record.count >= MIN_FRAMES and record.count >= MIN_FRACTION * since

    @property
    def hot(self) -> list[tuple[int, int]]:
        """The hot pixels (x, y), sorted."""
        return sorted(p for p, record in self.pixels.items() if self.is_hot(record))

    def with_frames(self, candidates: list[list[tuple[int, int]]]) -> HotPixelMap:
        """This map after ``len(candidates)`` more frames, each with its candidate pixels."""
        pixels = dict(self.pixels)
        frames = self.frames
        for per_frame in candidates:
            for x, y in set(map(tuple, per_frame[:MAX_CANDIDATES_PER_FRAME])):
                if not (0 <= x < self.width and 0 <= y < self.height):
                    continue
                old = pixels.get((x, y))
                pixels[(x, y)] = PixelRecord(1, frames) if old is None else PixelRecord(old.count + 1, old.first)
            frames += 1
        return dataclasses.replace(self, frames=frames, pixels=_bounded(pixels, frames), version=None)

    def to_json(self) -> dict:
        """The stored form: ``{"width", "height", "frames", "pixels": [[x, y, count, first], ...]}``."""
        return {"width": self.width, "height": self.height, "frames": self.frames,
                "pixels": [[x, y, r.count, r.first] for (x, y), r in sorted(self.pixels.items())]}

    @classmethod
    def from_json(cls, doc: dict, version: int | None = None) -> HotPixelMap:
        pixels = {(int(x), int(y)): PixelRecord(int(c), int(f)) for x, y, c, f in doc.get("pixels", [])}
        return cls(width=int(doc["width"]), height=int(doc["height"]), frames=int(doc.get("frames", 0)),
                   pixels=pixels, version=version)

    @classmethod
    def empty(cls, width: int, height: int) -> HotPixelMap:
        return cls(width=width, height=height)


def _bounded(pixels: dict[tuple[int, int], PixelRecord], frames: int) -> dict[tuple[int, int], PixelRecord]:
    if len(pixels) <= MAX_ENTRIES:
        return pixels
    probe = HotPixelMap(1, 1, frames)
    ranked = sorted(pixels.items(), key=lambda item: (not probe.is_hot(item[1]), -item[1].count, item[0]))
    return dict(ranked[:MAX_ENTRIES])


def near_hot_pixel(xy: np.ndarray, hot: list[tuple[int, int]], radius_px: float = SPOT_RADIUS_PX) -> np.ndarray:
    """True for each position (n, 2) within ``radius_px`` (each axis) of a hot pixel."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if not len(hot) or not len(xy):
        return np.zeros(len(xy), dtype=bool)
    h = np.asarray(hot, dtype=float).reshape(-1, 2)
    close = (np.abs(xy[:, None, 0] - h[None, :, 0]) <= radius_px) & (np.abs(xy[:, None, 1] - h[None, :, 1]) <= radius_px)
    return close.any(axis=1)


def drop_hot_pixel_sources(sequence, hot: list[tuple[int, int]], radius_px: float = SPOT_RADIUS_PX):
    """Spot-list telemetry without the sources on hot pixels: ``(sequence, dropped)``.

    ``sequence`` is an :class:`app.telemetry.Sequence`; ``dropped[i]`` lists the input positions
    (0-based, file order) of the sources removed from snapshot i.  The order of the other sources
    is kept.  With no hot pixel (or none hit) the same sequence object is returned.
    """
    dropped = []
    snapshots = []
    for snap in sequence.snapshots:
        on_hot = near_hot_pixel(snap.xy, hot, radius_px)
        dropped.append([int(k) for k in np.flatnonzero(on_hot)])
        if on_hot.any():
            snap = dataclasses.replace(snap, xy=snap.xy[~on_hot], brightness=snap.brightness[~on_hot])
        snapshots.append(snap)
    if not any(dropped):
        return sequence, dropped
    return dataclasses.replace(sequence, snapshots=tuple(snapshots)), dropped


#: The sky counts as static when the median fraction of a frame's star-like blobs found again within
#: :data:`STATIC_MATCH_PX` of the previous frame's exceeds this.
STATIC_SKY_FRACTION = 0.3
STATIC_MATCH_PX = 0.5


def sky_is_static(xy_per_frame: list[np.ndarray]) -> bool:
    """True when the stars did not move between the frames (inertial pointing): most blobs of each
    frame lie within half a pixel of one of the previous frame's."""
    fractions = []
    for before, after in zip(xy_per_frame, xy_per_frame[1:]):
        before, after = np.asarray(before, float).reshape(-1, 2), np.asarray(after, float).reshape(-1, 2)
        if not len(before) or not len(after):
            continue
        d = np.hypot(after[:, None, 0] - before[None, :, 0], after[:, None, 1] - before[None, :, 1]).min(axis=1)
        fractions.append(float(np.mean(d < STATIC_MATCH_PX)))
    return bool(fractions) and float(np.median(fractions)) > STATIC_SKY_FRACTION


def stationary_candidates(peaks_per_frame: list[list[tuple[int, int]]],
                          xy_per_frame: list[np.ndarray]) -> list[list[tuple[int, int]]]:
    """Per frame, the star-like blobs whose peak pixel is the same in at least ``MIN_FRAMES`` frames of
    the pass while the stars moved: hot pixels a sharpness test misses (pairs, clusters, a hot pixel
    on a faint star's wing).  From a pass whose sky did not move (:func:`sky_is_static`: every star
    stays put) nothing is taken."""
    none: list[list[tuple[int, int]]] = [[] for _ in peaks_per_frame]
    if len(peaks_per_frame) < MIN_FRAMES or sky_is_static(xy_per_frame):
        return none
    counts: dict[tuple[int, int], int] = {}
    for peaks in peaks_per_frame:
        for p in set(peaks):
            counts[p] = counts.get(p, 0) + 1
    repeated = {p for p, n in counts.items() if n >= MIN_FRAMES}
    return [[p for p in peaks if p in repeated] for peaks in peaks_per_frame]
