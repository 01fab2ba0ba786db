"""Tracking mode: identification with a prior attitude (Liebe's predictional
estimate, PE; FUSE's "known tracking").

1. Predict: the catalogue stars the camera would see at the prior attitude
   (stars within the field plus the prior's uncertainty).
2. Match by least distance, robust to a prior that is off by up to a degree:
   every pairing of a pattern point with a predicted star proposes the same
   image offset; the offset most pairings agree on wins (a vote, so a false
   star or a missing one changes nothing), and its pairings seed the fit.
   Each offset's votes are the offsets within the agreement radius of it,
   counted with a KD-tree (:func:`count_agreeing`): a wide prior (10 deg)
   gives thousands of pairings, whose all-pairs distance matrix would take
   gigabytes.
3. Refine: Wahba over the matched pairs with outlier rejection, re-matching
   with a tolerance shrinking to the points' noise (the same routine as
   lost-in-space identification, :func:`app.identification.verify.refine`).

Two matched stars fix an attitude, so tracking works with a pattern of as few as two points; a
larger pattern must pass the false-match test as lost-in-space answers do.

A prior wider than :data:`VOTE_MAX_SIGMA_DEG` is no longer one image offset: a
roll error of a few degrees moves the points at the field's edge by offsets
that differ by more than the agreement radius, and chance pairings outvote
the true ones.  Then the pattern is identified lost in space
(:func:`app.identification.engine.identify`) and the candidates the prior
excludes (the same test of boresight and roll) are left out.
"""

from __future__ import annotations

import time as _time
from dataclasses import replace
from datetime import datetime

import numpy as np
from scipy.spatial import cKDTree

from app.attitude import angle_between
from app.camera import Camera
from app.identification.candidates import build_candidate, prepare_pattern
from app.identification.engine import classify, identify
from app.identification.options import SearchOptions
from app.identification.result import AMBIGUOUS, IDENTIFIED, NO_MATCH, Solution
from app.identification.sky import Sky
from app.identification.verify import chord, refine


#: The widest prior (1-sigma, degrees) tracked by the vote.  600 single snapshots (the three cameras) tracked
#: from priors drawn uniformly within sigma of the truth: every one right at 1 and 2 deg, 95 % at 3, 71 % at
#: 5 and 12 % at 10 (``python -m app bench --suite sequence``'s tracking frames); lost in space, filtered by
#: the prior, is right whatever the width.
VOTE_MAX_SIGMA_DEG = 2.0


def count_agreeing(offsets: np.ndarray, radius: float) -> np.ndarray:
    """For each of ``offsets`` (K, 2), how many of ``offsets`` (itself and duplicates included) lie within
    ``radius`` (distance <= radius) of it.

    Exactly ``(np.linalg.norm(offsets[:, None] - offsets[None], axis=2) <= radius).sum(axis=1)``, in memory
    O(K) rather than the K x K x 2 array of that expression.  The KD-tree compares squared distances, which
    may round otherwise than that norm within an ulp of ``radius``; so it counts just inside and just outside
    ``radius``, and the offsets whose two counts differ are counted again with the norm.
    """
    offsets = np.asarray(offsets, dtype=float)
    tree = cKDTree(offsets)
    inside = np.asarray(tree.query_ball_point(offsets, radius * (1 - 1e-9), return_length=True), dtype=np.intp)
    outside = np.asarray(tree.query_ball_point(offsets, radius * (1 + 1e-9), return_length=True), dtype=np.intp)
    for i in np.flatnonzero(inside != outside):
        inside[i] = np.count_nonzero(np.linalg.norm(offsets[i] - offsets, axis=1) <= radius)
    return inside


