"""Lost-in-space identification: pattern -> ranked, distinct, refined attitudes.

The pipeline is the seed's (004) with the improvements issue 3 asks for:
hypotheses from the bright-pair index (:mod:`.hypotheses`), each checked by
mapping the whole pattern onto the sky; then the best ones are refined by
least squares over all their matched stars, merged when they are the same
attitude found from different edges, and scored with a false-match
probability (:mod:`.verify`).
"""

from __future__ import annotations

import time as _time
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Callable
from datetime import datetime

import numpy as np

from app.attitude import angle_between, rotation_angles_between, wahba_covariance
from app.attitude.wahba import cross_boresight_and_roll_sigma
from app.camera import Camera
from app.catalogue import Catalogue, load_catalogue, star_names
from app.identification.hypotheses import bright_pair_hypotheses, ordered_pattern_edges
from app.identification.triangle_features import tf_batches
from app.identification.result import (AMBIGUOUS, IDENTIFIED, NO_MATCH, Candidate, PlanetMatch,
                                       Solution, StarMatch)
from app.identification.verify import StarField, check_hypotheses, false_match_probability, refine
from app.index import BrightPairIndex, load_index


@dataclass(frozen=True)
class SearchOptions:
    """Tunable parameters of a search, with the reasoning for each default.

    FUSE's star identification rules (seed 001, Table 3) map onto these:
    ``min_pair_ang`` -> :attr:`min_pair_separation_px`, ``max_pair_ang`` -> the
    index's longest edge, ``pair_ang_tol`` -> :attr:`edge_tolerance_px`,
    ``addl_mtch_tol`` -> :attr:`match_tolerance_px`, ``max_roll`` ->
    :attr:`max_roll_change_deg` (tracking from a prior), ``min_mch`` ->
    :attr:`min_matches`, ``des_mch`` -> :attr:`early_stop_matches`, and the
    time-out -> :attr:`timeout_s`.
    """

    #: Edge-length window: this many pixels of systematic error (centroiding,
    #: distortion) plus 4 sigma of the two points' random error.
    edge_tolerance_px: float = 1.0
    #: Pattern points closer than this never form an edge (no usable direction;
    #: maybe one star reported twice).
    min_pair_separation_px: float = 2.0
    #: A pattern point matches a star within max(this, 5 sigma) pixels.
    match_tolerance_px: float = 1.5
    #: Fewest matched stars for a candidate to be reported (FUSE asks 4; with
    #: the false-match probability judging significance, 3 may be shown).
    min_matches: int = 3
    #: Tracking: a solution whose roll differs from the prior's by more than
    #: this is not accepted as "identified".
    max_roll_change_deg: float = 5.0
    #: Stars down to the camera's limiting magnitude plus this margin can be
    #: in the pattern (brightness is unreliable and detection is noisy).
    mag_margin: float = 0.75
    #: Use at most this many pattern points, the brightest.
    max_points: int = 16
    #: Distinct candidates returned for the operator to step through (the
    #: seed's Next/Prev: past the first few, alternatives are chance fits).
    max_candidates: int = 6
    #: Hypotheses refined (in order of promise) to find those candidates.
    max_refinements: int = 16
    #: Status "identified" needs a best false-match probability at most this ...
    identified_probability: float = 1e-6
    #: ... and no rival: another distinct candidate at or below this
    #: probability, with an RMS residual within this factor of the best's, and
    #: at most this many times as likely to be chance as the best (the odds
    #: of the two explanations: a 15-star match at 1e-60 is not put in doubt
    #: by a 3-star coincidence at 1e-4, a 4-star match at 1e-8 is).
    rival_probability: float = 1e-3
    rival_rms_factor: float = 3.0
    rival_odds: float = 1e6
    #: No candidate at or below this false-match probability: "no_match".
    no_match_probability: float = 0.01
    #: Stop generating hypotheses once a refined hypothesis matches this many
    #: points (or all of them) and this fraction of them, and at least this
    #: many edges were tried.  The fraction matters in dense fields: a slightly
    #: wrong attitude can catch 6 of 30 points, the right one catches nearly all.
    early_stop_matches: int = 6
    early_stop_fraction: float = 0.5
    early_stop_edges: int = 1
    #: Hypotheses refined right after each batch of edges.
    refine_per_batch: int = 3
    #: Wall-clock budget of one search, seconds.
    timeout_s: float = 5.0
    #: Planets are labelled when an unmatched point lies within this many pixels.
    planet_tolerance_px: float = 3.0


