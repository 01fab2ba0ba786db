"""Tracked stars vs ghosts, hot pixels and outliers in one snapshot sequence.

The steps of :func:`extract`:

1. **Motion between snapshots.**  The rotation between each snapshot and
   the next is estimated robustly (:mod:`app.extraction.motion`).  Sources
   sitting on the same pixel in three or more snapshots are kept out of
   this while they are a minority: hot pixels would vote for "no
   rotation".  Where a snapshot has no rotation to its predecessor (too few
   common stars, the Earth in view, a burst of ghosts), or one resting on
   the fewest matches accepted (``min_inliers``: ghosts line up by chance
   that well now and then), it is also linked to up to ``max_skip``
   snapshots back, and the link with the most matches is used.  Composing
   the links puts every snapshot of a connected run ("component") into one
   common frame: ``v_c = A[i] v_i``.  A run cut off from the longest one
   (a first snapshot sharing three stars with the second, among three
   ghosts) is then registered against the longest run's provisional tracks
   seen from its nearest snapshot, which hold more of its stars than any
   single snapshot does (:func:`_rejoin_components`).
2. **Refinement.**  The links' matched sources, joined transitively, give
   provisional tracks; each snapshot's rotation into the common frame is
   re-solved (Wahba) against their mean directions, which removes the drift
   of the composed links.
3. **Noise.**  The single-sighting position noise sigma is estimated from
   the matched sources' residuals (median based, so robust to the odd
   mismatch); the gates scale with it.
4. **Hot pixels.**  A source whose pixel is occupied (within ``hot_tol``)
   in another snapshot by a source the sky could not have carried there
   (the motion moves that sky point by more than the link gate) is
   stationary evidence; a source with two such partners is a hot pixel, and
   so is one with a single such partner when neither of the two has more
   than one partner that moved with the sky; so is every source on the same
   pixel as one with two such partners.  When the sky moves less
   than the link gate over the whole sequence a stationary source is
   indistinguishable from a star: it is kept as a track and a note says so
   (identification then finds it matches no star).
5. **Association.**  In the common frame a star is a fixed direction.
   Snapshots are visited in order; each one's sources are assigned to the
   existing tracks' mean directions by ``linear_sum_assignment`` on the
   angular distance, within the link gate (when every source's nearest
   track is a different one that is already the optimum); the rest start
   new tracks.  A
   star missing from some snapshots simply rejoins its track later.  The
   rotations are then re-solved once more against these fuller tracks.
6. **Outliers.**  A sighting farther from the mean of its track's other
   sightings than the noise allows (4.5 sigma, scaled for the other mean's
   own noise) is an outlier; the worst one per track is removed, up to
   three rounds.  A track left with one sighting dissolves: its sightings
   had no consistent partner and count as ghosts.
7. **Verdicts.**  Tracks need two sightings; what is left unlinked is a
   ghost (including every source of a snapshot linked to no other).  The
   reference snapshot is the one with the most tracked sources.

A sequence of one snapshot has nothing to track against: every source
becomes a one-sighting track and pattern point, with a note.

**Known hot pixels.**  ``known_hot`` (per snapshot, a flag per source)
names sources the caller already knows to be hot pixels, e.g. those on the
camera's mapped hot pixels (:mod:`app.frames.hotpixels`).  They keep their
place in the input (the per-source arrays are indexed as before) but get
the ``hot_pixel`` verdict: they take no part in the motion estimate or the
association, so they are never tracks or pattern points, even in a single
snapshot or when the sky hardly moves, where step 4 cannot tell them.
Without any flagged source the result is exactly that of ``extract``
without ``known_hot``.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from app.compiled import njit, warm_up_with
from app.extraction.model import (GHOST, HOT_PIXEL, OUTLIER, Extraction, ExtractionParameters, Track,
                                  assumed_sighting_noise_px)
from app.extraction.motion import estimate_pair_rotations, expand_ranges, wahba_rotations
from app.extraction.pattern import carried_tracks, seed_pattern, tracks_pattern
from app.telemetry.model import Sequence

DEFAULT_PARAMETERS = ExtractionParameters()
#: Median of a chi-square variable with 2 degrees of freedom (2 ln 2).
_CHI2_2_MEDIAN = 2.0 * math.log(2.0)


def _rotate(rotations: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Row-wise ``rotations[k] @ vectors[k]`` for (K, 3, 3) and (K, 3)."""
    return np.matmul(rotations, vectors[:, :, None])[:, :, 0]


def _norms(v: np.ndarray) -> np.ndarray:
    """Lengths of the (..., 3) vectors: numpy's norm, the same numbers, without its reduction over an axis of
    three (most of its time for a few hundred rows)."""
    return np.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2])


def _normalized(v: np.ndarray) -> np.ndarray:
    return v / _norms(v)[..., None]


def _padded(sequence: Sequence) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, N, 2) pixels, (S, N) brightness, (S, N) validity, NaN/False padded."""
    counts = np.array([s.n_sources for s in sequence.snapshots])
    n_max = int(counts.max())
    xy = np.full((len(counts), n_max, 2), np.nan)
    brightness = np.full((len(counts), n_max), np.nan)
    for i, snapshot in enumerate(sequence.snapshots):
        xy[i, :counts[i]] = snapshot.xy
        brightness[i, :counts[i]] = snapshot.brightness
    valid = np.arange(n_max)[None, :] < counts[:, None]
    return xy, brightness, valid


def _link_settings(p: ExtractionParameters, chord_px: float, field_area_px: float) -> dict:
    """The keyword arguments of :func:`estimate_pair_rotations`: the parameters' pixels as chords."""
    return dict(pair_tol=p.pair_tol_px * chord_px, min_baseline=p.min_baseline_px * chord_px,
                score_gate=p.score_gate_px * chord_px, fit_gate=p.fit_gate_px * chord_px,
                min_inliers=p.min_inliers, min_radius=p.min_match_radius_px * chord_px,
                max_false_alarms=p.max_false_alarms, field_area=field_area_px * chord_px**2,
                max_work=p.max_link_work, min_hypotheses=p.min_link_hypotheses)


