"""What extraction returns: tracks, per-source verdicts, inter-snapshot motion, patterns."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Version of the extraction method.  Stored extractions carry it; patterns refer to their
#: track ids, so a change that can number tracks differently must raise it (the archive then
#: refuses to re-extract old uploads silently: see app.workflow.archive).
#: 2: the work per snapshot link is capped (ExtractionParameters.max_link_work); sequences of
#: up to ~30 sources per snapshot extract as in version 1.
#: 3: a link with the fewest matches accepted gets skip links as rivals (the most matches wins),
#: and runs of snapshots cut off from the longest run are registered against its tracks.
EXTRACTION_VERSION = 3

#: 1-sigma position noise of one sighting, pixels per axis, wherever it could not be measured
#: (a single snapshot, too few tracks); the estimate's bounds are in ExtractionParameters.
DEFAULT_SIGHTING_SIGMA_PX = 0.7
#: ... and, where only assumed (a single snapshot), at least this fraction of the sensor's larger side:
#: a pinhole with one radial term leaves part of a lens's distortion, a part of the field whatever its
#: sampling (the real 27 deg frames: 1.3-3 px rms of 1,392 px with k1 and the principal point fitted).
#: Chosen so that the default holds to 1,400 px across, the finest sampling it was checked on with real
#: lenses; beyond, it grows with the sampling (1.4 px at 2,800 px, a photograph binned to the detection
#: budget), and every tolerance in pixels with it.
MODEL_ERROR_FRACTION = 5e-4


def assumed_sighting_noise_px(camera, default_px: float = DEFAULT_SIGHTING_SIGMA_PX) -> float:
    """The 1-sigma position error assumed for a sighting that nothing measures: ``default_px``, or
    :data:`MODEL_ERROR_FRACTION` of ``camera``'s larger side where that is more."""
    return max(float(default_px), MODEL_ERROR_FRACTION * max(camera.width, camera.height))

#: Rejection reasons of a source.
GHOST = "ghost"  # no consistent partner in any other snapshot
HOT_PIXEL = "hot_pixel"  # stays on the same pixel while the sky moves away from it, or known hot (a map)
OUTLIER = "outlier"  # linked to a track but inconsistent with it
REASONS = (GHOST, HOT_PIXEL, OUTLIER)


@dataclass(frozen=True)
class ExtractionParameters:
    """Tunable figures of :func:`app.extraction.extract`, in pixels unless stated.

    Gates scale with the noise estimated from the data (``sigma``, the
    1-sigma position error of one sighting per axis) but never drop below
    the floors given here, so integer-pixel telemetry still links.
    """

    #: Chord agreement of two source pairs before they may be the same stars.
    pair_tol_px: float = 3.0
    #: Source pairs closer than this never generate a rotation hypothesis.
    min_baseline_px: float = 40.0
    #: Distance at which a rotated source stops counting for a hypothesis.
    score_gate_px: float = 8.0
    #: Mutual-neighbour gate of the first rotation fit (before the noise is known).
    fit_gate_px: float = 5.0
    #: Fewest matched sources for a snapshot-to-snapshot rotation ...
    min_inliers: int = 3
    #: ... and the most false alarms tolerated (see app.extraction.motion.false_alarms),
    #: crediting every match with at least this residual.
    #: 0.02 per link keeps a pure-noise sequence of 16 snapshots almost always trackless.
    max_false_alarms: float = 0.02
    min_match_radius_px: float = 0.7
    #: Hypotheses come from the K brightest sources of each snapshot.
    hypothesis_sources: int = 20
    #: Most (hypothesis x source pair) evaluations per snapshot link: a link of n_a and n_b
    #: sources scores at most max(min_link_hypotheses, max_link_work // (n_a n_b)) hypotheses,
    #: the brightest (see app.extraction.motion).  2**18 never cuts the ~200 hypotheses of 10
    #: sources per snapshot (nor ~650 of 20) and keeps 64 x 64 random sources near 0.3 s.
    max_link_work: int = 1 << 18
    min_link_hypotheses: int = 64
    #: Sources of other snapshots examined around each source as its possible hot-pixel partners
    #: (nearest in x first): far more than real telemetry has within a few pixels, and a bound on
    #: the pairs of a file that puts every source on one pixel (64 x 64 would give 16 million).
    max_pixel_partners: int = 256
    #: A snapshot with no rotation to its predecessor is linked to up to this
    #: many snapshots back (so one bad snapshot does not cut the sequence).
    max_skip: int = 3
    #: Association gate in the common frame: max(floor, k * sigma).
    link_gate_floor_px: float = 3.5
    link_gate_sigmas: float = 6.0
    #: Two sightings of a hot pixel are this close: max(floor, k * sigma).
    hot_tol_floor_px: float = 1.0
    hot_tol_sigmas: float = 2.5
    #: A tracked sighting is an outlier beyond max(floor, k * sigma * sqrt(1 + 1/(n-1)))
    #: from the mean of the track's other n-1 sightings.
    outlier_floor_px: float = 2.0
    outlier_sigmas: float = 4.5
    #: Bounds of the estimated single-sighting noise.
    sigma_min_px: float = 0.3
    sigma_max_px: float = 3.0
    #: Noise assumed when nothing could be measured.
    sigma_default_px: float = DEFAULT_SIGHTING_SIGMA_PX