class Sky:
    """The catalogue and the bright-pair index, loaded once (the identification context).

    Apparent star fields are cached per hour of observation time: the
    aberration changes by < 0.02 arcsec in an hour.
    """

    def __init__(self, index: BrightPairIndex | None = None, catalogue: Catalogue | None = None):
        self.index = index or load_index()
        cat = (catalogue or load_catalogue()).brighter_than(self.index.mag_limit)
        if len(cat) != self.index.n_stars or not np.array_equal(cat.hip, self.index.hip):
            raise ValueError("the bright-pair index was built from another catalogue")
        self.catalogue = cat
        self.names = star_names()
        self._fields: OrderedDict[tuple, StarField] = OrderedDict()
        self._apparent: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._row_of_hip = self.catalogue.index_of_hip()

    def star_mask(self, mag_limit: float) -> np.ndarray:
        return self.index.mag <= mag_limit

    def apparent_vectors(self, t: datetime, velocity_km_s=None) -> np.ndarray:
        """Apparent places of every catalogue star in the index, for the hour of ``t``."""
        key = (t.replace(minute=0, second=0, microsecond=0),
               None if velocity_km_s is None else tuple(np.round(velocity_km_s, 3)))
        if key not in self._apparent:
            self._apparent[key] = self.catalogue.apparent_vectors(key[0], velocity_km_s)
            while len(self._apparent) > 32:
                self._apparent.popitem(last=False)
        return self._apparent[key]

    def field(self, t: datetime, mag_limit: float, velocity_km_s=None) -> StarField:
        """The stars down to ``mag_limit`` (a prefix: stars are sorted brightest first) with a KD-tree."""
        n = int(self.star_mask(mag_limit).sum())
        key = (t.replace(minute=0, second=0, microsecond=0), n,
               None if velocity_km_s is None else tuple(np.round(velocity_km_s, 3)))
        if key not in self._fields:
            vectors = self.apparent_vectors(t, velocity_km_s)[:n]
            self._fields[key] = StarField.from_vectors(vectors, np.arange(n))
            while len(self._fields) > 32:
                self._fields.popitem(last=False)
        return self._fields[key]

    def apparent_vectors_of(self, hips, t: datetime, velocity_km_s=None) -> np.ndarray:
        """Apparent places (unit vectors) of the stars with these HIP numbers at ``t``."""
        rows = np.array([self._row_of_hip[int(h)] for h in hips], dtype=int)
        return self.apparent_vectors(t, velocity_km_s)[rows]

    def name(self, row: int) -> str | None:
        entry = self.names.get(int(self.index.hip[row]))
        return entry[0] if entry else None


@dataclass(frozen=True, eq=False)
class PreparedPattern:
    """A pattern ready for any hypothesis method: the brightest points, their
    noise, tolerances and the star field they are checked against."""

    keep: np.ndarray  # rows of the original pattern used
    vectors: np.ndarray
    xy: np.ndarray
    sigma_px: np.ndarray
    match_tol: np.ndarray  # (m,) final match tolerance of each point, radians
    weights: np.ndarray  # (m,) Wahba weights 1 / sigma^2
    camera: Camera
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
    sigma_px = np.maximum(np.nan_to_num(np.asarray(pattern.sigma_px, float)[keep], nan=0.5), 0.05)
    scale = camera.pixel_scale_rad
    mag_limit = min(camera.limiting_magnitude + options.mag_margin, sky.index.mag_limit)
    return PreparedPattern(
        keep=keep, vectors=pattern.vectors[keep], xy=pattern.xy[keep], sigma_px=sigma_px,
        match_tol=np.maximum(options.match_tolerance_px, 5 * sigma_px) * scale,
        weights=1.0 / (sigma_px * scale) ** 2, camera=camera,
        field=sky.field(t, mag_limit, velocity_km_s), star_mask=sky.star_mask(mag_limit), scale=scale)