def _brightest_sources(valid: np.ndarray, brightness: np.ndarray, k: int) -> np.ndarray:
    """(S, K) indices of each row's K brightest valid sources, brightest first, -1 padded."""
    order = np.argsort(np.where(valid, -brightness, np.inf), axis=1, kind="stable")[:, :k]
    return np.where(np.take_along_axis(valid, order, axis=1), order, -1)


def _accepted_links(links: np.ndarray, result) -> dict:
    """{(a, b): (R, matches, number of matches)} of the links that got a rotation."""
    ok = np.flatnonzero(np.isfinite(result.rotation[:, 0, 0]))
    return {(a, b): (result.rotation[k], result.matches[k], n)
            for k, (a, b), n in zip(ok, links[ok].tolist(), result.n_inliers[ok].tolist())}


def _chain_motions(vectors: np.ndarray, brightness: np.ndarray, valid: np.ndarray, chord_px: float,
                   field_area_px: float, p: ExtractionParameters):
    """Rotations into a common frame per connected run of snapshots.

    Returns (A (S, 3, 3) with v_c = A[i] v_i, component (S,), the links used
    as (a, b, matches (N,)) triples, squared chords of all link inliers).
    """
    n_snap = vectors.shape[0]
    hyp = _brightest_sources(valid, brightness, p.hypothesis_sources)
    kwargs = _link_settings(p, chord_px, field_area_px)
    links = np.column_stack([np.arange(n_snap - 1), np.arange(1, n_snap)])
    first = estimate_pair_rotations(vectors, hyp, links, **kwargs)
    found = _accepted_links(links, first)
    # A snapshot with no link to its predecessor, or one resting on the fewest matches accepted
    # (two fix the hypothesis, one more is the only evidence: a chance alignment of ghosts passes
    # the false-alarm test now and then), is also linked to snapshots further back.
    weak = [b for b in range(1, n_snap) if found.get((b - 1, b), (None, None, 0))[2] <= p.min_inliers]
    skips = np.array([(b - d, b) for b in weak for d in range(2, p.max_skip + 1) if b - d >= 0],
                     dtype=int).reshape(-1, 2)
    second = estimate_pair_rotations(vectors, hyp, skips, **kwargs)
    found.update(_accepted_links(skips, second))

    to_common = np.tile(np.eye(3), (n_snap, 1, 1))
    component = np.zeros(n_snap, dtype=int)
    used = []
    n_components = 1
    for b in range(1, n_snap):
        # the link with the most matches wins, the nearest snapshot on ties
        options = [(a, *found[(a, b)]) for a in range(b - 1, max(-1, b - 1 - p.max_skip), -1) if (a, b) in found]
        if options:
            a, r, matches, _ = max(options, key=lambda option: option[3])
            # v_b = R v_a and v_c = A_a v_a  =>  v_c = A_a R^T v_b
            to_common[b] = to_common[a] @ r.T
            component[b] = component[a]
            used.append((a, b, matches))
        else:
            component[b] = n_components
            n_components += 1
    return to_common, component, used, np.concatenate([first.inlier_chord_sq, second.inlier_chord_sq])


def _linked_groups(used_links, flat_of: np.ndarray, n_sources: int) -> np.ndarray:
    """(M,) group label joining the sources matched by the used links transitively.

    Every snapshot has at most one used link from an earlier snapshot, so
    every source has at most one matched source in an earlier snapshot, its
    parent: a group is a chain of parents, labelled by its first source.
    Parents are followed to the first by pointer jumping (each round doubles
    the distance, so 16 snapshots take four rounds).
    """
    parent = np.arange(n_sources)
    if used_links:
        a = np.array([link[0] for link in used_links])
        b = np.array([link[1] for link in used_links])
        matches = np.array([link[2] for link in used_links])
        row, k = np.nonzero(matches >= 0)
        parent[flat_of[b[row], matches[row, k]]] = flat_of[a[row], k]
    while True:
        further = parent[parent]
        if np.array_equal(further, parent):
            return parent
        parent = further


def _nearest_snapshots(component: np.ndarray, main: int) -> list[tuple[int, int, int]]:
    """For every component other than ``main``: (component, its snapshot nearest in time to
    ``main``, the snapshot of ``main`` nearest to that one); earlier snapshots win ties."""
    in_main = np.flatnonzero(component == main)
    out = []
    for c in np.unique(component[component != main]):
        mine = np.flatnonzero(component == c)
        gap = np.abs(mine[:, None] - in_main[None, :])
        i, j = np.unravel_index(np.argmin(gap), gap.shape)
        out.append((int(c), int(mine[i]), int(in_main[j])))
    return out


