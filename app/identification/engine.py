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
from dataclasses import replace
from datetime import datetime
from typing import Callable

import numpy as np

from app.attitude import rotation_angles_between
from app.camera import Camera
from app.identification.candidates import build_candidate, prepare_pattern
from app.identification.methods import METHODS
from app.identification.options import SearchOptions
from app.identification.result import AMBIGUOUS, IDENTIFIED, NO_MATCH, Candidate, Solution
from app.identification.sky import Sky
from app.identification.verify import check_hypotheses, refine


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
    ``method`` names a lost-in-space method of :data:`app.identification.methods.METHODS`.
    """
    started = _time.perf_counter()
    generator = METHODS[method].hypotheses if method in METHODS else None
    if generator is None:
        lost_in_space = [name for name, m in METHODS.items() if m.hypotheses is not None]
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(lost_in_space)}")
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
    for hyp, tol, used in generator(p, sky, options):
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

    candidates = [build_candidate(c["refined"], p, sky, tol=c["tol"], n_hypotheses=n_tried, options=options,
                                  generating_edge=c["edge"], generating_pair=c["pair"], n_merged=c["merged"],
                                  planets=planets)
                  for c in found if c["refined"].n_matched >= max(3, options.min_matches)]
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