@dataclass(frozen=True, eq=False)
class Track:
    """One light source followed through the sequence."""

    id: int  # 0..T-1, numbered in order of first appearance
    snapshots: np.ndarray  # (k,) int: positions (0-based, file order) of snapshots where seen
    source_indices: np.ndarray  # (k,) int: index of the source within that snapshot
    xy: np.ndarray  # (k, 2) pixel positions
    mean_brightness: float

    @property
    def n_sightings(self) -> int:
        return int(self.snapshots.shape[0])


@dataclass(frozen=True, eq=False)
class Pattern:
    """The point pattern handed to identification, in the reference snapshot's frame."""

    track_ids: np.ndarray  # (m,) int; -1 for a point picked by hand
    xy: np.ndarray  # (m, 2) pixels in the REFERENCE snapshot's frame
    vectors: np.ndarray  # (m, 3) camera-frame unit vectors (through sequence.camera)
    brightness: np.ndarray  # (m,) mean brightness
    sightings: np.ndarray  # (m,) int: number of snapshots averaged
    sigma_px: np.ndarray  # (m,) estimated 1-sigma position error in pixels of each point

    def __len__(self) -> int:
        return int(self.track_ids.shape[0])

    @staticmethod
    def empty() -> "Pattern":
        return Pattern(np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0),
                       np.zeros(0, int), np.zeros(0))


@dataclass(frozen=True, eq=False)
class Extraction:
    """Tracked stars vs the rest, for one sequence."""

    reference: int  # position of the reference snapshot (most tracked sources)
    track_of_source: tuple[np.ndarray, ...]  # per snapshot (n_i,) int, -1 where rejected
    rejection: tuple[tuple[str | None, ...], ...]  # per snapshot per source: None or a REASONS member
    tracks: tuple[Track, ...]
    # (S, 3, 3): v_ref = motion[i] @ v_i; identity at the reference; NaN where unknown
    motion: np.ndarray
    pattern: Pattern  # every track carried into the reference frame and averaged
    seed_pattern: Pattern  # the seed's: tracked sources of the reference snapshot as they are
    #: Estimated 1-sigma position noise of one sighting, pixels per axis.
    noise_px: float = math.nan
    #: Human-readable remarks (single snapshot, sky not moving, ...).
    notes: tuple[str, ...] = ()
    #: Per snapshot (n_i,) bool: the sources the caller declared hot pixels (``extract``'s
    #: ``known_hot``, e.g. from the camera's hot-pixel map); None when none were given.
    known_hot: tuple[np.ndarray, ...] | None = None
