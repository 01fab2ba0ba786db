"""Identification: from an extracted pattern to ranked attitude candidates.

``solve_sequence`` is the one function the workflow and the benchmarks
call: extraction (unless given) -> pattern (unless given) -> identification
at the reference snapshot's time by one of :data:`METHODS`, with planets
labelled -> for every credible candidate, the attitude of the whole sequence
(one per snapshot, the body rate, and the attitude at the reference time
averaged over all snapshots: :mod:`app.attitude.sequence`).

Modules: ``options`` (:class:`SearchOptions`), ``sky`` (catalogue + index),
``methods`` (the registry), ``hypotheses`` and ``triangle_features``
(hypothesis generators), ``verify`` (check, refine, score), ``candidates``
(the one candidate builder), ``engine`` (lost in space), ``near_prior``
(tracking from a prior), ``result`` (what identification returns).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import chdtri

from app.attitude import propagate
from app.attitude.sequence import SequenceFit, fit_constant_rate, rate_from_motion, wahba_per_snapshot
from app.attitude.wahba import cross_boresight_and_roll_sigma
from app.camera_fit import Calibration, CameraAttitudeFit, default_priors, parameters_for
from app.camera_fit import calibrate as calibrate_camera
from app.catalogue import vectors_to_radec
from app.compiled import warm_up
from app.extraction import Extraction, Pattern, extract
from app.identification.candidates import optics_attitude_covariance
from app.identification.engine import classify, identify, is_rival
from app.identification.methods import METHODS, Method
from app.identification.near_prior import identify_near_prior
from app.identification.optics import ADOPT_PROBABILITY, HINT_PROBABILITY, departs
from app.identification.options import SearchOptions
from app.identification.result import (AMBIGUOUS, IDENTIFIED, NO_MATCH, Candidate, FocalLengthContradiction,
                                       PlanetMatch, Solution, StarMatch)
from app.identification.scale_free import NOT_GIVEN
from app.identification.sightings import (claimed_once, identified_sightings, observations, sighting_noise_px,
                                          source_match_tolerance_rad, sources_field, stars_at)
from app.identification.sky import Sky
from app.telemetry import Sequence

__all__ = ["AMBIGUOUS", "IDENTIFIED", "METHODS", "NO_MATCH", "Candidate", "FocalLengthContradiction", "Method",
           "PlanetMatch", "Prior", "SourceNames",
           "SearchOptions", "Sky", "Solution", "SolvedSequence", "StarMatch", "classify", "fit_sequence",
           "identify", "identify_near_prior", "solve_sequence", "source_stars"]


#: The image centre's direction is taken through optics with a free principal point (and k1) from this many
#: matched stars: a real lens's axis is often off the sensor's centre (tilted sensors, off-axis test frames:
#: 3-8 px of residual with a centred pinhole), and with fewer stars the principal point trades off against
#: the attitude too freely.  The centre's direction itself hardly depends on that trade-off (moving the
#: principal point and turning the camera together leaves it in place), which is why it is reported.
MIN_STARS_FOR_FREE_CENTRE = 8
#: ... with a weak prior: the principal point within this fraction of the sensor's width of its declared place.
PRINCIPAL_POINT_PRIOR_FRACTION = 0.1
#: A pattern point is taken for the star it sees within this many pixels (or 3 times the candidate's RMS
#: residual, when larger) for the image centre's fit: real centroids err by 1-2 px (trailed, saturated stars).
CENTRE_MATCH_PX = 3.0
#: A sighting no matched track vouches for is named only when a source scattered at random would fall that
#: near a star that bright less often than this: the sequences' ghosts and hot pixels (a few per snapshot)
#: then name a star at a rate of about 1 in 10,000 labels, and stars seen alone, brighter and nearer, keep it.
CHANCE_NAME_PROBABILITY = 1e-4


#: A sequence fit turning faster than this is not trusted: stars streak across many pixels within one
#: exposure long before (TUBSAT-class sensors track at well under 1 deg/s), so such a rate means wrong
#: time tags or a wrong identification, not a fast spacecraft.
MAX_PLAUSIBLE_RATE_DEG_S = 10.0


@dataclass(frozen=True, eq=False)
class SolvedSequence:
    sequence: Sequence
    extraction: Extraction
    pattern: Pattern
    solution: Solution
    #: Sequence attitude fits by candidate rank (credible candidates of multi-snapshot sequences).
    sequence_fits: dict[int, SequenceFit] = field(default_factory=dict)

    @property
    def reference_time(self):
        return self.sequence.snapshots[self.extraction.reference].time


@dataclass(frozen=True)
class Prior:
    """A prior attitude for tracking mode: ICRS -> camera at ``time`` (or at the
    reference snapshot when None), turning at ``rate_rad_s`` (camera axes)."""

    rotation: np.ndarray
    sigma_deg: float = 1.0
    time: object | None = None  # datetime
    rate_rad_s: np.ndarray | None = None

    def at(self, t) -> np.ndarray:
        """The prior propagated to ``t`` with its rate (:func:`app.attitude.propagate`)."""
        if self.time is None or self.rate_rad_s is None:
            return np.asarray(self.rotation, dtype=float)
        return propagate(self.rotation, self.rate_rad_s, (t - self.time).total_seconds())


def solve_sequence(sequence: Sequence, sky: Sky, *, options: SearchOptions = SearchOptions(),
                   extraction: Extraction | None = None, pattern: Pattern | None = None,
                   with_planets: bool = True, method: str = "bright_pair",
                   prior: Prior | None = None) -> SolvedSequence:
    """Extract (unless ``extraction`` is given) and identify ``pattern`` (default: the averaged one).

    ``method`` names one of :data:`METHODS`.  With a ``prior`` (required by
    ``tracking``, and turning any lost-in-space method into tracking) the
    pattern is matched near it (:func:`identify_near_prior`).  A sequence whose
    time is assumed is matched to the stars' mean places, without planets
    (:attr:`app.telemetry.Sequence.observer`).
    """
    from app.planets import planet_vectors

    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    if METHODS[method].needs_prior and prior is None:
        raise ValueError(f"the {method} method needs a prior attitude")
    # Every kernel, the extraction's too, before the extraction runs: a first run compiles them all at once on
    # every core (app.compiled) instead of the extraction's one by one at its first calls; with the cache
    # complete, each loads at its first call.
    warm_up(eager=False)
    extraction = extraction if extraction is not None else extract(sequence)
    pattern = pattern if pattern is not None else extraction.pattern
    t = sequence.snapshots[extraction.reference].time
    if prior is not None:
        solution = identify_near_prior(pattern, sequence.camera, t, sky, prior.at(t), prior_sigma_deg=prior.sigma_deg,
                                       velocity_km_s=sequence.observer, options=options)
    else:
        planets = (lambda: planet_vectors(t)) if with_planets and not sequence.time_assumed else None
        solution = identify(pattern, sequence.camera, t, sky, velocity_km_s=sequence.observer,
                            options=options, planets=planets, method=method)
        # Every further search within what the first left of one search's time-out.
        left_s = options.timeout_s - solution.elapsed_s
        if (solution.status != IDENTIFIED and "frames" in sequence.extra and len(pattern) >= 3
                and sequence.camera.focal_length_rough and left_s >= MIN_SECOND_SEARCH_S):
            solution = without_the_field_of_view(solution, pattern, sequence.camera, t, sky,
                                                 velocity_km_s=sequence.observer,
                                                 options=replace(options, timeout_s=left_s), planets=planets,
                                                 method=method)
            left_s = options.timeout_s - solution.elapsed_s
        if (solution.status == NO_MATCH and "frames" in sequence.extra and len(pattern) >= 3
                and left_s >= MIN_SECOND_SEARCH_S):
            said = mirrored_match(pattern, sequence.camera, t, sky, velocity_km_s=sequence.observer,
                                  options=replace(options, timeout_s=left_s), method=method)
            if said is not None:
                solution = replace(solution, notes=(*solution.notes, said))
    fits: dict[int, SequenceFit] = {}
    candidates = []
    notes = list(solution.notes)
    status = solution.status
    best = solution.candidates[0] if solution.candidates else None
    for c in solution.candidates:
        fit = None
        # The sequence fit for the best candidate and its rivals (what an operator weighs up).
        credible = c.false_match_probability <= options.rival_probability and (c is best or is_rival(c, best, options))
        if credible and len(sequence.snapshots) > 1:
            pattern_fit = c.camera_fit  # the optics fitted with the pattern's attitude (None: not fitted)
            if c.camera is not None or (c.camera_fit is not None
                                        and departs(c.camera_fit, sequence.camera, HINT_PROBABILITY)):
                c = fit_sequence_camera(sequence, extraction, c, sky.for_camera(c.camera or sequence.camera))
            fit = fit_sequence(sequence, extraction, pattern, c, sky.for_camera(c.camera or sequence.camera))
            if fit is not None and isinstance(pattern_fit, CameraAttitudeFit):
                fit = _fit_with_optics_uncertainty(fit, pattern_fit, c.camera_fit)
        rate_deg_s = math.degrees(float(np.linalg.norm(fit.rate_rad_s))) if fit is not None else 0.0
        if rate_deg_s > MAX_PLAUSIBLE_RATE_DEG_S:
            notes.append(f"the sequence fit of candidate {c.rank} gives a body rate of {rate_deg_s:,.0f} deg/s, "
                         f"beyond the {MAX_PLAUSIBLE_RATE_DEG_S:g} deg/s at which a star camera still images "
                         "stars: the fit is not used and the sequence needs an operator (check the snapshot times)")
            if c is best and status == IDENTIFIED:
                status = AMBIGUOUS
            fit = None
        if fit is not None:
            fits[c.rank] = fit
            cross, roll = cross_boresight_and_roll_sigma(fit.covariance)
            c = replace(c, rotation_matrix=fit.rotation,
                        sigma_cross_boresight_arcsec=math.degrees(cross) * 3600,
                        sigma_roll_arcsec=math.degrees(roll) * 3600)
        if credible and options.image_centre:  # of an answer an operator weighs up (a chance fit's is noise)
            c = replace(c, centre_radec_deg=image_centre_radec(c, pattern, sequence.camera, t, sky,
                                                               velocity_km_s=sequence.observer))
        candidates.append(c)
    solution = replace(solution, candidates=tuple(candidates), status=status, notes=tuple(notes))
    return SolvedSequence(sequence=sequence, extraction=extraction, pattern=pattern, solution=solution,
                          sequence_fits=fits)


#: An image whose field of view given by hand identifies nothing is searched without it
#: (:func:`without_the_field_of_view`), and one that matches nothing mirrored (:func:`mirrored_match`), in what
#: is left of the search's time-out, when that is at least this (s).
MIN_SECOND_SEARCH_S = 0.5


def without_the_field_of_view(first: Solution, pattern: Pattern, camera, t, sky: Sky, *, velocity_km_s=None,
                              options: SearchOptions = SearchOptions(), planets=None,
                              method: str = "bright_pair") -> Solution:
    """``first``, an image's answer with the field of view it was given by hand, or the image identified
    without it, whichever is better.

    A field of view given by hand can be plainly wrong: a photograph cropped or turned keeps its lens's angle
    in its owner's mind (a crop of half the width spans half the angle), another lens's, a guess. Within its
    tolerance nothing is identified then, though the stars alone would be: the pattern is searched again as if
    no field of view had been given (:mod:`.scale_free`), the first search's hypotheses counted in the
    false-match probability. Only an ``identified`` answer replaces the first, with a note saying the field of
    view given did not fit and what the stars fit; otherwise the first stays, and a note says what the second
    search found.
    """
    free = replace(camera, focal_length_unknown=True, focal_length_tolerance=None)
    found = identify(pattern, free, t, sky, velocity_km_s=velocity_km_s, options=options, planets=planets,
                     method=method, hypotheses_before=first.n_hypotheses)
    given = camera.fov_deg[0]
    elapsed = first.elapsed_s + found.elapsed_s
    if found.status != IDENTIFIED:
        return replace(first, elapsed_s=elapsed, n_hypotheses=max(first.n_hypotheses, found.n_hypotheses),
                       notes=(*first.notes, f"searched again without the field of view given ({given:.1f} deg): "
                                            f"{found.status.replace('_', ' ')} there"))
    fitted = found.candidates[0].camera
    said = (f"the field of view given, {given:.1f} deg, fits nothing identified"
            + (f"; the stars fit {fitted.fov_deg[0]:.2f} deg" if fitted is not None else "")
            + " (check it: a cropped or turned image spans another angle than its lens)")
    how, *rest = found.notes  # the search over scales: what it searched, after its own opening words
    # Two notes: the one an operator must read first stays short (the search's account is long).
    return replace(found, elapsed_s=elapsed,
                   notes=(said, f"searched again without it: {how.removeprefix(NOT_GIVEN)}", *rest))


def mirrored(pattern: Pattern, camera) -> tuple[Pattern, object]:
    """``pattern`` and ``camera`` seen in a mirror, left to right: x -> width - 1 - x (and the principal
    point with it), so each camera-frame vector's x is negated and nothing else changes (the distortion is
    radial)."""
    xy = pattern.xy.copy()
    xy[:, 0] = camera.width - 1 - xy[:, 0]
    vectors = pattern.vectors * np.array([-1.0, 1.0, 1.0])
    return replace(pattern, xy=xy, vectors=vectors), replace(camera, cx=camera.width - 1 - camera.cx)


def mirrored_match(pattern: Pattern, camera, t, sky: Sky, *, velocity_km_s=None,
                   options: SearchOptions = SearchOptions(), method: str = "bright_pair") -> str | None:
    """What to tell of a pattern that matches nothing as it is: whether its mirror image is identified.

    A rotation cannot mirror, so a mirrored image matches no sky (astrometry.net tries both parities for
    that reason).  Images come mirrored: a FITS file stored bottom-up with no ROWORDER, a flip in some
    program, a mirror in the optics.  The mirror image is searched with the same options and bounds; when
    it is identified, the note says where (the answer stays no match: its attitude would be a mirrored
    camera's), else None.  Only for images (a spot list's sensor is configured once: its no-match frames,
    the Earth's and noise's, keep their time), and within what the first search left of the time-out.
    """
    image, seen_by = mirrored(pattern, camera)
    found = identify(image, seen_by, t, sky, velocity_km_s=velocity_km_s, options=options, method=method)
    if found.status != IDENTIFIED:
        return None
    best = found.candidates[0]
    ra, dec, _ = best.radec_roll_deg
    return (f"mirrored left to right, the sources are identified (boresight RA {ra:.3f} deg, Dec {dec:+.3f} deg, "
            f"{best.n_matched} stars, P(false) {best.false_match_probability:.1e}): the "
            "image is mirrored (a FITS file stored bottom-up with no ROWORDER, a flip in processing, a mirror in "
            "the optics); flip it and solve it again")


def image_centre_radec(candidate: Candidate, pattern: Pattern, declared, t, sky: Sky, *,
                       velocity_km_s=None) -> tuple[float, float]:
    """RA, Dec (degrees) of the centre pixel ``((width - 1)/2, (height - 1)/2)`` under ``candidate``.

    Every pattern point (not only the brightest the search used) is matched
    to the star it sees within :data:`CENTRE_MATCH_PX` (or 3 times the
    candidate's RMS residual) through the candidate's camera (or
    ``declared``) and attitude, each star once; from
    :data:`MIN_STARS_FOR_FREE_CENTRE` such stars the optics are fitted on
    them with the attitude (focal length, k1, and the principal point with a
    weak prior of :data:`PRINCIPAL_POINT_PRIOR_FRACTION` of the width; least
    squares in pixels, :func:`app.camera_fit.fit_attitude_and_camera`), and
    the stars matched again through the fit, twice (once, when the fit matches
    the stars it was fitted on).  With fewer stars, the centre is seen through
    the candidate's own camera.
    """
    from app.camera_fit import fit_attitude_and_camera

    camera = candidate.camera or declared
    rotation = candidate.rotation_matrix
    centre = np.array([[(camera.width - 1) / 2.0, (camera.height - 1) / 2.0]])
    depth = sky.for_camera(camera)
    field = depth.field(t, depth.depth_for(camera, SearchOptions().mag_margin), velocity_km_s)
    rms_px = (candidate.rms_arcsec or 0.0) / camera.pixel_scale_arcsec
    tolerance_px = max(CENTRE_MATCH_PX, 3.0 * rms_px)
    xy = np.asarray(pattern.xy, dtype=float)
    sigma = np.nan_to_num(np.asarray(pattern.sigma_px, dtype=float), nan=0.5)
    names = ("focal_length_px", "k1", "cx", "cy")
    spread = PRINCIPAL_POINT_PRIOR_FRACTION * camera.width
    priors = {**default_priors(camera, names), "cx": (camera.cx, spread), "cy": (camera.cy, spread)}
    fitted_camera, fitted_rotation = camera, rotation
    fitted_on = None
    for _ in range(2):
        stars = stars_at(xy, fitted_camera, fitted_rotation, field, tolerance_px * fitted_camera.pixel_scale_rad)
        ok = claimed_once(stars)
        if np.count_nonzero(ok) < MIN_STARS_FOR_FREE_CENTRE:
            break
        if fitted_on is not None and np.array_equal(np.where(ok, stars, -1), fitted_on):
            break  # the fit matched the stars it was fitted on: fitting them again ends where it began
        fitted_on = np.where(ok, stars, -1)
        try:
            free = fit_attitude_and_camera(xy[ok], field.vectors[stars[ok]], fitted_rotation, camera,
                                           max(float(np.median(sigma[ok])), 0.05), fit=names, priors=priors)
        except ValueError:  # the stars cannot separate the parameters: the candidate's own camera
            break
        if not _principal_point_departs(free, camera):
            # The stars do not ask for another principal point: the camera's own, with the focal length and
            # k1 fitted (a free principal point on a centred lens only adds its noise to the centre).
            try:
                free = fit_attitude_and_camera(xy[ok], field.vectors[stars[ok]], fitted_rotation, camera,
                                               max(float(np.median(sigma[ok])), 0.05), fit=names[:2],
                                               priors=default_priors(camera, names[:2]))
            except ValueError:
                break
        fitted_camera, fitted_rotation = free.camera, free.rotation
    direction = fitted_rotation.T @ fitted_camera.pixels_to_vectors(centre)[0]
    ra, dec = vectors_to_radec(direction[None])
    return float(np.degrees(ra[0]) % 360.0), float(np.degrees(dec[0]))


def _principal_point_departs(fit, camera) -> bool:
    """Whether ``fit``'s principal point departs from ``camera``'s beyond chance (:data:`HINT_PROBABILITY`):
    the squared Mahalanobis distance of (cx, cy) against the chi-square quantile of 2 degrees of freedom."""
    names = list(fit.covariance_names)
    at = [names.index("cx"), names.index("cy")]
    d = np.array([fit.camera.cx - camera.cx, fit.camera.cy - camera.cy])
    try:
        distance = float(d @ np.linalg.solve(fit.covariance[np.ix_(at, at)], d))
    except np.linalg.LinAlgError:
        return False
    return distance > chdtri(2, HINT_PROBABILITY)


@dataclass(frozen=True)
class SourceNames:
    """The HIP number (or None) of every reported source, per snapshot in input order, and how many sources
    lie within the match distance of a star but were left unnamed, the name not being certain."""

    names: list[list[int | None]]
    uncertain: int

    @property
    def note(self) -> str | None:
        if not self.uncertain:
            return None
        return (f"{self.uncertain} source(s) near a star left unnamed: the name is not certain (another "
                f"source claims the star, the matched track names another, or a ghost would fall that near "
                f"a star that bright by chance more often than 1 in {round(1 / CHANCE_NAME_PROBABILITY):,})")


def source_stars(solved: SolvedSequence, sky: Sky, rank: int = 1,
                 mag_margin: float = SearchOptions().mag_margin) -> SourceNames | None:
    """HIP number (or None) of every reported source, by the attitude of candidate ``rank``.

    Each snapshot's attitude comes from the sequence fit (or, without one,
    from extraction's motion), so sources that tracking had to call ghosts,
    stars the sensor reported only once, are recognised too.  None unless the
    candidate's false-match probability reaches the "identified" threshold.

    A name is given only where it is certain (a wrong name is worse than
    none): the source's brightest star within the match distance
    (:func:`stars_at`), named by no other source of its snapshot; a sighting
    of a track the candidate matched must name the track's star; and the
    sightings no matched track vouches for (a ghost, a hot pixel and a star
    seen alone look alike) are named only where sources scattered at random
    would fall that near a star that bright less often than
    :data:`CHANCE_NAME_PROBABILITY` (:func:`chance_of_falling_near`): the
    product over the sightings of one track that name that star, as each
    snapshot is a new draw.
    """
    candidate = next((c for c in solved.solution.candidates if c.rank == rank), None)
    if candidate is None or candidate.false_match_probability > SearchOptions().identified_probability:
        return None
    sequence, extraction = solved.sequence, solved.extraction
    camera = candidate.camera or sequence.camera
    sky = sky.for_camera(camera)  # the depth the candidate was identified at
    t_ref = solved.reference_time
    fit = solved.sequence_fits.get(rank)
    tolerance = source_match_tolerance_rad(camera, extraction)
    noise_rad = sighting_noise_px(extraction) * camera.pixel_scale_rad
    field = sources_field(sky, sequence, t_ref, camera, mag_margin)
    star_of_track = {m.track: m.hip for m in candidate.matches if m.track is not None}
    track_of = {(position, source): track.id for track in extraction.tracks
                for position, source in zip(track.snapshots.tolist(), track.source_indices.tolist())}
    names: list[list[int | None]] = [[None] * snap.n_sources for snap in sequence.snapshots]
    near_a_star = 0
    unvouched: dict[tuple, list[tuple[int, int, float]]] = {}  # (track or sighting, HIP) -> (snapshot, source, chance)
    for pos, snap in enumerate(sequence.snapshots):
        dt = (snap.time - t_ref).total_seconds()
        if fit is not None:
            R = fit.attitude_at(dt)
        elif np.all(np.isfinite(extraction.motion[pos])):
            R = extraction.motion[pos].T @ candidate.rotation_matrix
        else:
            continue
        stars = stars_at(snap.xy, camera, R, field, tolerance)
        hips = np.where(claimed_once(stars), sky.index.hip[field.rows[np.maximum(stars, 0)]], -1)
        chance = chance_of_falling_near(snap.xy, camera, R, field, stars, noise_rad)
        near_a_star += int(np.count_nonzero(stars >= 0))
        for source in np.flatnonzero(hips >= 0).tolist():
            hip, track = int(hips[source]), track_of.get((pos, source))
            if track in star_of_track:
                names[pos][source] = hip if hip == star_of_track[track] else None
            else:
                key = ("track", track) if track is not None else ("sighting", pos, source)
                unvouched.setdefault((key, hip), []).append((pos, source, float(chance[source])))
    for (_, hip), sightings in unvouched.items():
        if math.prod(c for _, _, c in sightings) < CHANCE_NAME_PROBABILITY:
            for pos, source, _ in sightings:
                names[pos][source] = hip
    named = sum(name is not None for snap in names for name in snap)
    return SourceNames(names=names, uncertain=near_a_star - named)


def chance_of_falling_near(xy: np.ndarray, camera, rotation: np.ndarray, field, stars: np.ndarray,
                           noise_rad: float) -> np.ndarray:
    """(n,) probability that a source scattered at random on the sky falls as near a star as bright as
    ``stars`` (from :func:`stars_at`; inf where -1) as each of ``xy`` falls to its own.

    With stars of magnitude <= m spread at ``N(<= m) / 4 pi`` per steradian
    (their mean density over the sky), the chance of one within angle ``d``
    is ``pi d^2 N(<= m) / 4 pi`` (small angles); ``d`` is at least one
    sighting's noise (``noise_rad``), as no sighting fits closer than that.
    """
    out = np.full(len(xy), np.inf)
    seen = stars >= 0
    if not np.any(seen):
        return out
    body = camera.pixels_to_vectors(np.asarray(xy, dtype=float)[seen])
    cosine = np.clip(np.einsum("ni,ni->n", body @ rotation, field.vectors[stars[seen]]), -1.0, 1.0)
    distance = np.maximum(np.arccos(cosine), noise_rad)
    if field.mag is None:
        brighter = np.full(len(distance), len(field.vectors))
    else:
        brighter = np.searchsorted(field.mag, field.mag[stars[seen]], side="right")  # mag ascends
    out[seen] = np.pi * distance ** 2 * brighter / (4 * np.pi)
    return out


def fit_sequence_camera(sequence: Sequence, extraction: Extraction, candidate: Candidate, sky: Sky) -> Candidate:
    """The candidate with its optics refitted over every snapshot's raw sightings (one camera, an attitude
    per snapshot: :func:`app.camera_fit.calibrate` on this one sequence).

    Optics fitted on the averaged pattern alone are biased when they are
    far from the declared ones: extraction carried the sightings into the
    reference frame through the declared camera, and undeclared distortion
    moves stars differently across the field as it turns.  The raw
    sightings are free of that.  The focal length and k1 are fitted (with
    the declaration's weak priors); the principal point needs many
    sequences (a calibration).  The fitted camera is adopted when the
    candidate had adopted fitted optics already or the sequence's sightings
    reject the declared ones (:func:`app.identification.optics.departs`);
    the candidate is returned unchanged when the sightings cannot fix the
    optics.
    """
    star_of_track = {m.track: m.hip for m in candidate.matches if m.track is not None}
    found = observations(identified_sightings(sequence, extraction, star_of_track, sky), extraction,
                         candidate.rotation_matrix, None)
    names = parameters_for(sum(len(o.xy) for o in found) // max(1, len(found)))
    if len(found) < 2 or not names:
        return candidate
    try:
        result = calibrate_camera(found, candidate.camera or sequence.camera, parameters=names,
                                  priors=default_priors(sequence.camera, names))
    except ValueError:
        return candidate
    # Adopted when the pattern already asked for other optics, or the whole sequence does.
    adopt = candidate.camera is not None or departs(result, sequence.camera, ADOPT_PROBABILITY)
    return replace(candidate, camera=result.camera if adopt else None, camera_fit=result)


def _fit_with_optics_uncertainty(fit: SequenceFit, pattern_fit: CameraAttitudeFit, camera_fit) -> SequenceFit:
    """The sequence fit with what its optics leave open added to its attitude's covariance
    (:func:`app.identification.candidates.optics_attitude_covariance`): the attitude's regression on the
    optics from the pattern's joint fit, the optics' covariance from the sequence's own calibration where
    there is one (``camera_fit``), else from the pattern's fit.

    The sequence fit holds the optics fixed: simulated sequences of the 20 deg camera 4 % off (80) had
    3 in 80 cross-boresight errors beyond 3 sigma about one axis, the optics fitted on the sequence
    within its own uncertainty.
    """
    if isinstance(camera_fit, Calibration):
        extra = optics_attitude_covariance(pattern_fit, camera_fit.parameters, camera_fit.covariance)
    else:
        extra = optics_attitude_covariance(pattern_fit)
    return replace(fit, covariance=fit.covariance + extra)


def fit_sequence(sequence: Sequence, extraction: Extraction, pattern: Pattern, candidate: Candidate,
                 sky: Sky) -> SequenceFit | None:
    """Per-snapshot attitudes from the candidate's identified tracks, then the constant-rate fit.

    Each snapshot uses the sightings of the tracks the candidate matched to
    stars, through the candidate's camera (the declared one, or the optics
    fitted with its attitude: one camera for every snapshot), against the
    stars' apparent places.
    """
    camera = candidate.camera or sequence.camera
    t_ref = sequence.snapshots[extraction.reference].time
    star_of_track = {m.track: m.hip for m in candidate.matches if m.track is not None}
    if len(star_of_track) < 2:
        return None
    sightings = identified_sightings(sequence, extraction, star_of_track, sky)
    sigma = max(sighting_noise_px(extraction), 0.05) * camera.pixel_scale_rad
    snaps = []
    if sightings:
        width = max(len(s.xy) for s in sightings)
        xy = np.zeros((len(sightings), width, 2))
        stars = np.tile([0.0, 0.0, 1.0], (len(sightings), width, 1))
        sigmas = np.full((len(sightings), width), np.inf)
        for k, s in enumerate(sightings):
            n = len(s.xy)
            xy[k, :n], stars[k, :n], sigmas[k, :n] = s.xy, s.star_vectors, sigma
        body = camera.pixels_to_vectors(xy.reshape(-1, 2)).reshape(len(sightings), width, 3)
        snaps = [sa for sa in wahba_per_snapshot(body, stars, sigmas, positions=[s.position for s in sightings],
                                                 dt_s=[s.dt_s for s in sightings]) if sa is not None]
    dt = np.array([(s.time - t_ref).total_seconds() for s in sequence.snapshots])
    return fit_constant_rate(snaps, candidate.rotation_matrix, rate_from_motion(extraction.motion, dt))