def _virtual_snapshots(camera, common: np.ndarray, brightness: np.ndarray, snap: np.ndarray,
                       component: np.ndarray, groups: np.ndarray, usable: np.ndarray,
                       to_common: np.ndarray, views: list[tuple[int, int]]):
    """The sky each component's provisional tracks show in one of its snapshots' frames.

    For a view (component c, snapshot s of c) the points are every group of c
    with two or more sightings, at its mean common-frame direction w carried
    into s (``A_s^T w``) where that falls on the sensor, and s's own usable
    sources in no such group.  A lone snapshot's view is its own sources; a
    longer run's view holds the stars it saw anywhere near s, without the
    ghosts (seen once) and dropouts of s.  Returns zero-padded vectors (V, N, 3),
    brightness (V, N), validity (V, N) and each point's group label (V, N).
    """
    live = np.where(usable, groups, -1)
    n_labels = len(groups)
    label_size = np.bincount(live[live >= 0], minlength=n_labels)
    label_comp = np.full(n_labels, -1)
    label_comp[live[live >= 0]] = component[snap[live >= 0]]
    sums = np.zeros((n_labels, 3))
    np.add.at(sums, live[live >= 0], common[live >= 0])
    mean_brightness = np.bincount(live[live >= 0], brightness[live >= 0], n_labels) / np.maximum(label_size, 1)
    rows = []
    for c, s in views:
        multi = np.flatnonzero((label_size >= 2) & (label_comp == c))
        local = _normalized(sums[multi]) @ to_common[s]  # rows w^T A_s
        xy, front = camera.vectors_to_pixels(local)
        seen = front & camera.on_sensor(xy)
        single = np.flatnonzero(usable & (snap == s) & (label_size[groups] < 2))
        rows.append((np.concatenate([local[seen], common[single] @ to_common[s]]),
                     np.concatenate([mean_brightness[multi[seen]], brightness[single]]),
                     np.concatenate([multi[seen], groups[single]])))
    width = max(1, max(len(r[2]) for r in rows))
    vectors = np.zeros((len(views), width, 3))
    bright = np.zeros((len(views), width))
    label = np.full((len(views), width), -1)
    for v, (vec, b, lab) in enumerate(rows):
        vectors[v, :len(lab)], bright[v, :len(lab)], label[v, :len(lab)] = vec, b, lab
    return vectors, bright, label >= 0, label


def _rejoin_components(camera, vectors: np.ndarray, brightness: np.ndarray, snap: np.ndarray,
                       usable: np.ndarray, groups: np.ndarray, to_common: np.ndarray, component: np.ndarray,
                       chord_px: float, p: ExtractionParameters):
    """Runs of snapshots cut off from the longest run, joined to it through their tracks' sky.

    With three ghosts and a hot pixel among ten sources two snapshots may
    share only three stars, and three matches within a pixel are not
    improbable enough by chance among hundreds of pair hypotheses
    (:func:`app.extraction.motion.false_alarms`): the link is refused, rightly,
    and a snapshot whose every link is refused (the first one, whose single
    link is to the second, most often) is left alone, its stars lost.  But
    the longest run knows more sky than any one snapshot: its provisional
    tracks carried into its snapshot m nearest to the cut-off run, and the
    cut-off run's own tracks (or a lone snapshot's sources) in its snapshot
    x nearest to m, share every star either saw there, seen once or not
    (:func:`_virtual_snapshots`), with no ghost of the long run but m's.  The same
    robust estimator and false-alarm test find ``v_x = R v_m``; then every
    snapshot y of the run gets ``A_y <- A_m R^T A_x^T A_y`` and the matched
    groups are merged.  Rounds repeat while a run joins (a run next to a
    newly joined one may now see enough), all runs of a round in one call.
    The work is bounded: only runs within ``max_skip`` snapshots of the
    longest are tried, and never twice from the same pair of snapshots.

    Returns (to_common, component, groups), updated.
    """
    to_common, component, groups = to_common.copy(), component.copy(), groups.copy()
    settings = _link_settings(p, chord_px, camera.width * camera.height)
    tried = set()
    while True:
        main = int(np.argmax(np.bincount(component)))
        if np.sum(component == main) < 2:
            return to_common, component, groups
        pairs = [(c, x, m) for c, x, m in _nearest_snapshots(component, main)
                 if abs(x - m) <= p.max_skip and (x, m) not in tried]
        if not pairs:
            return to_common, component, groups
        tried.update((x, m) for _, x, m in pairs)
        views = [view for c, x, m in pairs for view in ((main, m), (c, x))]
        common = _rotate(to_common[snap], vectors)
        points, bright, valid, label = _virtual_snapshots(camera, common, brightness, snap, component, groups,
                                                          usable, to_common, views)
        links = np.arange(len(views)).reshape(-1, 2)
        found = estimate_pair_rotations(points, _brightest_sources(valid, bright, p.hypothesis_sources), links,
                                        **settings)
        joined = np.flatnonzero(np.isfinite(found.rotation[:, 0, 0]))
        if len(joined) == 0:
            return to_common, component, groups
        relabel = np.arange(len(groups))
        for k in joined:
            c, x, m = pairs[k]
            run = component == c
            # v_x = R v_m, v_c = A_m v_m  =>  v_c = A_m R^T v_x = A_m R^T A_x^T (A_y v_y)
            to_common[run] = to_common[m] @ found.rotation[k].T @ to_common[x].T @ to_common[run]
            component[run] = main
            matched = np.flatnonzero(found.matches[k] >= 0)
            relabel[label[2 * k + 1, found.matches[k, matched]]] = label[2 * k, matched]
        groups = relabel[groups]


