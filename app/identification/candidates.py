"""From a refined attitude to a :class:`Candidate`: the one builder every identification method uses.

A pattern is first *prepared* (:func:`prepare_pattern`): its brightest
points, their noise, match tolerances and the star field they are checked
against.  Any method (bright pairs, triangle features, tracking from a prior)
ends with a refinement (:func:`app.identification.verify.refine`) that
:func:`build_candidate` turns into a scored candidate: matched stars, planets
explaining unmatched points, deviation, false-match probability and the
attitude's 1-sigma (Wahba covariance inflated by the reduced chi-square).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Callable

import numpy as np

from app.attitude import wahba_covariance
from app.attitude.wahba import cross_boresight_and_roll_sigma
from app.camera import Camera
from app.camera_fit import CameraAttitudeFit
from app.extraction import DEFAULT_SIGHTING_SIGMA_PX
from app.identification.options import SearchOptions
from app.identification.result import Candidate, PlanetMatch, StarMatch
from app.identification.sky import Sky
from app.identification.verify import (Refined, StarField, brightest_within, false_match_probability,
                                       local_density_per_sr)


@dataclass(frozen=True, eq=False)
class PreparedPattern:
    """A pattern ready for any hypothesis method: the brightest points, their
    noise, tolerances and the star field they are checked against."""

    keep: np.ndarray  # rows of the original pattern used
    track_ids: np.ndarray  # (m,) their track ids (-1: picked by hand)
    vectors: np.ndarray
    xy: np.ndarray
    sigma_px: np.ndarray
    match_tol: np.ndarray  # (m,) final match tolerance of each point, radians
    weights: np.ndarray  # (m,) Wahba weights 1 / sigma^2
    camera: Camera  # the camera the directions were computed with
    declared_camera: Camera  # the telemetry's camera (differs from ``camera`` at a searched focal length)
    field: StarField
    star_mask: np.ndarray  # index rows the camera can see
    scale: float  # radians per pixel

    @property
    def m(self) -> int:
        return len(self.vectors)


def prepare_pattern(pattern, camera: Camera, t: datetime, sky: Sky, velocity_km_s=None,
                    options: SearchOptions = SearchOptions()) -> PreparedPattern:
    # The brightest points only (faint sources are most often ghosts or missing stars).
    keep = np.argsort(-np.nan_to_num(pattern.brightness, nan=0.0), kind="stable")[:options.max_points]
    sigma_px = np.maximum(np.nan_to_num(np.asarray(pattern.sigma_px, float)[keep], nan=DEFAULT_SIGHTING_SIGMA_PX), 0.05)
    scale = camera.pixel_scale_rad
    mag_limit = sky.depth_for(camera, options.mag_margin)
    return PreparedPattern(
        keep=keep, track_ids=np.asarray(pattern.track_ids)[keep], vectors=pattern.vectors[keep], xy=pattern.xy[keep], sigma_px=sigma_px,
        match_tol=np.maximum(options.match_tolerance_px, 5 * sigma_px) * scale,
        weights=1.0 / (sigma_px * scale) ** 2, camera=camera, declared_camera=camera,
        field=sky.field(t, mag_limit, velocity_km_s), star_mask=sky.star_mask(mag_limit), scale=scale)


def build_candidate(r: Refined, p: PreparedPattern, sky: Sky, *, tol: float, n_hypotheses: int,
                    options: SearchOptions, generating_edge: tuple[int, int] | None = None,
                    generating_pair: tuple[int, int] | None = None, n_merged: int = 1,
                    planets: Callable[[], dict[str, np.ndarray]] | None = None, n_fitted: int = 0) -> Candidate:
    """The candidate of refinement ``r`` of prepared pattern ``p`` (rank 0: the caller ranks).

    ``tol`` is the match tolerance the hypothesis was checked with and
    ``n_hypotheses`` how many were tried: both enter the false-match
    probability (:func:`app.identification.verify.false_match_probability`).
    ``generating_edge`` (rows of ``p``) and ``generating_pair`` (index rows)
    name the hypothesis that found it.  ``planets()`` (names -> apparent unit
    vectors) is called only for a credible candidate that leaves points
    unmatched.  ``n_fitted`` optical parameters were fitted besides the
    attitude (each takes a degree of freedom from the fit's tightness test).
    """
    vectors, keep, field, scale, m = p.vectors, p.keep, p.field, p.scale, p.m
    R = r.rotation
    star_of_point, residual_rad = named_by_brightest(r.star_of_point, r.residual_rad, vectors @ R, field,
                                                     p.match_tol)
    matched = np.flatnonzero(star_of_point >= 0)

    def track_of(i):
        t = int(p.track_ids[i])
        return t if t >= 0 else None

    matches = tuple(
        StarMatch(pattern_index=int(keep[i]), track=track_of(i), hip=int(sky.index.hip[field.rows[star_of_point[i]]]),
                  name=sky.name(int(field.rows[star_of_point[i]])),
                  residual_arcsec=float(np.degrees(residual_rad[i]) * 3600))
        for i in matched)
    resid = residual_rad[matched]
    sum_sq = float(resid @ resid)
    density = local_density_per_sr(field, R[2], p.camera.corner_radius * scale)  # R[2]: the boresight in ICRS
    fmp = false_match_probability(m, len(matched), tol, density, n_hypotheses, sum_sq,
                                  n_fitted=n_fitted)
    planet_matches = []
    unmatched = np.flatnonzero(star_of_point < 0)
    if planets is not None and len(unmatched) and fmp <= options.rival_probability:
        sky_dirs = vectors[unmatched] @ R
        for name, pv in planets().items():
            ang = np.arccos(np.clip(sky_dirs @ pv, -1, 1))
            for k in np.flatnonzero(ang <= options.planet_tolerance_px * scale):
                i = unmatched[k]
                planet_matches.append(PlanetMatch(pattern_index=int(keep[i]), track=track_of(i), name=name,
                                                  residual_arcsec=float(np.degrees(ang[k]) * 3600)))
    deviation = float(np.sum(r.nearest_rad))
    sigma_rad = p.sigma_px[matched] * scale
    cov = wahba_covariance(vectors[matched], sigma_rad) * max(1.0, reduced_chi2(resid, sigma_rad, n_fitted))
    sigma_cross, sigma_roll = cross_boresight_and_roll_sigma(cov)
    return Candidate(
        rank=0, rotation_matrix=R,
        deviation_arcsec=float(np.degrees(deviation) * 3600),
        deviation_px_per_point=float(deviation / m / scale),
        rms_arcsec=math.degrees(math.sqrt(sum_sq / len(resid))) * 3600 if len(resid) else float("nan"),
        false_match_probability=fmp, matches=matches, planets=tuple(planet_matches),
        generating_edge=(-1, -1) if generating_edge is None else (int(keep[generating_edge[0]]),
                                                                   int(keep[generating_edge[1]])),
        generating_pair_hip=(-1, -1) if generating_pair is None else (int(sky.index.hip[generating_pair[0]]),
                                                                       int(sky.index.hip[generating_pair[1]])),
        n_hypotheses_merged=n_merged,
        sigma_cross_boresight_arcsec=float(np.degrees(sigma_cross) * 3600),
        sigma_roll_arcsec=float(np.degrees(sigma_roll) * 3600))


def with_optics_uncertainty(candidate: Candidate, fit: CameraAttitudeFit) -> Candidate:
    """``candidate`` with the optics ``fit`` (fitted with its attitude) as its ``camera_fit``, and its
    attitude's 1-sigma widened to the fit's where that is wider.

    The fit's is the attitude marginalised over the optics: the attitude
    block of the joint covariance over (attitude, optics), its information
    including the optics' priors (the declared tolerance), inflated by the
    fit's reduced chi-square when above 1.  The candidate's own (Wahba's)
    holds the optics fixed: a focal length off within its tolerance, too
    little to be adopted, still moves an off-centre pattern's attitude
    further than the centroid noise allows.  Simulated single snapshots of
    the 20 deg camera 2 % off (146 identified): the cross-boresight pulls'
    rms 0.97 with 1 beyond 3 sigma, 0.58 and none widened; exact and 4 %
    off (the fit adopted) they stay 0.5-0.6.
    """
    chi2_reduced = fit.chi2 / fit.dof if fit.dof > 0 else 1.0
    cross, roll = cross_boresight_and_roll_sigma(np.asarray(fit.covariance)[:3, :3] * max(1.0, chi2_reduced))
    cross_arcsec, roll_arcsec = math.degrees(cross) * 3600, math.degrees(roll) * 3600
    return replace(candidate, camera_fit=fit,
                   sigma_cross_boresight_arcsec=max(candidate.sigma_cross_boresight_arcsec, cross_arcsec),
                   sigma_roll_arcsec=max(candidate.sigma_roll_arcsec, roll_arcsec))


def optics_attitude_covariance(joint: CameraAttitudeFit, optics_names: tuple[str, ...] | None = None,
                                optics_covariance: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) rad^2: the part of an attitude's covariance its optics leave open, ``J C J^T``.

    ``J = S_ao S_oo^-1`` is the attitude's regression on the optics in the
    joint fit's covariance ``S`` (attitude ``a`` first, optics ``o``): how
    far the attitude moves with each optical parameter.  ``C`` is the
    optics' covariance that applies: ``optics_covariance`` over
    ``optics_names`` (a sequence's calibration, fitted on every snapshot;
    the parameters the joint fit did not fit are left out), else the joint
    fit's own ``S_oo`` (then ``J C J^T`` is the marginal covariance minus
    the one at fixed optics).  A sequence fit holds the optics fixed: this
    is what it adds (:func:`app.identification.solve_sequence`).
    """
    names = list(joint.covariance_names[3:])
    S = np.asarray(joint.covariance, dtype=float)
    try:
        J = np.linalg.solve(S[3:, 3:], S[3:, :3]).T  # S_oo symmetric: (S_oo^-1 S_oa)^T = S_ao S_oo^-1
    except np.linalg.LinAlgError:
        return np.zeros((3, 3))
    if optics_covariance is None:
        return J @ S[3:, 3:] @ J.T
    at = {name: k for k, name in enumerate(optics_names or ())}
    shared = [k for k, name in enumerate(names) if name in at]
    rows = [at[names[k]] for k in shared]
    C = np.asarray(optics_covariance, dtype=float)[np.ix_(rows, rows)]
    return J[:, shared] @ C @ J[:, shared].T


def named_by_brightest(star_of_point: np.ndarray, residual_rad: np.ndarray, directions: np.ndarray,
                       field: StarField, match_tol: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The refinement's star of each point (and its residual), or the brightest star within the point's
    match tolerance where that is another one no other point names (:func:`brightest_within`: the
    refinement takes the nearest, and a faint neighbour of the star seen took its name).  ``directions``:
    the points' directions on the sky (ICRS unit vectors) at the refined attitude."""
    stars, residuals = star_of_point.copy(), residual_rad.copy()
    matched = np.flatnonzero(stars >= 0)
    if not len(matched):
        return stars, residuals
    brightest = brightest_within(directions[matched], field, float(np.max(match_tol[matched])))
    named = set(stars[matched].tolist())
    for i, star in zip(matched.tolist(), brightest.tolist()):
        cosine = float(directions[i] @ field.vectors[star]) if star >= 0 else -1.0
        if star >= 0 and star not in named and np.arccos(min(cosine, 1.0)) <= match_tol[i]:
            named.discard(int(stars[i]))
            named.add(star)
            stars[i], residuals[i] = star, np.arccos(min(cosine, 1.0))
    return stars, residuals


def reduced_chi2(residual_rad: np.ndarray, sigma_rad: np.ndarray, n_fitted: int = 0) -> float:
    """chi^2 per degree of freedom of a Wahba fit: 2 per star, 3 taken by the attitude, ``n_fitted`` by the optics."""
    dof = 2 * len(residual_rad) - 3 - n_fitted
    return float(np.sum((residual_rad / sigma_rad) ** 2) / dof) if dof > 0 else 1.0