def identify_near_prior(pattern, camera: Camera, t: datetime, sky: Sky, prior_rotation: np.ndarray, *,
          prior_sigma_deg: float = 1.0, velocity_km_s=None,
          options: SearchOptions = SearchOptions()) -> Solution:
    """Identify ``pattern`` near ``prior_rotation`` (ICRS -> camera), 1-sigma ``prior_sigma_deg``."""
    started = _time.perf_counter()
    if len(pattern.vectors) < 2:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=_time.perf_counter() - started,
                        notes=(f"the pattern has {len(pattern.vectors)} point(s); tracking needs 2",))
    prior = np.asarray(prior_rotation, dtype=float)
    if prior_sigma_deg > VOTE_MAX_SIGMA_DEG and len(pattern.vectors) >= 3:
        return _lost_in_space_near(pattern, camera, t, sky, prior, prior_sigma_deg, velocity_km_s, options, started)
    p = prepare_pattern(pattern, camera, t, sky, velocity_km_s, options)
    search = np.radians(3.0 * prior_sigma_deg)  # how far a star can be from its prediction

    # 1. Predicted stars: within the field's half-diagonal plus the search radius of the boresight.
    reach = camera.diagonal_fov_rad / 2 + search
    rows = np.array(p.field.tree.query_ball_point(prior[2], float(chord(min(reach, np.pi)))), dtype=int)
    if len(rows) == 0:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=_time.perf_counter() - started,
                        notes=("no catalogue star near the prior attitude",))
    predicted = p.field.vectors[rows] @ prior.T  # camera frame at the prior attitude

    # 2. Vote for the offset: tangent-plane differences point -> star, in radians.
    offsets = (predicted[None, :, :2] / predicted[None, :, 2:3]) - (p.vectors[:, None, :2] / p.vectors[:, None, 2:3])
    near = np.linalg.norm(offsets, axis=2) <= search
    cand = offsets[near]  # (K, 2)
    if len(cand) == 0:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=_time.perf_counter() - started,
                        notes=("no catalogue star within the prior's uncertainty of any pattern point",))
    # Agreement radius: the points' noise plus what a roll error of the prior
    # does across the field.
    agree = float(np.max(p.match_tol)) + np.radians(prior_sigma_deg) * camera.diagonal_fov_rad / 2
    votes = count_agreeing(cand, agree)
    # Ties (common with two or three stars) go to the offset the prior finds likelier.
    score = votes - 0.5 * (np.linalg.norm(cand, axis=1) / search) ** 2
    best_offset = cand[np.argmax(score)]

    # Start the fit from the prior moved so the predicted stars shift onto the points.
    # Rotating by +a about camera y adds a to x/z; by +a about x subtracts a from y/z.
    from scipy.spatial.transform import Rotation  # here, not at start-up (lost in space never needs it)

    nudge = Rotation.from_rotvec([best_offset[1], -best_offset[0], 0.0]).as_matrix()
    start = nudge @ prior
    r = refine(start, p.vectors, p.weights, p.field, p.match_tol, agree)
    matched = np.flatnonzero(r.star_of_point >= 0)
    if len(matched) < 2:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=_time.perf_counter() - started,
                        notes=("fewer than two pattern points match stars near the prior",))
    # Each voted pairing was a hypothesis: they all enter the false-match probability.
    candidate = replace(build_candidate(r, p, sky, tol=agree, n_hypotheses=len(cand), options=options), rank=1)
    fmp = candidate.false_match_probability
    # With a prior the question is only "which nearby star", so a pattern of two points that both match
    # in agreement with the prior is identified; any other must pass the usual test (two matches among
    # ten points are what a wide prior finds by chance: false-match probability 1).
    moved = float(angle_between(r.rotation[2], prior[2]))
    if _agrees_with_prior(r.rotation, prior, prior_sigma_deg, options) and (
            len(matched) == p.m == 2 or fmp <= options.identified_probability):
        status = IDENTIFIED
    else:
        status = AMBIGUOUS
    return Solution(status=status, candidates=(candidate,), elapsed_s=_time.perf_counter() - started,
                    notes=(f"tracking from a prior {prior_sigma_deg:g} deg; moved {np.degrees(moved):.3f} deg",))


def _agrees_with_prior(rotation: np.ndarray, prior: np.ndarray, prior_sigma_deg: float,
                       options: SearchOptions) -> bool:
    """Whether an attitude lies within 3 sigma of the prior: its boresight, and (FUSE's roll check) its roll
    about the boresight."""
    moved = float(angle_between(rotation[2], prior[2]))
    turn = rotation @ prior.T
    roll_change = abs(float(np.degrees(np.arctan2(turn[0, 1] - turn[1, 0], turn[0, 0] + turn[1, 1]))))
    return (moved <= np.radians(3.0 * prior_sigma_deg)
            and roll_change <= max(options.max_roll_change_deg, 3 * prior_sigma_deg))


def _lost_in_space_near(pattern, camera: Camera, t: datetime, sky: Sky, prior: np.ndarray, prior_sigma_deg: float,
                        velocity_km_s, options: SearchOptions, started: float) -> Solution:
    """A wide prior: the lost-in-space candidates within 3 sigma of it, ranked and classified among
    themselves (the search's hypotheses, over the whole sky, stay in their false-match probabilities)."""
    found = identify(pattern, camera, t, sky, velocity_km_s=velocity_km_s, options=options)
    kept = [replace(c, rank=k + 1) for k, c in enumerate(
        c for c in found.candidates if _agrees_with_prior(c.rotation_matrix, prior, prior_sigma_deg, options))]
    note = (f"tracking from a prior {prior_sigma_deg:g} deg wide, wider than the {VOTE_MAX_SIGMA_DEG:g} deg a vote "
            f"for one image offset holds: searched lost in space, {len(kept)} of {len(found.candidates)} "
            "candidates within 3 sigma of the prior kept")
    return Solution(status=classify(kept, options), candidates=tuple(kept),
                    elapsed_s=_time.perf_counter() - started, notes=(*found.notes, note),
                    focal_length_contradiction=found.focal_length_contradiction)