def _refine_to_common(vectors: np.ndarray, snap: np.ndarray, label: np.ndarray,
                      to_common: np.ndarray) -> np.ndarray:
    """Each snapshot's rotation into the common frame re-solved against track means (Wahba).

    Only labels with two or more sightings count; snapshots with fewer than
    two such sightings keep their rotation.  Snapshot s's new rotation is the
    R minimising sum |mean - R v|^2 over its sightings v
    (:func:`app.extraction.motion.wahba_rotations`).
    """
    profiles, counts = _snapshot_profiles(vectors, snap, label, to_common)
    return np.where((counts >= 2)[:, None, None], wahba_rotations(profiles), to_common)


@njit
def _snapshot_profiles(vectors, snap, label, to_common):
    """Each snapshot's attitude profile against the track means, B_s = sum mean v^T over its sightings v in
    a track of two or more, and the number of those sightings.

    A track's mean is the normalised sum of its sightings carried into the common frame (``A_s v``).
    Labels are below the number of sources.
    """
    m = label.shape[0]
    size = np.zeros(m, dtype=np.int64)
    for i in range(m):
        if label[i] >= 0:
            size[label[i]] += 1
    sums = np.zeros((m, 3))
    for i in range(m):
        if label[i] >= 0 and size[label[i]] >= 2:
            A = to_common[snap[i]]
            for r in range(3):
                sums[label[i], r] += A[r, 0] * vectors[i, 0] + A[r, 1] * vectors[i, 1] + A[r, 2] * vectors[i, 2]
    profiles = np.zeros((to_common.shape[0], 3, 3))
    counts = np.zeros(to_common.shape[0], dtype=np.int64)
    for i in range(m):
        if label[i] >= 0 and size[label[i]] >= 2:
            t = label[i]
            norm = np.sqrt(sums[t, 0] * sums[t, 0] + sums[t, 1] * sums[t, 1] + sums[t, 2] * sums[t, 2])
            for r in range(3):
                for c in range(3):
                    profiles[snap[i], r, c] += sums[t, r] / norm * vectors[i, c]
            counts[snap[i]] += 1
    return profiles, counts


