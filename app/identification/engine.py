"""Lost-in-space identification: pattern -> ranked, distinct, refined attitudes.

The pipeline is the seed's (004) with these improvements:
hypotheses from the bright-pair index (:mod:`.hypotheses`), each checked by
mapping the whole pattern onto the sky; then the best ones are refined by
least squares over all their matched stars, merged when they are the same
attitude found from different edges, and scored with a false-match
probability (:mod:`.verify`).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Callable

import numpy as np

from app.attitude import rotation_angles_between
from app.camera import Camera
from app.compiled import warm_up
from app.identification.candidates import PreparedPattern, build_candidate, prepare_pattern, with_optics_uncertainty
from app.identification.focal_estimate import FocalEstimate, check_radius_px, focal_estimate
from app.identification.focal_scan import FocalScan, ScanBatch, ScanGroup
from app.identification.hypotheses import PairHypotheses, check_pair_hypotheses, ordered_pattern_edges
from app.identification.methods import METHODS
from app.identification.optics import focal_lengths_to_try, prepared_with_camera, refine_optics
from app.identification.options import SearchOptions
from app.identification.result import AMBIGUOUS, IDENTIFIED, NO_MATCH, Candidate, FocalLengthContradiction, Solution
from app.identification.scale_free import identify_unknown_scale
from app.identification.sky import Sky
from app.identification.verify import check_hypotheses, refine, refine_many

#: The bright triangles' focal length is searched first when it is at least this far from the declared one
#: (a fraction): its estimates err by 0.05 % RMS, 0.13 % at most (144 simulated single snapshots and
#: sequences of the 20 deg camera, 0-5 % off), so an exact camera never leaves its own search (closer, the
#: triangles' match is refined as a hypothesis of the declared camera).
ESTIMATE_MIN_OFFSET = 0.005
#: When the bright triangles fit no focal length within the declared tolerance (or nothing is identified),
#: they are looked up this far (a fraction) from the declared focal length, for a declaration wrong beyond
#: its tolerance: said to the operator, never searched.
DIAGNOSIS_TOLERANCE = 0.2
#: The phase that searches every other focal length within the tolerance at once (:mod:`.focal_scan`).
SCAN = "scan"


def identify(pattern, camera: Camera, t: datetime, sky: Sky, *, velocity_km_s=None,
             options: SearchOptions = SearchOptions(),
             planets: Callable[[], dict[str, np.ndarray]] | None = None,
             method: str = "bright_pair", hypotheses_before: int = 0,
             focal_length_from: str = "declared") -> Solution:
    """Identify a pattern seen by ``camera`` at UTC ``t``.

    ``pattern`` has ``vectors`` (m, 3) camera-frame unit vectors, ``xy``
    (m, 2) pixels, ``sigma_px`` (m,), ``brightness`` (m,) and ``track_ids``
    (m,) (-1 for hand-picked points) - an :class:`app.extraction.Pattern`.
    ``planets()`` returns planet names -> apparent unit vectors at ``t``; it is
    called only when a credible candidate leaves a point unmatched (an
    ephemeris evaluation costs tens of milliseconds);
    ``method`` names a lost-in-space method of :data:`app.identification.methods.METHODS`.

    The declared camera is tried first; when that does not settle the
    answer, focal lengths within the camera's declared tolerance follow
    (:mod:`app.identification.optics`), and every credible candidate has its
    optics fitted with its attitude.  A camera whose focal length is unknown has its scale searched first
    (:mod:`.scale_free`).  ``hypotheses_before`` counts hypotheses a caller tried already for this pattern
    (a search over scales): they enter the false-match probability; ``focal_length_from`` is the word the
    notes give the camera's focal length ("the declared one"; a search over scales says where it found it).
    """
    # The compiled kernels, once a process: compiling (a first run) never counts against the search's time;
    # with the cache complete, each loads at its first call (app.compiled.warm_up).
    warm_up(eager=False)
    generator = METHODS[method].hypotheses if method in METHODS else None
    if generator is None:
        lost_in_space = [name for name, m in METHODS.items() if m.hypotheses is not None]
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(lost_in_space)}")
    m_all = len(pattern.vectors)
    if m_all < 3:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=0.0,
                        notes=(f"the pattern has {m_all} point(s); at least 3 are needed",))
    if camera.focal_length_unknown:
        return identify_unknown_scale(pattern, camera, t, sky, velocity_km_s=velocity_km_s, options=options,
                                      planets=planets, method=method, identify=identify,
                                      hypotheses_before=hypotheses_before)
    sky = sky.for_camera(camera)  # a narrow field needs fainter stars
    started = _time.perf_counter()
    declared = prepare_pattern(pattern, camera, t, sky, velocity_km_s, options)
    focal_lengths = focal_lengths_to_try(camera, declared.xy) if options.search_focal_length \
        else [camera.focal_length_px]
    search = _Search(sky, options, generator, started, camera)
    search.n_tried = search.n_before = hypotheses_before
    # The declared camera's first feature; then a few features at the focal length the pattern's bright
    # triangles point to, when that is clearly another (when it is the declared one, their match is refined
    # as a bright-pair hypothesis of its own); the declared camera's next features; then a few features at
    # every other focal length (bright pairs: all at once, :mod:`.focal_scan`; other methods: the first
    # feature at each, nearest first, then a few more at each), and the rest of the declared camera's.
    # An exact camera settles in the first phases as it always did, and a wrong one costs one search where
    # its triangles point (or, when they point nowhere, a few features per focal length) instead of a full
    # search at each.  (The pattern seen at another focal length is prepared when its phase comes: an exact
    # camera never needs it.)
    searched = focal_lengths[1:]
    prepared = {}
    notes: list[str] = []

    def at(f):
        if f is None:
            return declared
        if f not in prepared:
            prepared[f] = prepared_with_camera(declared, camera.with_optics(focal_length_px=f))
        return prepared[f]

    settled_at = None
    tried_before_focal_search = None
    focal_search_stopped = False
    contradiction = None  # the bright triangles fit a focal length outside the declared tolerance
    looked_wide = False

    def wide_contradiction() -> FocalLengthContradiction | None:
        """The bright triangles looked up DIAGNOSIS_TOLERANCE from the declared focal length: what they fit
        outside the declared tolerance (within it, only the lookup within the tolerance chooses a focal length)."""
        nonlocal looked_wide
        looked_wide = True
        wide = focal_estimate(declared, sky.bright_triangles(), options, DIAGNOSIS_TOLERANCE)
        return _contradiction(wide, camera) if wide is not None and _outside_tolerance(wide, camera) else None

    def phases():
        """(focal length (None: the declared), features to try) in turn, until one settles (or, when the
        bright triangles' own match settles the declared camera, or contradicts it, none more)."""
        nonlocal settled_at, contradiction
        if not searched:
            yield None, None
            return
        yield None, 1
        estimate = focal_estimate(declared, sky.bright_triangles(), options)
        if estimate is None:  # nothing within the tolerance: a declaration wrong beyond it shows further out
            contradiction = wide_contradiction()
        elif _outside_tolerance(estimate, camera):
            contradiction = _contradiction(estimate, camera)
        if contradiction is not None:
            # Optics outside the declaration never make a credible answer: not searched there, but said.  Nor
            # within the declaration: the stars fit that focal length beyond chance (the estimate's test), so a
            # search there would cost a dozen searches (0.3-0.5 s) to find chance fits.
            return
        offset = None if estimate is None else _offset(estimate, camera)
        if estimate is not None and abs(offset) < ESTIMATE_MIN_OFFSET:
            if METHODS[method].bright_triangles:
                # The declared focal length holds, and the match found is a hypothesis of this method's own
                # (the shape matches checked count among the hypotheses tried).
                search.n_tried += estimate.n_tried
                search.consider(declared, estimate.rotation, np.array(estimate.pattern_edge),
                                np.array(estimate.catalogue_pair), check_radius_px(declared) * declared.scale)
                if search.settled(declared, used=1):
                    settled_at = declared
                    return
        elif estimate is not None:
            # The shape matches the estimate checked count among the hypotheses tried: they chose where to look.
            search.n_tried += estimate.n_tried
            search.fitted_focal_lengths.add(estimate.focal_length_px)
            beyond = (f", within the {focal_length_from} {camera.focal_tolerance:.1%} and the estimate's own "
                      f"{ESTIMATE_MIN_OFFSET:.1%}" if abs(offset) > camera.focal_tolerance else "")
            notes.append(f"the pattern's bright triangles put the focal length at "
                         f"{estimate.focal_length_px:.1f} px ({offset:+.1%} of the {focal_length_from}{beyond}), "
                         "searched first")
            # Their match is a hypothesis at that focal length, as at the declared one: on real frames the
            # first bright-pair edges often catch too few stars through a rotation made from two points
            # (short edges, distortion), where the triangle's fitted rotation catches them all.
            estimated = at(estimate.focal_length_px)
            if METHODS[method].bright_triangles:
                search.consider(estimated, estimate.rotation, np.array(estimate.pattern_edge),
                                np.array(estimate.catalogue_pair), check_radius_px(estimated) * estimated.scale)
                if search.settled(estimated, used=1):
                    settled_at = estimated
                    return
            yield estimate.focal_length_px, options.focal_search_features
        yield None, options.declared_features_first
        if METHODS[method].focal_scan:
            yield SCAN, (options.rough_focal_search_features if camera.focal_length_rough
                         else options.focal_search_features)
        else:
            yield from ((f, 1) for f in searched)
            yield from ((f, options.focal_search_features) for f in searched)
        yield None, None

    for f, max_features in phases():
        if f is not None:
            # A pattern that matches nowhere (the Earth, noise) must not pay a dozen searches.
            if tried_before_focal_search is None:
                tried_before_focal_search = search.n_tried
            if search.n_tried - tried_before_focal_search > options.focal_search_max_hypotheses:
                focal_search_stopped = True
                continue
        if f is SCAN:
            settled_at = search.run_scan([declared] + [at(g) for g in searched], max_features)
            if settled_at is not None:
                break
        else:
            p = at(f)
            if search.run(p, max_features):
                settled_at = p
                break
        if search.timed_out():
            break
    # Why a method can have no feature at all, when it had none (the sky is not to blame then).
    no_feature = METHODS[method].no_feature if search.used == 0 else ""
    if not search.parts:
        return Solution(status=NO_MATCH, candidates=(), elapsed_s=_time.perf_counter() - started,
                        notes=(f"no {method} hypothesis: {no_feature or 'no catalogue feature fits the pattern'}",),
                        n_hypotheses=search.n_tried)
    search.alternatives(settled_at or declared)

    n_scales = search.n_scales
    candidates = [_candidate(c, camera, sky, search.n_tried, options, planets) for c in search.found
                  if c["refined"].n_matched >= max(3, options.min_matches)]
    candidates.sort(key=lambda c: (c.false_match_probability, -c.n_matched, c.deviation_arcsec))
    candidates = candidates[:options.max_candidates]
    candidates.sort(key=lambda c: (-c.n_matched, c.false_match_probability, c.deviation_arcsec))
    candidates = [replace(c, rank=i + 1) for i, c in enumerate(candidates)]
    status = classify(candidates, options)
    if status != IDENTIFIED and contradiction is None and not looked_wide:
        # A focal length declared wrong beyond its tolerance identifies nothing: say so when the pattern's
        # triangles fit one, so that an operator can correct the declaration (or calibrate) and search again.
        contradiction = wide_contradiction()
    features = f"{search.used} pattern feature{'s' * (search.used != 1)}"
    if no_feature:
        notes.append(no_feature)
    if focal_search_stopped:
        notes.append(f"the search of other focal lengths stopped after {options.focal_search_max_hypotheses:,} "
                     "hypotheses: a field of stars seen at a wrong focal length is usually found long before")
    if search.n_tried - search.n_before > options.max_hypotheses:
        notes.append(f"the search stopped at its bound of {options.max_hypotheses:,} hypotheses "
                     "(SearchOptions.max_hypotheses)")
    if status == NO_MATCH and settled_at is None and contradiction is None and METHODS[method].focal_scan:
        notes.append(_searched(search, declared, camera, len(searched), focal_length_from))
    notes.insert(0, f"{search.n_tried} {method} hypotheses from {features}"
                 + (f" at {n_scales} focal lengths within {camera.focal_tolerance:.1%} of the {focal_length_from} one"
                    if n_scales > 1 else ""))
    return Solution(status=status, candidates=tuple(candidates), elapsed_s=_time.perf_counter() - started,
                    notes=tuple(notes), focal_length_contradiction=contradiction, n_hypotheses=search.n_tried)


class _Search:
    """The hypotheses and refinements of one identification, over one or more focal lengths.

    ``found`` holds the distinct refined hypotheses of every focal length
    tried (dicts: the starting rotation ``R0``, the refined ``rotation``, the
    :class:`Refined`, the generating ``edge`` and catalogue ``pair``, the
    check ``tol``, how many hypotheses ``merged`` into it, the prepared
    pattern ``searched`` whose hypothesis it was, and the prepared pattern
    ``p`` it was refined with: the same, or the same seen through optics
    fitted on its stars).
    """

    def __init__(self, sky: Sky, options: SearchOptions, generator, started: float, declared: Camera) -> None:
        self.sky, self.options, self.generator, self.started = sky, options, generator, started
        self.declared = declared
        #: Focal lengths fitted on stars already (the bright triangles' estimate): no optics fit per hypothesis.
        self.fitted_focal_lengths: set[float] = set()
        self.found: list[dict] = []
        self.parts: dict[int, list[_Caught]] = {}  # by id of the prepared pattern: its checked hypotheses that
        # caught 3 points or more
        self.n_checked: dict[int, int] = {}  # by id of the prepared pattern: how many it checked
        self.batches: dict[int, object] = {}  # by id of the prepared pattern: its hypothesis batches
        self.refined: dict[tuple, object] = {}  # by (id of the prepared pattern, hypothesis key): its Refined
        self._version = 0  # counts the changes of ``found``
        self._stacks: dict[tuple, tuple] = {}
        self.n_tried = 0
        self.n_before = 0  # hypotheses a caller tried before this search (counted, not bounded here)
        self.n_refined = 0
        self.n_scales = 0
        self.used = 0
        self.used_at: dict = {}  # features used, by id of the prepared pattern (the scan's: "scan")
        self.scan: FocalScan | None = None

    def timed_out(self) -> bool:
        """The search's bounds are spent: its wall-clock budget, or its count of hypotheses
        (``options.max_hypotheses``, the same answer on a loaded machine)."""
        return (_time.perf_counter() - self.started > self.options.timeout_s
                or self.n_tried - self.n_before > self.options.max_hypotheses)

    def _rotations(self, key: str, p=None) -> tuple[list[dict], np.ndarray | None]:
        """The found candidates (refined with ``p``, when given) and their rotations ``key`` stacked
        (kept until ``found`` changes: every hypothesis considered asks for them)."""
        cache_key = (key, None if p is None else id(p))
        cached = self._stacks.get(cache_key)
        if cached is None or cached[0] != self._version:
            found = [c for c in self.found if p is None or c["searched"] is p]
            cached = (self._version, found, np.stack([c[key] for c in found]) if found else None)
            self._stacks[cache_key] = cached
        return cached[1], cached[2]

    def _nearest(self, R: np.ndarray, key: str, p=None) -> tuple[dict | None, float]:
        """The found candidate (refined with ``p``, when given) whose rotation ``key`` is closest to R,
        and that angle."""
        found, stack = self._rotations(key, p)
        if not found:
            return None, np.inf
        angles = rotation_angles_between(stack, R)
        k = int(np.argmin(angles))
        return found[k], float(angles[k])

    def prefetch(self, p, keys, R0s: np.ndarray, tols: np.ndarray) -> None:
        """Refine these hypotheses of ``p`` (keys: their positions among all of ``p``'s) in one batch, for
        :meth:`consider`.

        A refinement depends only on its hypothesis, so refining the next few
        at once (:func:`app.identification.verify.refine_many`, a third of
        the cost of one at a time) changes nothing but the time: a hypothesis
        :meth:`consider` then merges without refining only wastes its share.
        """
        todo = [k for k, key in enumerate(keys) if (id(p), key) not in self.refined]
        if not todo:
            return
        refined = refine_many(R0s[todo], p.vectors, p.weights, p.field, p.match_tol, tols[todo])
        for k, r in zip(todo, refined):
            self.refined[(id(p), keys[k])] = r

    def _refine(self, p, key, R0, tol):
        r = self.refined.get((id(p), key)) if key is not None else None
        return r if r is not None else refine(R0, p.vectors, p.weights, p.field, p.match_tol, tol)

    def consider(self, p, R0, edge, pair, tol, key: int | None = None) -> None:
        """Refine one hypothesis unless it repeats a distinct one already found.

        A hypothesis repeats a candidate when it starts within ``merge_angle``
        of the hypothesis that candidate came from, or when its refinement
        ends within ``merge_angle`` of the candidate's; then the better of
        the two refinements (more matches, then the smaller deviation)
        stays: in a dense field a first edge can settle on a slightly wrong
        attitude that catches a few stars, and a later edge (or focal
        length) finds the one that catches them all.
        """
        merge_angle = 20 * p.scale
        # Starting points repeat within one focal length only: the same catalogue pair gives nearly the
        # same starting rotation at every focal length, and only the right one refines well.
        same, angle = self._nearest(R0, "R0", p)
        if angle >= merge_angle:
            self.n_refined += 1
            r = self._refine(p, key, R0, tol)
            fitted = p
            if (p.camera is not self.declared and p.camera.focal_length_px not in self.fitted_focal_lengths
                    and r.n_matched >= 3 and self.options.fit_optics):
                # A searched focal length is only near the truth: the optics fitted on the stars this
                # hypothesis caught bring in the rest, so that the right focal length settles at once.
                optics = refine_optics(r, p, self.declared, p.field)
                if optics is not None and optics.within_tolerance and optics.refined.n_matched > r.n_matched:
                    r, fitted = optics.refined, optics.prepared
            same, angle = self._nearest(r.rotation, "rotation")
            if angle >= merge_angle:
                self.found.append({"R0": R0, "rotation": r.rotation, "refined": r, "edge": edge, "pair": pair,
                                   "merged": 1, "tol": tol, "p": fitted, "searched": p})
                self._version += 1
                return
            old = same["refined"]
            if (r.n_matched, -float(np.sum(r.nearest_rad))) > (old.n_matched, -float(np.sum(old.nearest_rad))):
                same.update(R0=R0, rotation=r.rotation, refined=r, edge=edge, pair=pair, tol=tol, p=fitted,
                            searched=p)
                self._version += 1
        same["merged"] += 1

    def _check(self, p, hyp, tol) -> _Caught:
        """Check hypotheses ``hyp`` of ``p`` with tolerances ``tol``, and keep those that caught 3 points or more
        (:meth:`_keep`)."""
        if isinstance(hyp, PairHypotheses):  # made where they are checked, only the caught ones kept
            at, n_match, dev, rotations = check_pair_hypotheses(hyp, p.field, tol)
        else:
            n_match, dev = check_hypotheses(hyp.rotations, p.vectors, p.field, tol)
            at = np.flatnonzero(n_match >= 3)
            n_match, dev, rotations = n_match[at], dev[at], hyp.rotations[at]
        return self._keep(p, hyp, tol, at, n_match, dev, rotations)

    def _keep(self, p, hyp, tol, at, n_match, dev, rotations) -> _Caught:
        """Keep the checked hypotheses ``hyp`` of ``p`` that caught 3 points or more (at ``at``, with their
        matches, deviations and rotations) for :meth:`alternatives`, and count them all (the rest never make a
        candidate: a candidate has 3 matches at least)."""
        offset = self.n_checked.get(id(p), 0)  # keys: positions among all of p's hypotheses
        self.n_checked[id(p)] = offset + len(hyp)
        caught = _Caught(at, offset + at, rotations, hyp.pattern_edge[at], hyp.catalogue_pair[at], n_match, dev,
                         tol[at])
        self.parts.setdefault(id(p), []).append(caught)
        self.n_tried += len(hyp)
        return caught

    def run(self, p, max_features: int | None = None) -> bool:
        """Hypotheses of pattern ``p`` in batches, the most promising refined after each; True once settled.

        Settled: a refined hypothesis explains most of the pattern (for
        bright pairs usually after the first sure edges).  ``max_features``
        caps the pattern features (edges) tried.
        """
        options = self.options
        if id(p) not in self.batches:  # resumable: a later run of the same pattern goes on where this stops
            self.batches[id(p)] = self.generator(p, self.sky, options)
            self.n_scales += 1
        parts = self.parts.setdefault(id(p), [])
        for hyp, tol, used in self.batches[id(p)]:
            self.used = max(self.used, used)
            self.used_at[id(p)] = used
            if len(hyp):
                first = not parts
                c = self._check(p, hyp, tol)
                # The declared camera's first batch usually settles the answer, and then the alternatives
                # are its next hypotheses in this order: refine those in the same batch.
                first_declared = first and p.camera is self.declared
                order = best_first(c.n_match, c.dev, options.max_refinements if first_declared
                                   else options.refine_per_batch)
                top = order[:options.refine_per_batch]
                ahead = order if first_declared else top
                ahead = [h for h in ahead if c.n_match[h] >= options.min_matches or h in top]
                self.prefetch(p, c.keys[ahead].tolist(), c.rotations[ahead], c.tol[ahead])
                for h in top.tolist():
                    self.consider(p, c.rotations[h], c.pattern_edge[h], c.catalogue_pair[h], float(c.tol[h]),
                                  key=int(c.keys[h]))
            if self.settled(p, used):
                return True
            if self.timed_out() or (max_features is not None and used >= max_features):
                break
        return False

    def run_scan(self, patterns: list[PreparedPattern], max_features: int) -> PreparedPattern | None:
        """The focal scan's hypotheses (:mod:`.focal_scan`: ``patterns`` is the pattern seen at every focal
        length searched, the declared first) in batches, the most promising of each batch refined at its
        own focal length; the prepared pattern of the focal length that settled, else None."""
        options = self.options
        if "scan" not in self.batches:
            self.scan = FocalScan(patterns, self.sky, options)
            self.batches["scan"] = self.scan.batches()
            self.n_scales += len(patterns) - 1
        for batch, used in self.batches["scan"]:
            self.used = max(self.used, used)
            self.used_at["scan"] = used
            checked = self._check_batch(batch)
            # A pair whose hypothesis caught a third star is tried at the other focal lengths of its window.
            checked += self._check_batch(self.scan.elsewhere([(c.group, c.caught.at) for c in checked]))
            if checked:
                n_match = np.concatenate([c.caught.n_match for c in checked])
                dev = np.concatenate([c.caught.dev for c in checked])
                which = np.repeat(np.arange(len(checked)), [len(c.caught.n_match) for c in checked])
                within = np.concatenate([np.arange(len(c.caught.n_match)) for c in checked])
                top = [(checked[which[h]].caught, checked[which[h]].p, int(within[h]))
                       for h in best_first(n_match, dev, options.refine_per_batch)]
                for c, p in dict.fromkeys((c, p) for c, p, _ in top):
                    ahead = [h for cc, _, h in top if cc is c]
                    self.prefetch(p, c.keys[ahead].tolist(), c.rotations[ahead], c.tol[ahead])
                for c, p, h in top:
                    self.consider(p, c.rotations[h], c.pattern_edge[h], c.catalogue_pair[h], float(c.tol[h]),
                                  key=int(c.keys[h]))
                for p in dict.fromkeys(c.p for c in checked):
                    if self.settled(p, used):
                        return p
            if self.timed_out() or used >= max_features:
                break
        return None

    def _check_batch(self, batch: ScanBatch) -> list[_Checked]:
        """Check a batch of the focal scan's hypotheses (:mod:`.focal_scan`: every focal length's at once, one
        compiled call) and keep each group's (made at one focal length) as :meth:`_check` keeps them."""
        if not batch.groups:
            return []
        at, n_match, dev, rotations = check_pair_hypotheses(batch.hypotheses, self.scan.patterns[0].field,
                                                            batch.check_tol)
        ends = np.searchsorted(at, [g.start + len(g.hypotheses) for g in batch.groups]).tolist()
        checked = []
        for g, a, b in zip(batch.groups, [0] + ends[:-1], ends):
            p = self.scan.patterns[g.step]
            checked.append(_Checked(g, p, self._keep(p, g.hypotheses, g.check_tol, at[a:b] - g.start, n_match[a:b],
                                                     dev[a:b], rotations[a:b])))
        return checked

    def settled(self, p, used: int) -> bool:
        """Whether a refined hypothesis of ``p`` explains most of it, after ``used`` pattern features."""
        options = self.options
        best = max((c["refined"].n_matched for c in self.found if c["searched"] is p), default=0)
        return (best >= min(p.m, options.early_stop_matches) and best >= options.early_stop_fraction * p.m
                and used >= options.early_stop_edges)

    def alternatives(self, p) -> None:
        """More distinct alternatives for the operator's Next/Prev, in order of promise, from ``p``'s hypotheses.

        The hypotheses that will need refining are refined a batch at a time
        (:meth:`prefetch`): the next ones in order, as many as the refinement
        budget has left, leaving out those that start where a found one did.
        """
        options = self.options
        parts = self.parts.get(id(p))

        def enough() -> bool:
            credible = sum(c["refined"].n_matched >= max(3, options.min_matches) for c in self.found)
            return (credible >= options.max_candidates or self.n_refined >= options.max_refinements
                    or self.timed_out())

        if not parts or enough():  # (a search that found nothing has spent its refinements long before)
            return
        rot, pe, cp, n_match, dev, hyp_tol, keys = (np.concatenate([getattr(c, name) for c in parts]) for name in (
            "rotations", "pattern_edge", "catalogue_pair", "n_match", "dev", "tol", "keys"))
        kept = np.flatnonzero(n_match >= options.min_matches)  # the rest never make a candidate
        order = kept[np.lexsort((dev[kept], -n_match[kept]))]
        merge_angle = 20 * p.scale
        for i, h in enumerate(order.tolist()):
            if enough():
                break
            if (id(p), int(keys[h])) not in self.refined and self._nearest(rot[h], "R0", p)[1] >= merge_angle:
                budget = options.max_refinements - self.n_refined
                ahead = order[i:i + 4 * budget]
                _, starts = self._rotations("R0", p)
                if starts is not None:
                    first = np.min([rotation_angles_between(rot[ahead], R) for R in starts], axis=0)
                    ahead = ahead[first >= merge_angle]
                ahead = ahead[:budget]
                self.prefetch(p, keys[ahead].tolist(), rot[ahead], hyp_tol[ahead])
            self.consider(p, rot[h], pe[h], cp[h], float(hyp_tol[h]), key=int(keys[h]))


def best_first(n_match: np.ndarray, dev: np.ndarray, k: int) -> np.ndarray:
    """The first ``k`` of ``np.lexsort((dev, -n_match))`` (the most matches, then the smallest deviation, then
    the earliest), without sorting them all: a focal scan's batch on a frame that matches nothing holds
    thousands of hypotheses that caught 3 points by chance, of which 3 are refined (sorting them all took 0.7 ms
    a batch, 3 % of such a frame's search; measured 2026-11-26).

    Every hypothesis with more matches than the ``k``-th best's comes first; of those with as many, the ones
    with a deviation up to the one that fills ``k`` (its equals too, so that the earliest win a tie); those few
    are sorted as lexsort sorts them all (stable: the earliest first among equals)."""
    n = len(n_match)
    if n <= 4 * k:
        return np.lexsort((dev, -n_match))[:k]
    kth = np.partition(n_match, n - k)[n - k]  # the k-th largest match count
    better = np.flatnonzero(n_match > kth)
    ties = np.flatnonzero(n_match == kth)
    d = dev[ties]
    ties = ties[~(d > np.partition(d, k - len(better) - 1)[k - len(better) - 1])]  # nan-safe: kept, sorted last
    chosen = np.sort(np.concatenate([better, ties]))
    return chosen[np.lexsort((dev[chosen], -n_match[chosen]))][:k]


@dataclass(frozen=True, eq=False)
class _Caught:
    """The hypotheses of a checked batch that caught 3 points or more: their positions in the batch, their
    keys (positions among all of the pattern's hypotheses), rotations, generating edges and pairs, matches,
    capped deviations and check tolerances."""

    at: np.ndarray
    keys: np.ndarray
    rotations: np.ndarray
    pattern_edge: np.ndarray
    catalogue_pair: np.ndarray
    n_match: np.ndarray
    dev: np.ndarray
    tol: np.ndarray


@dataclass(frozen=True, eq=False)
class _Checked:
    """A checked group of the focal scan: the group, its prepared pattern, and its hypotheses that caught 3
    points or more."""

    group: ScanGroup
    p: PreparedPattern
    caught: _Caught


def _searched(search: _Search, declared, camera: Camera, n_other: int, focal_length_from: str) -> str:
    """What a bright-pair search that found nothing searched, in a sentence."""
    separation = search.options.min_pair_separation_px
    edges = ordered_pattern_edges(declared.xy, camera, separation)
    i, j = np.triu_indices(declared.m, k=1)
    pairs = int(np.count_nonzero(np.hypot(*(declared.xy[i] - declared.xy[j]).T) >= separation))
    said = (f"nothing found: searched {search.used_at.get(id(declared), 0)} of the pattern's {len(edges)} "
            f"Delaunay edges at the {focal_length_from} focal length"
            + (f" (not its other {pairs - len(edges)} point pair{'s' * (pairs - len(edges) != 1)}, each with a "
               "point between its two)" if pairs > len(edges) else ""))
    if search.scan is not None:
        said += (f", and its first {search.used_at.get('scan', 0)} at the {n_other} other focal lengths within "
                 f"{camera.focal_tolerance:.1%} at once (each catalogue pair at the one nearest its length, and at "
                 "the others that fit it when it caught a third star)")
    return said


def _offset(estimate: FocalEstimate, camera: Camera) -> float:
    """The estimated focal length's departure from the declared one, a fraction."""
    return estimate.focal_length_px / camera.focal_length_px - 1


def _outside_tolerance(estimate: FocalEstimate, camera: Camera) -> bool:
    """Whether an estimated focal length lies outside the declared tolerance by more than the estimate's own
    uncertainty."""
    return abs(_offset(estimate, camera)) > camera.focal_tolerance + ESTIMATE_MIN_OFFSET


def _contradiction(estimate: FocalEstimate, camera: Camera) -> FocalLengthContradiction:
    """What an operator needs to act on a declaration the stars contradict: the focal length they fit and
    where the camera then points."""
    return FocalLengthContradiction(
        focal_length_px=estimate.focal_length_px, declared_focal_length_px=camera.focal_length_px,
        declared_tolerance=camera.focal_tolerance, n_matched=estimate.n_matched, n_points=estimate.n_points,
        rotation_matrix=estimate.rotation)


def _candidate(c: dict, declared: Camera, sky: Sky, n_tried: int, options: SearchOptions, planets) -> Candidate:
    """The candidate of a found hypothesis, its optics fitted when it is credible (see :mod:`.optics`)."""
    r, p = c["refined"], c["p"]
    searched_scale = p.camera is not declared  # found at another focal length than the declared one
    common = dict(tol=c["tol"], n_hypotheses=n_tried, options=options, generating_edge=c["edge"],
                  generating_pair=c["pair"], n_merged=c["merged"], planets=planets)
    candidate = build_candidate(r, p, sky, n_fitted=int(searched_scale), **common)
    if not options.fit_optics or candidate.false_match_probability > options.rival_probability:
        return replace(candidate, camera=p.camera) if searched_scale else candidate
    optics = refine_optics(r, p, declared, p.field)
    if optics is None:
        return replace(candidate, camera=p.camera) if searched_scale else candidate
    if optics.significant or searched_scale:
        candidate = build_candidate(optics.refined, optics.prepared, sky,
                                    n_fitted=len(optics.fit.parameters), **common)
        candidate = replace(candidate, camera=optics.prepared.camera)
    if not optics.within_tolerance:
        # The stars fit only with optics the declaration excludes: no credible identification.
        candidate = replace(candidate, false_match_probability=1.0)
    return with_optics_uncertainty(candidate, optics.fit)  # its attitude sigma marginal over the optics


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
    Nor is a candidate that names the same stars for the points both match
    (at least two, none named otherwise): it is the same identification with
    fewer or other points caught (on real frames, found again at another
    searched focal length, a few tenths of a degree away), not another
    explanation.
    """
    p, p_best = candidate.false_match_probability, best.false_match_probability
    return (p <= options.rival_probability and candidate.rms_arcsec <= options.rival_rms_factor * best.rms_arcsec
            and p <= options.rival_odds * max(p_best, 1e-300) and not same_identification(candidate, best))


def same_identification(a: Candidate, b: Candidate) -> bool:
    """Whether two candidates name the same star for every pattern point both match, at least two of them."""
    star_of = {m.pattern_index: m.hip for m in b.matches}
    common = [(m.hip, star_of[m.pattern_index]) for m in a.matches if m.pattern_index in star_of]
    return len(common) >= 2 and all(x == y for x, y in common)