def bright_pair_batches(p: PreparedPattern, sky: Sky, options: SearchOptions):
    """Hypotheses from the bright-pair index, edge batches of growing size (see :mod:`.hypotheses`)."""
    edges = ordered_pattern_edges(p.xy, p.camera, options.min_pair_separation_px)
    if not edges:
        return
    v = p.vectors
    first, second = np.array(edges).T
    edge_sigma_px = np.hypot(p.sigma_px[first], p.sigma_px[second])
    # Aberration differs across the field by up to ~1e-4 of an edge's length.
    edge_len = angle_between(v[first], v[second])
    edge_tol = (options.edge_tolerance_px + 4 * edge_sigma_px) * p.scale + 1.1e-4 * edge_len
    # A rotation from one edge errs at distance D from its first point by ~tol * D / L.
    reach = np.arccos(np.clip(v @ v.T, -1, 1)).max(axis=1)[first]
    check_tol = np.minimum(np.max(p.match_tol) + edge_tol * np.maximum(1.0, reach / np.maximum(edge_len, 1e-9)),
                           10 * p.scale)
    e, batch = 0, 1
    while e < len(edges):
        stop = min(len(edges), e + batch)
        hyp = bright_pair_hypotheses(v, edges[e:stop], edge_tol[e:stop], sky.index, p.star_mask)
        yield hyp, check_tol[e + hyp.edge_number], stop
        e, batch = stop, batch * 2


#: Hypothesis generators by method name: each yields (Hypotheses, check
#: tolerance per hypothesis, pattern edges/features used so far).
HYPOTHESIS_METHODS = {"bright_pair": bright_pair_batches, "tf": tf_batches}