def _same_pixel_pairs(xy: np.ndarray, snap: np.ndarray, tol: float,
                      max_partners: int = DEFAULT_PARAMETERS.max_pixel_partners) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (m, n), both orders, of sources of different snapshots within ``tol`` pixels.

    Sorting by x and expanding the x-windows keeps this near-linear.  Each
    source examines at most ``max_partners`` neighbours in x on either side
    (real telemetry has a handful within a few pixels); without that bound a
    file with every source on one pixel would make 16 million pairs.
    """
    order = np.argsort(xy[:, 0], kind="stable")
    xs = xy[order, 0]
    here = np.arange(len(xs))
    lo = np.maximum(np.searchsorted(xs, xs - tol, side="left"), here - max_partners)
    hi = np.minimum(np.searchsorted(xs, xs + tol, side="right"), here + max_partners + 1)
    i, j = expand_ranges(lo, hi)
    a, b = order[i], order[j]
    d = xy[a] - xy[b]
    keep = (snap[a] != snap[b]) & (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] < tol * tol)
    return a[keep], b[keep]


def _predicted_pixels(camera, to_common: np.ndarray, common: np.ndarray) -> np.ndarray:
    """(M, S, 2): where each common-frame direction appears in every snapshot (A_s^T w)."""
    local = np.matmul(common[None], to_common)  # (S, M, 3) rows w^T A_s
    xy, _ = camera.vectors_to_pixels(local.reshape(-1, 3))
    return xy.reshape(to_common.shape[0], common.shape[0], 2).transpose(1, 0, 2)


def _hot_pixels(xy: np.ndarray, snap: np.ndarray, comp: np.ndarray, predicted: np.ndarray,
                hot_tol: float, gate: float, max_partners: int) -> np.ndarray:
    """(M,) hot-pixel flags of the flattened sources (module docstring, step 4)."""
    m = len(snap)
    rows, cols = _same_pixel_pairs(xy, snap, hot_tol, max_partners)
    linked = comp[rows] == comp[cols]
    rows, cols = rows[linked], cols[linked]
    with np.errstate(invalid="ignore"):
        # the row source's sky point, carried into the column source's snapshot
        carried = np.hypot(*(predicted[rows, snap[cols]] - xy[cols]).T) < gate
    n_fixed = np.bincount(rows[~carried], minlength=m)
    strong = n_fixed >= 2
    hot = strong.copy()
    # One stationary partner: hot only if neither it nor the partner has
    # another sighting that moved with the sky (a ghost that happens to
    # fall on a star's pixel of another snapshot is not a hot pixel).
    fixed_pair = ~carried & (n_fixed[rows] == 1)
    single, partner = rows[fixed_pair], cols[fixed_pair]
    if len(single):
        involved = np.unique(np.concatenate([single, partner]))
        n_sky = np.zeros(m, dtype=int)
        # (k, M) comparisons in blocks: a crafted file can involve every one of 4096 sources
        step = max(1, (1 << 20) // max(m, 1))
        for start in range(0, len(involved), step):
            block = involved[start:start + step]
            pred = predicted[block][:, snap]  # (k, M, 2)
            with np.errstate(invalid="ignore"):
                moved = np.hypot(pred[..., 0] - xy[None, :, 0], pred[..., 1] - xy[None, :, 1]) < gate
            moved &= (snap[block, None] != snap[None, :]) & (comp[block, None] == comp[None, :])
            n_sky[block] = moved.sum(axis=1)
        hot[single] = (n_sky[single] <= 1) & (n_sky[partner] <= 1)
    # the stationary companions of a clear hot pixel are hot too: in the
    # middle of a slow drift they have fewer partners the sky moved away from
    hot[rows[strong[cols]]] = True
    return hot


def _associate(common: np.ndarray, snap: np.ndarray, comp: np.ndarray, usable: np.ndarray,
               gate_chord: float) -> np.ndarray:
    """(M,) track label per flattened source (-1 unusable), snapshots visited in order.

    Costs are 1 - cos(angle) = chord^2 / 2, monotonic in the angle.  The loop over snapshots, with the
    tracks' means updated after each, is :func:`_associate_kernel`.  Where two sources of a snapshot want
    one track it stops and hands back that snapshot's costs; the optimal one-to-one assignment decides
    (scipy's ``linear_sum_assignment``, pairs beyond the gate costing more than any within it), and the
    kernel goes on from that snapshot with the pairs it chose.
    """
    m = len(snap)
    bounds = np.searchsorted(snap, np.arange(snap.max(initial=-1) + 2))
    max_cost = gate_chord**2 / 2.0
    label, sums, means, track_comp = np.full(m, -1), np.zeros((m, 3)), np.zeros((m, 3)), np.full(m, -1)
    start, settled, chosen = 0, False, np.full((0, 2), -1)
    while True:
        start, cost = _associate_kernel(common, comp, usable, bounds, max_cost, label, sums, means, track_comp,
                                        start, settled, chosen)
        if start < 0:
            return label
        # Imported here: scipy.optimize costs ~0.1 s at start-up and few sequences come here.
        from scipy.optimize import linear_sum_assignment

        rows, cols = linear_sum_assignment(np.where(cost > max_cost, _TOO_FAR, cost))
        within = cost[rows, cols] <= max_cost
        settled, chosen = True, np.column_stack([rows[within], cols[within]])


#: Cost of a source-track pair beyond the gate in the assignment: more than any pair within it (<= 2).
_TOO_FAR = 10.0


@njit
def _associate_kernel(common, comp, usable, bounds, max_cost, label, sums, means, track_comp, start, settled,
                      chosen):
    """:func:`_associate`'s loop from snapshot ``start`` on; snapshot s's sources are ``bounds[s]:bounds[s + 1]``.

    Each usable source of a snapshot goes to the track of its component whose mean direction is nearest
    (least 1 - cos, the first on ties), within ``max_cost``; a source that starts no track starts a new one,
    numbered in order.  A track's mean is the normalised sum of its sightings, updated after each snapshot.
    ``label`` (per source), ``sums`` and ``means`` (per track, (M, 3)) and ``track_comp`` (each track's
    component, -1 past the last track) carry the tracks from call to call.  Where two sources want one
    track the kernel stops: it returns the snapshot and its (sources x candidate tracks) costs, and is
    called again from that snapshot, ``settled``, with ``chosen``: the (source, candidate) pairs to take
    there, numbered as the rows and columns of those costs (usable sources and the tracks of their
    component, in order).  Returns (-1, empty) at the end.
    (Plain loops: each numpy function in a kernel adds to the first run's compilation.)
    """
    m = common.shape[0]
    n_tracks = 0
    while n_tracks < m and track_comp[n_tracks] >= 0:
        n_tracks += 1
    idx = np.empty(m, dtype=np.int64)
    candidates = np.empty(m, dtype=np.int64)
    for s in range(start, bounds.shape[0] - 1):
        n = 0
        for i in range(bounds[s], bounds[s + 1]):
            if usable[i]:
                idx[n] = i
                n += 1
        if n == 0:
            continue
        n_cand = 0
        for t in range(n_tracks):
            if track_comp[t] == comp[idx[0]]:
                candidates[n_cand] = t
                n_cand += 1
        if n_cand:
            cost = np.empty((n, n_cand))
            for r in range(n):
                for k in range(n_cand):
                    t = candidates[k]
                    cost[r, k] = 1.0 - (common[idx[r], 0] * means[t, 0] + common[idx[r], 1] * means[t, 1]
                                        + common[idx[r], 2] * means[t, 2])
            col = np.full(n, -1)
            if settled and s == start:
                for k in range(chosen.shape[0]):
                    col[chosen[k, 0]] = chosen[k, 1]
            else:
                wanted = np.zeros(n_cand, dtype=np.int64)
                for r in range(n):
                    nearest = 0
                    for k in range(1, n_cand):
                        if cost[r, k] < cost[r, nearest]:
                            nearest = k
                    if cost[r, nearest] <= max_cost:
                        col[r] = nearest
                        wanted[nearest] += 1
                        if wanted[nearest] > 1:
                            return s, cost  # two sources want one track: the caller settles it
            for r in range(n):
                if col[r] >= 0:
                    t = candidates[col[r]]
                    label[idx[r]] = t
                    for d in range(3):
                        sums[t, d] += common[idx[r], d]
                    norm = np.sqrt(sums[t, 0] * sums[t, 0] + sums[t, 1] * sums[t, 1] + sums[t, 2] * sums[t, 2])
                    for d in range(3):
                        means[t, d] = sums[t, d] / norm
        for r in range(n):
            if label[idx[r]] < 0:
                label[idx[r]] = n_tracks
                for d in range(3):
                    sums[n_tracks, d] = means[n_tracks, d] = common[idx[r], d]
                track_comp[n_tracks] = comp[idx[r]]
                n_tracks += 1
    return -1, np.empty((0, 0))


@warm_up_with
def _warm_up_association() -> None:
    """Compile :func:`_associate_kernel` and :func:`_snapshot_profiles` for the arrays extraction passes (a
    settled snapshot's call has the same types: no need to import scipy.optimize at every start)."""
    common = np.array([[0.0, 0.0, 1.0], [0.0, 0.001, 1.0], [0.0, 0.0, 1.0], [0.0, 0.001, 1.0]])
    _associate(common, np.array([0, 0, 1, 1]), np.zeros(4, dtype=int), np.ones(4, dtype=bool), 0.01)
    _snapshot_profiles(common, np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]), np.tile(np.eye(3), (2, 1, 1)))


def _track_sizes(label: np.ndarray) -> np.ndarray:
    """(M,) number of sightings of each source's track (0 when unlabelled)."""
    if not np.any(label >= 0):
        return np.zeros(len(label), dtype=int)
    sizes = np.bincount(label[label >= 0])
    return np.where(label >= 0, sizes[np.maximum(label, 0)], 0)


def _track_sums(label: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """(T, 3) sum of the vectors of each label (rows of unused labels are 0)."""
    live = label >= 0
    n = int(label.max(initial=-1)) + 1
    # per coordinate, as np.add.at would add them (in order) but without its overhead
    return np.column_stack([np.bincount(label[live], vectors[live, k], n) for k in range(3)]).reshape(n, 3)


def _outliers(common: np.ndarray, label: np.ndarray, sigma_chord: float, p: ExtractionParameters,
              chord_px: float) -> np.ndarray:
    """(M,) outlier flags: sightings too far from the mean of their track's others."""
    outlier = np.zeros(len(label), dtype=bool)
    for _ in range(3):
        live = np.where(outlier, -1, label)
        size = _track_sizes(live)
        candidates = np.flatnonzero(size >= 2)
        if len(candidates) == 0:
            break
        sums = _track_sums(live, common)
        others = _normalized(sums[live[candidates]] - common[candidates])
        residual = _norms(common[candidates] - others)
        k = size[candidates]
        limit = np.maximum(p.outlier_floor_px * chord_px,
                           p.outlier_sigmas * sigma_chord * np.sqrt(1.0 + 1.0 / (k - 1)))
        excess = residual / limit
        bad = excess > 1.0
        if not np.any(bad):
            break
        # remove only the worst sighting of each track per round
        worst = np.full(int(label.max()) + 1, -np.inf)
        np.maximum.at(worst, live[candidates[bad]], excess[bad])
        outlier[candidates[bad & (excess >= worst[live[candidates]])]] = True
    return outlier


def _noise_sigma_px(residual_sq_px: np.ndarray, dof_factor: np.ndarray, p: ExtractionParameters) -> float:
    """Per-axis sigma from 2D residuals r with E|r|^2 = 2 sigma^2 dof_factor (median based)."""
    if len(residual_sq_px) < 5:
        return p.sigma_default_px
    scaled = residual_sq_px / dof_factor
    middle = len(scaled) // 2  # the upper median: np.median's overhead is most of the cost here
    # Squared chords computed as 2 - 2 cos can come out a rounding error below zero (exact matches).
    sigma = math.sqrt(max(0.0, float(np.partition(scaled, middle)[middle])) / _CHI2_2_MEDIAN)
    return min(max(sigma, p.sigma_min_px), p.sigma_max_px)


def _max_sky_motion_px(camera, motion: np.ndarray, members: np.ndarray) -> float:
    """Largest pixel shift of the field's centre and corners between ``members`` and the reference."""
    probe_xy, probe_vectors = _field_probes(camera)
    moved = np.matmul(motion[members], probe_vectors.T)  # (n, 3, 5)
    xy, _ = camera.vectors_to_pixels(np.swapaxes(moved, 1, 2).reshape(-1, 3))
    d = xy.reshape(len(members), len(probe_xy), 2) - probe_xy
    return float(np.nanmax(np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1])))  # numpy's norm, faster


