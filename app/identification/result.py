"""What identification returns: ranked, distinct attitude candidates and a status."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.attitude import quaternion_from_rotation, radec_roll_from_rotation
from app.camera import Camera
from app.camera_fit import CameraAttitudeFit, Calibration

#: Status values of a solved sequence.
IDENTIFIED = "identified"  # one candidate, false-match probability below the threshold
AMBIGUOUS = "ambiguous"  # candidates exist, an operator must decide
NO_MATCH = "no_match"  # nothing resembling the pattern in the catalogue


@dataclass(frozen=True)
class StarMatch:
    pattern_index: int  # row of the pattern
    track: int | None  # the pattern point's track id (None: picked by hand)
    hip: int
    name: str | None
    residual_arcsec: float


@dataclass(frozen=True)
class PlanetMatch:
    pattern_index: int
    track: int | None
    name: str  # "jupiter", ...
    residual_arcsec: float


@dataclass(frozen=True, eq=False)
class Candidate:
    """One distinct attitude hypothesis, refined over all its matched stars."""

    rank: int
    rotation_matrix: np.ndarray  # ICRS -> camera at the reference snapshot's time
    deviation_arcsec: float  # seed's deviation: sum over pattern points of the angle to the nearest star
    deviation_px_per_point: float
    rms_arcsec: float  # RMS residual of the matched points
    false_match_probability: float
    matches: tuple[StarMatch, ...]
    planets: tuple[PlanetMatch, ...] = ()
    # The pattern edge (two pattern rows) and the catalogue pair (HIP numbers)
    # that generated this hypothesis first.
    generating_edge: tuple[int, int] = (-1, -1)
    generating_pair_hip: tuple[int, int] = (-1, -1)
    n_hypotheses_merged: int = 1
    sigma_cross_boresight_arcsec: float | None = None
    sigma_roll_arcsec: float | None = None
    #: The camera the matches were made with when it is not the declared one (a focal length searched
    #: or optics fitted: :mod:`app.identification.optics`); None: the declared camera.
    camera: Camera | None = None
    #: The optics fitted with the attitude (reported whenever the candidate was credible enough): on the
    #: pattern, or over the whole sequence's sightings (app.identification.fit_sequence_camera).
    camera_fit: CameraAttitudeFit | Calibration | None = None
    #: RA, Dec (degrees) of the image's centre pixel, as astrometry.net reports a frame: the boresight's when
    #: the principal point is the centre, else through the optics (principal point free) fitted on the
    #: candidate's stars (:func:`app.identification.image_centre_radec`).  None: not computed (a candidate
    #: that is not credible: chance would explain it).
    centre_radec_deg: tuple[float, float] | None = None

    @property
    def n_matched(self) -> int:
        return len(self.matches)

    @property
    def quaternion(self) -> np.ndarray:
        return quaternion_from_rotation(self.rotation_matrix)

    @property
    def radec_roll_deg(self) -> tuple[float, float, float]:
        return radec_roll_from_rotation(self.rotation_matrix)


@dataclass(frozen=True, eq=False)
class FocalLengthContradiction:
    """The stars contradict the declared focal length: the pattern's bright triangles fit one outside the
    declared tolerance (:mod:`app.identification.focal_estimate`).  Such optics are never searched, since
    nothing found with them would be credible; an operator who recognises the pointing corrects the
    camera (or calibrates it) and searches again."""

    focal_length_px: float  # the focal length the triangles fit, refitted on every point they caught
    declared_focal_length_px: float
    declared_tolerance: float  # a fraction of the declared focal length
    n_matched: int  # pattern points on stars at that focal length
    n_points: int
    rotation_matrix: np.ndarray  # ICRS -> camera, the attitude at that focal length

    @property
    def offset(self) -> float:
        """The fitted focal length's departure from the declared one, a fraction."""
        return self.focal_length_px / self.declared_focal_length_px - 1

    @property
    def radec_roll_deg(self) -> tuple[float, float, float]:
        return radec_roll_from_rotation(self.rotation_matrix)

    def note(self) -> str:
        """What it means for an operator, in a sentence."""
        ra, dec, _ = self.radec_roll_deg
        return (f"the pattern's bright triangles fit a focal length of {self.focal_length_px:.1f} px "
                f"({self.offset:+.1%} of the declared), outside its tolerance of {self.declared_tolerance:.1%}, "
                f"with {self.n_matched} of {self.n_points} points on stars near RA {ra:.1f} deg, Dec {dec:+.1f} deg: "
                "if that is where the camera pointed, correct the camera's focal length (or its "
                "focal_length_tolerance) in the telemetry, or calibrate the camera, and search again")


@dataclass(frozen=True, eq=False)
class Solution:
    status: str
    candidates: tuple[Candidate, ...]
    elapsed_s: float = 0.0
    notes: tuple[str, ...] = field(default_factory=tuple)
    #: Set when the stars fit a focal length outside the declared tolerance (said here, not in ``notes``).
    focal_length_contradiction: FocalLengthContradiction | None = None
    #: Hypotheses tried, those a caller tried before included (the false-match probability's count).
    n_hypotheses: int = 0

    @property
    def best(self) -> Candidate | None:
        return self.candidates[0] if self.candidates else None