def identify(pattern, camera: Camera, t: datetime, sky: Sky, *, velocity_km_s=None,
             options: SearchOptions = SearchOptions(),
             planets: Callable[[], dict[str, np.ndarray]] | None = None,
             method: str = "bright_pair") -> Solution:
    """Identify a pattern seen by ``camera`` at UTC ``t``.

    ``pattern`` has ``vectors`` (m, 3) camera-frame unit vectors, ``xy``
    (m, 2) pixels, ``sigma_px`` (m,), ``brightness`` (m,) and ``track_ids``
    (m,) (-1 for hand-picked points) - an :class:`app.extraction.Pattern`.
    ``planets()`` returns planet names -> apparent unit vectors at ``t``; it is
    called only when a credible candidate leaves a point unmatched (an
    ephemeris evaluation costs tens of milliseconds);
    ``method`` names a generator in :data:`HYPOTHESIS_METHODS`.
    """
    started = _time.perf_counter()
    if method not in HYPOTHESIS_METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(HYPOTHESIS_METHODS)}")
    m_all = len(pattern.vectors)
    if m_all < 3:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=_time.perf_counter() - started,
                        notes=(f"the pattern has {m_all} point(s); at least 3 are needed",))
    p = prepare_pattern(pattern, camera, t, sky, velocity_km_s, options)
    vectors, m, scale, field = p.vectors, p.m, p.scale, p.field
    match_tol, weights = p.match_tol, p.weights

    merge_angle = 20 * scale
    found: list[dict] = []  # distinct refined hypotheses
    n_refined = 0

    def nearest_found(R: np.ndarray, key: str) -> tuple[dict | None, float]:
        """The found candidate whose rotation ``key`` is closest to R, and that angle."""
        if not found:
            return None, np.inf
        angles = rotation_angles_between(np.stack([c[key] for c in found]), R)
        k = int(np.argmin(angles))
        return found[k], float(angles[k])

    def consider(R0, edge, pair, tol) -> None:
        """Refine one hypothesis unless it repeats a distinct one already found.

        A hypothesis repeats a candidate when it starts within ``merge_angle``
        of the hypothesis that candidate came from, or when its refinement
        ends within ``merge_angle`` of the candidate's; then the better of
        the two refinements (more matches, then the smaller deviation)
        stays: in a dense field a first edge can settle on a slightly wrong
        attitude that catches a few stars, and a later edge finds the one
        that catches them all.
        """
        nonlocal n_refined
        same, angle = nearest_found(R0, "R0")
        if angle >= merge_angle:
            n_refined += 1
            r = refine(R0, vectors, weights, field, match_tol, tol)
            same, angle = nearest_found(r.rotation, "rotation")
            if angle >= merge_angle:
                found.append({"R0": R0, "rotation": r.rotation, "refined": r, "edge": edge, "pair": pair,
                              "merged": 1, "tol": tol})
                return
            old = same["refined"]
            if (r.n_matched, -float(np.sum(r.nearest_rad))) > (old.n_matched, -float(np.sum(old.nearest_rad))):
                same.update(R0=R0, rotation=r.rotation, refined=r, edge=edge, pair=pair, tol=tol)
        same["merged"] += 1

    # Hypotheses come in batches; after each, the most promising new ones are
    # refined, and the search stops once one explains most of the pattern
    # (for bright pairs usually after the first sure edges).
    parts: list[tuple] = []
    n_tried, used = 0, 0
    for hyp, tol, used in HYPOTHESIS_METHODS[method](p, sky, options):
        if len(hyp):
            n_match, dev = check_hypotheses(hyp.rotations, vectors, field, tol)
            parts.append((hyp.rotations, hyp.pattern_edge, hyp.catalogue_pair, n_match, dev, tol))
            n_tried += len(hyp)
            for h in np.lexsort((dev, -n_match))[:options.refine_per_batch]:
                if n_match[h] >= 3:
                    consider(hyp.rotations[h], hyp.pattern_edge[h], hyp.catalogue_pair[h], float(tol[h]))
        best = max((c["refined"].n_matched for c in found), default=0)
        if (best >= min(m, options.early_stop_matches) and best >= options.early_stop_fraction * m
                and used >= options.early_stop_edges):
            break
        if _time.perf_counter() - started > options.timeout_s:
            break
    if not parts:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=_time.perf_counter() - started,
                        notes=(f"no {method} hypothesis: no catalogue feature fits the pattern",))
    # More distinct alternatives for the operator's Next/Prev, in order of promise.
    rot, pe, cp, n_match, dev, hyp_tol = (np.concatenate(x) for x in zip(*parts))
    for h in np.lexsort((dev, -n_match)):
        credible = sum(c["refined"].n_matched >= max(3, options.min_matches) for c in found)
        if (n_match[h] < max(3, options.min_matches) or credible >= options.max_candidates
                or n_refined >= options.max_refinements):
            break
        if _time.perf_counter() - started > options.timeout_s:
            break
        consider(rot[h], pe[h], cp[h], float(hyp_tol[h]))

    candidates = [_candidate(c, p, pattern, sky, n_tried, options, planets) for c in found
                  if c["refined"].n_matched >= max(3, options.min_matches)]
    candidates.sort(key=lambda c: (c.false_match_probability, -c.n_matched, c.deviation_arcsec))
    candidates = candidates[:options.max_candidates]
    candidates.sort(key=lambda c: (-c.n_matched, c.false_match_probability, c.deviation_arcsec))
    candidates = [replace(c, rank=i + 1) for i, c in enumerate(candidates)]
    status = classify(candidates, options)
    return Solution(status=status, candidates=tuple(candidates), elapsed_s=_time.perf_counter() - started,
                    notes=(f"{n_tried} {method} hypotheses from {used} pattern features",))