@functools.lru_cache(maxsize=16)
def _field_probes(camera) -> tuple[np.ndarray, np.ndarray]:
    """The field's centre and corners (5, 2) and their camera-frame vectors (5, 3), made once per camera."""
    probe_xy = np.array([[camera.cx, camera.cy], [0, 0], [camera.width - 1, 0],
                         [0, camera.height - 1], [camera.width - 1, camera.height - 1]], dtype=float)
    vectors = camera.pixels_to_vectors(probe_xy)
    probe_xy.flags.writeable = vectors.flags.writeable = False
    return probe_xy, vectors


def _single_snapshot(sequence: Sequence, p: ExtractionParameters, hot: np.ndarray | None = None) -> Extraction:
    """Every source a one-sighting track, numbered in input order; ``hot`` (n,) flags known hot pixels,
    which are left out (verdict ``hot_pixel``)."""
    snapshot = sequence.snapshots[0]
    n = snapshot.n_sources
    if hot is None or not hot.any():
        kept = np.arange(n)
        track_of_source = np.arange(n)
        rejection = (None,) * n
        notes = ("single snapshot: nothing to track against, every source is a pattern point",)
    else:
        kept = np.flatnonzero(~hot)
        track_of_source = np.full(n, -1)
        track_of_source[kept] = np.arange(len(kept))
        rejection = tuple(HOT_PIXEL if h else None for h in hot)
        notes = ("single snapshot: nothing to track against, every source is a pattern point "
                 "except the known hot pixels",)
    tracks = tuple(Track(id=t, snapshots=np.array([0]), source_indices=np.array([k]),
                         xy=np.asarray(snapshot.xy[k:k + 1], dtype=float),
                         mean_brightness=float(snapshot.brightness[k])) for t, k in enumerate(kept))
    motion = np.eye(3)[None]
    noise = assumed_sighting_noise_px(sequence.camera, p.sigma_default_px)  # nothing to measure it against
    return Extraction(reference=0, track_of_source=(track_of_source,), rejection=(rejection,),
                      tracks=tracks, motion=motion,
                      pattern=tracks_pattern(sequence.camera, motion, tracks, noise),
                      seed_pattern=seed_pattern(sequence.camera, 0, tracks, noise), noise_px=noise, notes=notes)


