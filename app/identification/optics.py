"""Identification with an imperfect camera model: a search over the focal length, then the optics fitted
with the attitude.

Why.  A pattern point's direction is ``camera.pixels_to_vectors(xy)``.  When
the true focal length is ``f (1 + e)`` and the declared one ``f``, every
angle in the pattern is off by about the fraction ``e``: an edge of ``L``
pixels by ``e L`` pixels, beyond the edge window of the bright-pair lookup
(a few pixels) once ``e L`` exceeds it, so the true attitude is never
hypothesised.  Undeclared radial distortion ``k1`` does the same, growing
with the distance from the centre (``f k1 r^3``).

How.

1. :func:`focal_lengths_to_try`: the declared focal length first, then
   focal lengths stepping outwards to both sides up to the declared
   tolerance (``camera.focal_tolerance``, 5 % when undeclared).  The step is
   what the lookup tolerates: a residual scale error ``d`` shifts an edge of
   ``L`` px by ``d L`` and a point at distance ``D`` from the generating
   edge's first point by ``d D``; half a step must stay within the edge
   window of the pattern's first edges and within a few match tolerances
   across the pattern, so the step is ``2 w / L_max`` with ``w`` a few pixels
   (:data:`SCALE_WINDOW_PX`), clipped to [:data:`MIN_STEP`, :data:`MAX_STEP`].
   The engine searches the first features of every focal length (bright
   pairs: all at once, each catalogue pair at the focal length nearest its
   length, :mod:`app.identification.focal_scan`; other methods: one step
   after another) and stops at the first that identifies the pattern.
2. :func:`refine_optics`: a candidate's matched stars fix the attitude and
   the optics together (:func:`app.camera_fit.fit_attitude_and_camera`: the
   focal length from 3 stars, k1 too from 6, with weak priors from the
   declaration); the pattern is mapped again through the fitted camera,
   re-matched and refitted, until the matches stop changing.
3. Honesty.  Every focal length tried adds its hypotheses to the count that
   the false-match probability multiplies (the look-elsewhere effect), each
   fitted optical parameter takes a degree of freedom from the fit's
   tightness test, and a candidate whose fitted focal length falls outside
   the declared tolerance (by more than 3 sigma) is not credible: a wrong
   camera model must never turn a chance fit into ``identified``.
   A fitted camera replaces the declared one only when the data ask for it
   (the declared optics rejected at :data:`ADOPT_PROBABILITY` by a
   chi-square test of the fitted parameters, or more stars matched): an
   exactly known camera keeps its answers unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import chdtri  # inverse chi-square survival function

from app.camera import Camera
from app.camera_fit import CameraAttitudeFit, default_priors, fit_attitude_and_camera, parameters_for
from app.identification.candidates import PreparedPattern
from app.identification.verify import Refined, StarField, refine

#: Half the scale step, in pixels of pattern geometry (see the module doc).
SCALE_WINDOW_PX = 4.0
#: Bounds of the focal-length step (fractions).
MIN_STEP, MAX_STEP = 0.004, 0.02
#: Fitted optics replace the declared ones when the declared ones are this unlikely given the fit (a
#: chi-square test of the fitted parameters jointly, about 5 sigma) or the fitted optics match this many
#: more stars: an exactly known camera keeps its answers.
ADOPT_PROBABILITY = 1e-6
ADOPT_MORE_MATCHES = 2
#: A sequence's optics are fitted over all its snapshots when the pattern's fit already hints at
#: optics other than the declared ones at this level (or adopted them): cheap insurance, a few ms.
HINT_PROBABILITY = 0.01
#: Rounds of fit -> re-match in :func:`refine_optics`.
OPTICS_ROUNDS = 3


def focal_lengths_to_try(camera: Camera, xy: np.ndarray) -> list[float]:
    """The declared focal length, then outward steps to both sides within the declared tolerance."""
    f = camera.focal_length_px
    tolerance = camera.focal_tolerance
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if tolerance <= 0 or len(xy) < 3:
        return [f]
    extent = float(np.max(np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=2)))
    step = min(MAX_STEP, max(MIN_STEP, 2 * SCALE_WINDOW_PX / max(extent, 1.0)))
    n = int(math.ceil(tolerance / step - 1e-9))
    out = [f]
    for k in range(1, n + 1):
        e = min(k * step, tolerance)
        out += [f * (1 + e), f * (1 - e)]
    return out


def prepared_with_camera(p: PreparedPattern, camera: Camera) -> PreparedPattern:
    """The prepared pattern seen through another camera: its directions and angular tolerances change."""
    scale = camera.pixel_scale_rad
    factor = scale / p.scale
    return replace(p, vectors=camera.pixels_to_vectors(p.xy), camera=camera, scale=scale,
                   match_tol=p.match_tol * factor, weights=p.weights / factor ** 2)


@dataclass(frozen=True, eq=False)
class OpticsFit:
    """What :func:`refine_optics` found: the refinement through the fitted camera and the fit itself."""

    refined: Refined
    prepared: PreparedPattern  # through ``fit.camera``
    fit: CameraAttitudeFit
    within_tolerance: bool  # the fitted focal length agrees with the declaration's tolerance
    significant: bool  # the data ask for the fitted optics (see ADOPT_SIGMAS)


def refine_optics(r: Refined, p: PreparedPattern, declared: Camera, field: StarField) -> OpticsFit | None:
    """Fit the optics with the attitude on ``r``'s matched stars, re-match through them, repeat.

    None when the matched stars are too few (fewer than 3) or cannot
    separate the parameters.
    """
    fit = None
    start_matches = r.n_matched
    for _ in range(OPTICS_ROUNDS):
        ok = np.flatnonzero(r.star_of_point >= 0)
        names = parameters_for(len(ok))
        if not names:
            break
        try:
            trial = fit_attitude_and_camera(p.xy[ok], field.vectors[r.star_of_point[ok]], r.rotation, p.camera,
                                            float(np.median(p.sigma_px[ok])), fit=names,
                                            priors=default_priors(declared, names))
        except ValueError:
            break
        q = prepared_with_camera(p, trial.camera)
        # Start wide: points the old optics put too far from their stars may now match.
        again = refine(trial.rotation, q.vectors, q.weights, field, q.match_tol, 3 * float(np.max(q.match_tol)))
        if again.n_matched < r.n_matched:
            # The fitted optics lose stars: keep the matches made without them (the fit stays on record).
            fit = fit or trial
            break
        previous = r.star_of_point
        fit, r, p = trial, again, q
        if np.array_equal(r.star_of_point, previous):
            break
    if fit is None:
        return None
    sigma_f = fit.sigma.get("focal_length_px", math.inf)
    offset_f = abs(fit.camera.focal_length_px - declared.focal_length_px)
    within = offset_f <= declared.focal_tolerance * declared.focal_length_px + 3 * sigma_f
    consistent = p.camera is fit.camera  # r and p are through the fitted camera
    significant = consistent and (departs(fit, declared, ADOPT_PROBABILITY)
                                  or r.n_matched >= start_matches + ADOPT_MORE_MATCHES)
    return OpticsFit(refined=r, prepared=p, fit=fit, within_tolerance=bool(within), significant=bool(significant))


def departs(fit, declared: Camera, probability: float) -> bool:
    """Whether the declared optics are rejected at ``probability`` by the fitted ones (a chi-square test).

    ``fit`` is a :class:`app.camera_fit.CameraAttitudeFit` (its covariance
    starts with the 3 rotation angles) or a :class:`app.camera_fit.Calibration`
    (optics only).  The parameters are correlated (the focal length and k1
    trade off over a narrow field), so they are judged together: the squared
    Mahalanobis distance of the fitted optics from the declared ones against
    the chi-square quantile with one degree of freedom per parameter.
    """
    names = fit.parameters
    fitted, stated = fit.camera.optics(), declared.optics()
    d = np.array([fitted[n] - stated[n] for n in names])
    covariance = fit.covariance[-len(names):, -len(names):]
    try:
        distance = float(d @ np.linalg.solve(covariance, d))
    except np.linalg.LinAlgError:
        return False
    return distance > chdtri(len(names), probability)