def classify(candidates: list[Candidate], options: SearchOptions) -> str:
    """identified / ambiguous / no_match from the ranked candidates (see SearchOptions).

    A rival blocks "identified" when chance does not explain it either
    (probability at most ``rival_probability``), its residuals are of the
    same order as the best candidate's (RMS within ``rival_rms_factor``: a
    true attitude fits its stars to the measurement noise, so a rival fitting
    several times worse is not a competing explanation), and the odds
    between the two are not overwhelming (see :func:`is_rival`).
    """
    if not candidates or min(c.false_match_probability for c in candidates) > options.no_match_probability:
        return NO_MATCH
    best = candidates[0]
    rivals = [c for c in candidates[1:] if is_rival(c, best, options)]
    if best.false_match_probability <= options.identified_probability and not rivals:
        return IDENTIFIED
    return AMBIGUOUS


def is_rival(candidate: Candidate, best: Candidate, options: SearchOptions) -> bool:
    """Whether ``candidate`` competes with ``best`` as an explanation of the pattern.

    If the best were the chance fit, the other being true, chance would have
    produced it with probability ``P_best``; the other way round, ``P_other``.
    Their ratio is the odds between the two explanations; beyond
    ``rival_odds`` the weaker one is no rival, however unlikely by chance alone.
    """
    p, p_best = candidate.false_match_probability, best.false_match_probability
    return (p <= options.rival_probability and candidate.rms_arcsec <= options.rival_rms_factor * best.rms_arcsec
            and p <= options.rival_odds * max(p_best, 1e-300))


def _candidate(c, p: PreparedPattern, pattern, sky: Sky, n_tried, options: SearchOptions, planets) -> Candidate:
    vectors, keep, field, scale, m = p.vectors, p.keep, p.field, p.scale, p.m
    r = c["refined"]
    R = r.rotation
    matched = np.flatnonzero(r.star_of_point >= 0)
    track_ids = np.asarray(pattern.track_ids)[keep]

    def track_of(i):
        t = int(track_ids[i])
        return t if t >= 0 else None

    matches = tuple(
        StarMatch(pattern_index=int(keep[i]), track=track_of(i), hip=int(sky.index.hip[field.rows[r.star_of_point[i]]]),
                  name=sky.name(int(field.rows[r.star_of_point[i]])),
                  residual_arcsec=float(np.degrees(r.residual_rad[i]) * 3600))
        for i in matched)
    resid = r.residual_rad[matched]
    fmp = false_match_probability(m, len(matched), c["tol"], field.density_per_sr, n_tried,
                                  float(np.sum(resid ** 2)))
    planet_matches = []
    unmatched = np.flatnonzero(r.star_of_point < 0)
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
    cov = wahba_covariance(vectors[matched], sigma_rad) * max(1.0, reduced_chi2(resid, sigma_rad))
    sigma_cross, sigma_roll = cross_boresight_and_roll_sigma(cov)
    return Candidate(
        rank=0, rotation_matrix=R,
        deviation_arcsec=float(np.degrees(deviation) * 3600),
        deviation_px_per_point=float(deviation / m / scale),
        rms_arcsec=float(np.degrees(np.sqrt(np.mean(resid ** 2))) * 3600) if len(resid) else float("nan"),
        false_match_probability=fmp, matches=matches, planets=tuple(planet_matches),
        generating_edge=(int(keep[c["edge"][0]]), int(keep[c["edge"][1]])),
        generating_pair_hip=(int(sky.index.hip[c["pair"][0]]), int(sky.index.hip[c["pair"][1]])),
        n_hypotheses_merged=c["merged"],
        sigma_cross_boresight_arcsec=float(np.degrees(sigma_cross) * 3600),
        sigma_roll_arcsec=float(np.degrees(sigma_roll) * 3600))


def reduced_chi2(residual_rad: np.ndarray, sigma_rad: np.ndarray) -> float:
    """chi^2 per degree of freedom of a Wahba fit: 2 per star, 3 taken by the attitude."""
    dof = 2 * len(residual_rad) - 3
    return float(np.sum((residual_rad / sigma_rad) ** 2) / dof) if dof > 0 else 1.0