def _no_sources(sequence: Sequence, p: ExtractionParameters) -> Extraction:
    n_snap = len(sequence.snapshots)
    motion = np.full((n_snap, 3, 3), np.nan)
    motion[0] = np.eye(3)
    empty = (np.zeros(0, dtype=int),) * n_snap
    pattern = tracks_pattern(sequence.camera, motion, (), p.sigma_default_px)
    return Extraction(reference=0, track_of_source=empty, rejection=((),) * n_snap, tracks=(),
                      motion=motion, pattern=pattern, seed_pattern=pattern, noise_px=p.sigma_default_px,
                      notes=("no sources in any snapshot",))


def _known_hot_flags(sequence: Sequence, known_hot) -> tuple[np.ndarray, ...]:
    """``known_hot`` as one (n_i,) bool array per snapshot; ValueError when it does not fit the sequence."""
    if len(known_hot) != len(sequence.snapshots):
        raise ValueError(f"known_hot has {len(known_hot)} entries for {len(sequence.snapshots)} snapshots")
    flags = []
    for i, (snapshot, per) in enumerate(zip(sequence.snapshots, known_hot)):
        per = np.asarray(per, dtype=bool).reshape(-1)
        if per.shape[0] != snapshot.n_sources:
            raise ValueError(f"known_hot[{i}] has {per.shape[0]} flags for {snapshot.n_sources} sources")
        flags.append(per)
    return tuple(flags)


def extract(sequence: Sequence, parameters: ExtractionParameters = DEFAULT_PARAMETERS, *,
            known_hot=None) -> Extraction:
    """Tell tracked stars from ghosts, hot pixels and outliers (see the module docstring).

    ``known_hot``: per snapshot, a flag per source (input order) for sources known to be hot pixels
    (see the module docstring); they get the ``hot_pixel`` verdict.  The result records it as
    :attr:`Extraction.known_hot`.  Raises ValueError for a sequence without snapshots, or a
    ``known_hot`` that does not match the sequence's sources.
    """
    if not sequence.snapshots:
        raise ValueError("a sequence needs at least one snapshot")
    if known_hot is None:
        return _extract(sequence, parameters, None)
    flags = _known_hot_flags(sequence, known_hot)
    return dataclasses.replace(_extract(sequence, parameters, flags if any(f.any() for f in flags) else None),
                               known_hot=flags)


