"""Bright-pair hypotheses of every searched focal length at once: the focal scan.

Why.  A focal length off by the fraction ``e`` scales every pattern angle
by about ``1 + e``; an edge of ``L`` pixels leaves the bright-pair lookup's
length window (``w``, a few pixels) once ``e L > w``, so the engine also
searches the focal lengths within the declared tolerance, in steps
(:func:`app.identification.optics.focal_lengths_to_try`: half a step moves
the pattern's farthest point by at most 4 pixels, so 12-38 steps for a 5 %
tolerance).  Searched step by step, a short edge's window spans several
steps (a window of ``2 w`` pixels is ``2 w / L`` of the edge's length, the
step ``8 / L_max``), so each catalogue pair of the first, shortest, edges was
tried again at each of those steps: 3-5 times on the 20 deg camera, and a
pattern that matches nothing (noise, the Earth) paid for it at every step
(60 % of its search).

How.  Each pattern edge is looked up once, over the union of its windows at
every searched focal length but the declared one, and each catalogue pair
found is tried once: at the searched focal length whose length of that edge
is nearest the pair's, when the pair lies within that focal length's window
(the hypothesis the stepped search made there).  The declared camera's own
search tried the pairs of its window; a pair nearest the declared focal
length goes to the nearest other whose window holds it.  The hypotheses keep
their focal length (the prepared pattern of their step), so checking,
refining, the optics fit and the false-match count go on as for a step of
their own.

The nearest is only the edge's guess.  An edge of ``L`` pixels knows the
scale to ``w / L`` (5 % for a 100-pixel edge whose stars sit 1-3 pixels from
their catalogue places, as on defocused real frames), and a real lens's
distortion makes the best pinhole scale differ across the field by ~1 %:
at the nearest focal length a true pair's far stars can miss.  Its near ones
do not (a star at ``D`` pixels from the edge moves ``D w / L`` across the
window, within the check tolerance for ``D`` up to about ``L``), so a pair
whose hypothesis catches a third star is also tried at every other focal
length whose window holds it (:meth:`FocalScan.elsewhere`): the stepped
search's other tries of that pair, for the pairs that earn them (a quarter
of a random pattern's, at a 10 px check tolerance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.compiled import njit, warm_up_with
from app.identification.candidates import PreparedPattern
from app.identification.hypotheses import PairHypotheses, edge_batches, ordered_pattern_edges, stacked_edge_windows
from app.identification.options import SearchOptions
from app.identification.sky import Sky


@dataclass(frozen=True, eq=False)
class ScanGroup:
    """Hypotheses made at one searched focal length."""

    step: int  # position of their prepared pattern in the scan's list
    hypotheses: PairHypotheses
    check_tol: np.ndarray  # (H,) radians
    pair_length: np.ndarray  # (H,) the catalogue pairs' lengths, radians
    start: int  # position of the first in its batch


@dataclass(frozen=True, eq=False)
class ScanBatch:
    """Hypotheses made at several searched focal lengths, in order of focal length: one stack, checked at once
    (:attr:`hypotheses`, :attr:`check_tol`), and its groups, one per focal length (views of it; iterating a
    batch gives them)."""

    hypotheses: PairHypotheses
    check_tol: np.ndarray
    groups: list[ScanGroup]

    def __iter__(self):
        return iter(self.groups)

    def __len__(self) -> int:
        return len(self.groups)


class FocalScan:
    """The bright-pair hypotheses of one pattern seen at several focal lengths (``patterns``: the declared
    first, then at least one other), each catalogue pair at the focal length nearest its length (see the
    module doc)."""

    def __init__(self, patterns: list[PreparedPattern], sky: Sky, options: SearchOptions) -> None:
        declared = patterns[0]
        self.patterns, self.index, self.star_mask = patterns, sky.index, declared.star_mask
        self.edges = ordered_pattern_edges(declared.xy, declared.camera, options.min_pair_separation_px)
        self.edge_array = np.array(self.edges, dtype=np.int64).reshape(-1, 2)
        self.vectors = np.stack([p.vectors for p in patterns])  # (S, m, 3)
        if self.edges:
            # (E, S): each edge's angle at each focal length, its window's half-width, its check tolerance.
            self.lengths, self.tolerance, self.check_tol = (
                np.ascontiguousarray(x.T) for x in stacked_edge_windows(patterns, options, self.edges))

    def batches(self):
        """Yields (the batch's hypotheses by focal length, a :class:`ScanBatch`, the pattern features used so
        far), edge batches of growing size as :func:`.hypotheses.bright_pair_batches`."""
        for e0, stop in edge_batches(len(self.edges)):
            yield self._batch(*self._nearest_step_hypotheses(e0, stop)), stop

    def _batch(self, steps: np.ndarray, pair_length: np.ndarray, e: np.ndarray, r1: np.ndarray,
               r2: np.ndarray) -> ScanBatch:
        """Hypotheses of edges ``e`` onto index stars ``r1``, ``r2`` (pairs of length ``pair_length``), each at
        its focal length ``steps``, in order of focal length (the order they came in within each), with one
        group per focal length."""
        steps, e, r1, r2 = (np.ascontiguousarray(x, dtype=np.int64) for x in (steps, e, r1, r2))
        steps, pair_length, e, edge, pair, check_tol, starts = _by_focal_length(
            steps, len(self.patterns), np.ascontiguousarray(pair_length, dtype=float), e, r1, r2, self.edge_array,
            self.check_tol)
        hypotheses = PairHypotheses(self.vectors, self.index.vectors, edge, pair, e, steps)
        groups = [ScanGroup(step, PairHypotheses(self.vectors, self.index.vectors, edge[a:b], pair[a:b], e[a:b],
                                                 steps[a:b]), check_tol[a:b], pair_length[a:b], a)
                  for step, (a, b) in enumerate(zip(starts[:-1].tolist(), starts[1:].tolist())) if b > a]
        return ScanBatch(hypotheses, check_tol, groups)

    def _nearest_step_hypotheses(self, e0: int, stop: int) -> tuple[np.ndarray, ...]:
        """Edges ``e0:stop``'s hypotheses, every index pair within one of an edge's windows at the searched
        focal length (not the declared) whose length of the edge is nearest the pair's, kept when within that
        window: (steps, the pairs' lengths, edge numbers, first stars, second stars), edge after edge, both
        orientations of each pair as in :func:`app.identification.hypotheses.bright_pair_hypotheses`.  Each
        edge's pairs are a run of the index (sorted by length), found for all edges at once; one compiled
        loop (:func:`_nearest_step_pairs`) takes each pair to its focal length."""
        lengths, windows, index = self.lengths[e0:stop, 1:], self.tolerance[e0:stop, 1:], self.index
        first = np.searchsorted(index.length_rad, np.min(lengths - windows, axis=1), side="left")
        last = np.searchsorted(index.length_rad, np.max(lengths + windows, axis=1), side="right")
        mask = np.ones(index.n_stars, dtype=np.bool_) if self.star_mask is None else self.star_mask
        return _nearest_step_pairs(np.ascontiguousarray(lengths), np.ascontiguousarray(windows),
                                   np.argsort(lengths, axis=1, kind="stable"), first, last, e0, index.star_a,
                                   index.star_b, index.length_rad, mask)

    def elsewhere(self, picked: list[tuple[ScanGroup, np.ndarray]]) -> ScanBatch:
        """The hypotheses picked (``(group, positions in it)`` pairs) at every other searched focal length
        (not the declared) whose window holds their pair, grouped by focal length."""
        picked = [(group, which) for group, which in picked if len(which)]
        if not picked:
            none = np.empty(0, dtype=np.int64)
            return self._batch(none, np.empty(0), none, none, none)
        e = np.concatenate([group.hypotheses.edge_number[which] for group, which in picked])
        pair = np.concatenate([group.hypotheses.catalogue_pair[which] for group, which in picked])
        pair_length = np.concatenate([group.pair_length[which] for group, which in picked])
        own = np.concatenate([np.full(len(which), group.step) for group, which in picked])
        held = np.abs(self.lengths[e] - pair_length[:, None]) <= self.tolerance[e]  # (n, S)
        held[:, 0] = False
        held[np.arange(len(e)), own] = False
        h, steps = np.nonzero(held)
        return self._batch(steps, pair_length[h], e[h], pair[h, 0], pair[h, 1])


@njit
def _by_focal_length(steps, n_steps, pair_length, e, r1, r2, edge_array, check_tol):
    """Hypotheses (each at focal length ``steps[h]`` of ``n_steps``, edge ``e[h]``, stars ``r1[h]``, ``r2[h]``)
    in order of focal length, the order they came in within each (a counting sort): (steps, pair lengths, edge
    numbers, pattern edges (H, 2), catalogue pairs (H, 2), check tolerances, where each focal length's begin
    (``n_steps + 1``)), in one pass where numpy's stable sort and gathers took ~0.5 ms a batch."""
    H = steps.shape[0]
    starts = np.zeros(n_steps + 1, dtype=np.int64)
    for h in range(H):
        starts[steps[h] + 1] += 1
    for s in range(n_steps):
        starts[s + 1] += starts[s]
    at = starts[:-1].copy()
    sorted_steps, sorted_length, sorted_e = np.empty(H, dtype=np.int64), np.empty(H), np.empty(H, dtype=np.int64)
    edge, pair, tol = np.empty((H, 2), dtype=np.int64), np.empty((H, 2), dtype=np.int64), np.empty(H)
    for h in range(H):
        s = steps[h]
        k = at[s]
        at[s] += 1
        sorted_steps[k], sorted_length[k], sorted_e[k] = s, pair_length[h], e[h]
        edge[k, 0], edge[k, 1] = edge_array[e[h], 0], edge_array[e[h], 1]
        pair[k, 0], pair[k, 1] = r1[h], r2[h]
        tol[k] = check_tol[e[h], s]
    return sorted_steps, sorted_length, sorted_e, edge, pair, tol, starts


@njit
def _nearest_step_pairs(lengths, windows, order, first, last, e0, star_a, star_b, length_rad, star_mask):
    """See :meth:`FocalScan._nearest_step_hypotheses`: for edge ``e0 + r`` (its angle ``lengths[r, s]`` and
    window ``windows[r, s]`` at searched focal length ``s + 1``, ``order[r]`` those lengths in order), each
    index row in ``first[r]:last[r]`` whose stars are both in ``star_mask`` goes to the nearest of the lengths
    (the one at the pair's place among them or the one before, the one before on a tie) when within its
    window."""
    E, S = lengths.shape
    total = 0
    for r in range(E):
        total += last[r] - first[r]
    steps, pair_length = np.empty(2 * total, dtype=np.int64), np.empty(2 * total)
    edge_number, r1, r2 = np.empty(2 * total, dtype=np.int64), np.empty(2 * total, dtype=np.int64), \
        np.empty(2 * total, dtype=np.int64)
    h = 0
    for r in range(E):
        start = h
        for row in range(first[r], last[r]):
            a, b, length = star_a[row], star_b[row], length_rad[row]
            if not (star_mask[a] and star_mask[b]):
                continue
            place = 0  # how many of the lengths lie below the pair's (np.searchsorted, side "left")
            while place < S and lengths[r, order[r, place]] < length:
                place += 1
            below = min(max(place - 1, 0), S - 1)
            above = min(below + 1, S - 1)
            near_below = abs(length - lengths[r, order[r, below]]) <= abs(lengths[r, order[r, above]] - length)
            step = order[r, below] if near_below else order[r, above]
            if abs(length - lengths[r, step]) <= windows[r, step]:
                steps[h], pair_length[h], edge_number[h], r1[h], r2[h] = step + 1, length, e0 + r, a, b
                h += 1
        n = h - start
        for k in range(start, h):  # the other orientation
            steps[k + n], pair_length[k + n], edge_number[k + n], r1[k + n], r2[k + n] = \
                steps[k], pair_length[k], edge_number[k], r2[k], r1[k]
        h += n
    return steps[:h], pair_length[:h], edge_number[:h], r1[:h], r2[:h]


@warm_up_with
def _warm_up_scan() -> None:
    """Compile the scan's ordering for the types the searches pass."""
    one = np.zeros(1, dtype=np.int64)
    _by_focal_length(one, 1, np.zeros(1), one, one, one, np.zeros((1, 2), dtype=np.int64), np.zeros((1, 1)))
    _nearest_step_pairs(np.zeros((1, 1)), np.ones((1, 1)), one.reshape(1, 1), one, one + 1, 0, one, one + 1,
                        np.zeros(1), np.ones(2, dtype=np.bool_))