def _extract(sequence: Sequence, p: ExtractionParameters, known_hot: tuple[np.ndarray, ...] | None) -> Extraction:
    """:func:`extract` for a sequence with snapshots; ``known_hot`` None or flags with at least one set."""
    if len(sequence.snapshots) == 1:
        return _single_snapshot(sequence, p, None if known_hot is None else known_hot[0])
    if not any(s.n_sources for s in sequence.snapshots):
        return _no_sources(sequence, p)
    camera = sequence.camera
    n_snap = len(sequence.snapshots)
    chord_px = 1.0 / camera.focal_length_px  # chord of one pixel near the centre
    xy_pad, bright_pad, valid = _padded(sequence)
    # flattened sources, snapshot by snapshot (contiguous copies: the kernels are compiled for those)
    snap, index = (np.ascontiguousarray(k) for k in np.nonzero(valid))
    xy = xy_pad[snap, index]
    vectors = camera.pixels_to_vectors(xy)
    vectors_pad = np.full(xy_pad.shape[:2] + (3,), np.nan)
    vectors_pad[snap, index] = vectors
    flat_of = np.full(valid.shape, -1)
    flat_of[snap, index] = np.arange(len(snap))
    known = None if known_hot is None else np.concatenate(known_hot)  # flattened order is (snapshot, source)

    # 1. motion, without recurring sources while they are a minority (and never known hot pixels)
    rows, _ = _same_pixel_pairs(xy, snap, p.hot_tol_floor_px, p.max_pixel_partners)
    recurring = np.bincount(rows, minlength=len(snap)) >= 2
    motion_valid = valid.copy()
    if 0 < recurring.sum() < 0.5 * len(snap):
        motion_valid[snap[recurring], index[recurring]] = False
    if known is not None:
        motion_valid[snap[known], index[known]] = False
    motion_vectors = np.where(motion_valid[..., None], vectors_pad, 0.0)  # zero rows never match
    to_common, component, used, link_sq = _chain_motions(motion_vectors, bright_pad, motion_valid,
                                                         chord_px, camera.width * camera.height, p)
    groups = _linked_groups(used, flat_of, len(snap))
    to_common, component, groups = _rejoin_components(camera, vectors, bright_pad[snap, index],
                                                      snap, motion_valid[snap, index], groups, to_common,
                                                      component, chord_px, p)
    comp = component[snap]

    # 2. refinement against the provisional tracks of the links' matches
    to_common = _refine_to_common(vectors, snap, groups, to_common)
    common = _rotate(to_common[snap], vectors)

    # 3. noise; link residuals are differences of two sightings: E|r|^2 = 2 sigma^2 * 2
    sigma = _noise_sigma_px(link_sq / chord_px**2, np.full(len(link_sq), 2.0), p)
    gate = max(p.link_gate_floor_px, p.link_gate_sigmas * sigma)
    hot_tol = max(p.hot_tol_floor_px, p.hot_tol_sigmas * sigma)

    # 4. hot pixels, 5. association
    hot = _hot_pixels(xy, snap, comp, _predicted_pixels(camera, to_common, common), hot_tol, gate,
                      p.max_pixel_partners)
    if known is not None:
        hot |= known
    linked_snapshot = np.bincount(component)[comp] >= 2  # a lone snapshot has nothing to track against
    label = _associate(common, snap, comp, ~hot & linked_snapshot, gate * chord_px)
    # the full tracks (gaps bridged, more stars per snapshot) pin the rotations better
    to_common = _refine_to_common(vectors, snap, label, to_common)
    common = _rotate(to_common[snap], vectors)

    # 6. outliers, with the noise re-estimated from the tracks themselves
    size = _track_sizes(label)
    tracked = size >= 2
    if np.any(tracked):
        mean = _normalized(_track_sums(label, common)[label[tracked]])
        d = common[tracked] - mean
        residual_sq = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]) / chord_px**2
        sigma = _noise_sigma_px(residual_sq, 1.0 - 1.0 / size[tracked], p)
    outlier = _outliers(common, np.where(tracked, label, -1), sigma * chord_px, p, chord_px)
    cut = np.where(outlier, -1, label)
    kept = _track_sizes(cut) >= 2
    # only a sighting cut from a track that survives is an outlier; the
    # members of a track that dissolved had no consistent partner (ghosts)
    survivors = np.zeros(int(label.max(initial=0)) + 1, dtype=bool)
    survivors[cut[kept]] = True
    outlier &= survivors[np.maximum(label, 0)] & (label >= 0)
    label = np.where(kept, cut, -1)

    # 7. verdicts; the reference has the most tracked sources (first on ties)
    per_snapshot = np.bincount(snap[label >= 0], minlength=n_snap)
    reference = int(np.argmax(per_snapshot))
    same = component == component[reference]
    motion = np.full((n_snap, 3, 3), np.nan)
    motion[same] = np.matmul(to_common[reference].T, to_common[same])
    tracks, track_of_source, rejection = _verdicts(sequence, snap, index, label, hot, outlier, xy)

    notes = []
    sky_motion = _max_sky_motion_px(camera, motion, np.flatnonzero(same))
    if tracks and 2 * sky_motion < gate:
        notes.append(f"the sky moved at most {sky_motion:.1f} px from the reference snapshot: hot pixels "
                     f"cannot be told from stars and stationary sources are kept as tracks")
    if not tracks:
        notes.append("no source was seen moving consistently with the sky in two snapshots: no tracks")
    carried = carried_tracks(tracks, motion)
    if len(carried) < len(tracks):
        notes.append(f"{len(tracks) - len(carried)} track(s) in snapshots not linked to the reference "
                     f"snapshot are left out of the pattern")
    return Extraction(reference=reference, track_of_source=track_of_source, rejection=rejection,
                      tracks=tracks, motion=motion, pattern=tracks_pattern(camera, motion, carried, sigma),
                      seed_pattern=seed_pattern(camera, reference, tracks, sigma), noise_px=sigma,
                      notes=tuple(notes))


def _verdicts(sequence: Sequence, snap: np.ndarray, index: np.ndarray, label: np.ndarray,
              hot: np.ndarray, outlier: np.ndarray, xy: np.ndarray):
    """Tracks numbered by first appearance, and per-source track ids and reasons."""
    # flattened order is (snapshot, source) order, so first occurrences number the tracks
    labels_in_order = label[label >= 0]
    _, first = np.unique(labels_in_order, return_index=True)
    old_ids = labels_in_order[np.sort(first)]
    new_id = np.full(max(1, int(label.max(initial=-1)) + 1), -1, dtype=int)
    new_id[old_ids] = np.arange(len(old_ids))
    track_id = np.where(label >= 0, new_id[np.maximum(label, 0)], -1)

    brightness = np.concatenate([np.asarray(s.brightness, dtype=float) for s in sequence.snapshots])
    in_track = np.flatnonzero(track_id >= 0)
    by_track = in_track[np.argsort(track_id[in_track], kind="stable")]  # stable: snapshot order kept
    sizes = np.bincount(track_id[in_track], minlength=len(old_ids))
    ends = np.cumsum(sizes).tolist()
    mean_brightness = np.bincount(track_id[in_track], brightness[in_track], len(old_ids)) / np.maximum(sizes, 1)
    snaps, indices, points = snap[by_track], index[by_track], xy[by_track]
    tracks = tuple(Track(id=tid, snapshots=snaps[start:end], source_indices=indices[start:end], xy=points[start:end],
                         mean_brightness=b)
                   for tid, (start, end, b) in enumerate(zip([0] + ends[:-1], ends, mean_brightness.tolist())))

    reason = np.full(len(label), GHOST, dtype=object)
    reason[outlier] = OUTLIER
    reason[hot] = HOT_PIXEL
    reason[track_id >= 0] = None
    bounds = np.searchsorted(snap, np.arange(len(sequence.snapshots) + 1)).tolist()
    reasons = reason.tolist()
    # every source of a snapshot is in the flattened list, in input order
    track_of_source = tuple(track_id[start:end].copy() for start, end in zip(bounds[:-1], bounds[1:]))
    rejection = tuple(tuple(reasons[start:end]) for start, end in zip(bounds[:-1], bounds[1:]))
    return tracks, track_of_source, rejection
