"""The extraction's compiled kernels against the numpy code they replaced, kept here as the reference.

Each kernel of :mod:`app.extraction` replaced numpy code; that code
survives only here, run on the same inputs as the kernel: random ones built
to reach every branch (two sources claiming one track, several runs of
snapshots, padding, ties) and the real inputs of simulated sequences.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from app.attitude.rotations import rotation_from_rotvec
from app.camera import CAMERAS
from app.extraction import extract, linking, motion
from app.extraction.assignment import min_cost_assignment
from app.simulate import simulate_sequence


def _normalized(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt((v * v).sum(axis=-1, keepdims=True))


# --- the numpy association, as it was before the kernel -------------------------------------------------

def associate_reference(common, snap, comp, usable, gate_chord):
    """linking._associate before the kernel: the loop over snapshots in numpy, scipy's assignment."""
    label = np.full(len(snap), -1, dtype=int)
    sums = np.zeros((len(snap), 3))
    means = np.zeros((len(snap), 3))
    track_comp = np.full(len(snap), -1)
    n_tracks = 0
    max_cost = gate_chord**2 / 2.0
    too_far = 10.0
    conflicts = 0
    bounds = np.searchsorted(snap, np.arange(snap.max(initial=-1) + 2))
    for s in range(len(bounds) - 1):
        idx = np.arange(bounds[s], bounds[s + 1])[usable[bounds[s]:bounds[s + 1]]]
        if len(idx) == 0:
            continue
        assigned = np.zeros(len(idx), dtype=bool)
        candidates = np.flatnonzero(track_comp[:n_tracks] == comp[idx[0]])
        if len(candidates):
            cost = 1.0 - common[idx] @ means[candidates].T
            nearest = np.argmin(cost, axis=1)
            rows = np.flatnonzero(cost[np.arange(len(idx)), nearest] <= max_cost)
            cols = nearest[rows]
            if len(np.unique(cols)) < len(cols):
                conflicts += 1
                cost[cost > max_cost] = too_far
                rows, cols = linear_sum_assignment(cost)
                keep = cost[rows, cols] < too_far
                rows, cols = rows[keep], cols[keep]
            tracks = candidates[cols]
            label[idx[rows]] = tracks
            sums[tracks] += common[idx[rows]]
            means[tracks] = _normalized(sums[tracks])
            assigned[rows] = True
        new = idx[~assigned]
        fresh = n_tracks + np.arange(len(new))
        label[new] = fresh
        sums[fresh] = means[fresh] = common[new]
        track_comp[fresh] = comp[new]
        n_tracks += len(new)
    return label, conflicts


def _random_association(rng):
    """A sequence's sources in the common frame: stars seen with noise and dropouts, ghosts, doubles.

    Stars lie within ~0.1 rad of the boresight; each snapshot sees most of them with a noise of about a
    third of the gate, adds ghosts, and now and then a second source right beside a star (two sources
    wanting one track).  Snapshots belong to one, two or three runs (components).
    """
    n_snap = int(rng.integers(2, 12))
    n_stars = int(rng.integers(1, 25))
    stars = _normalized(np.column_stack([rng.normal(0, 0.1, (n_stars, 2)), np.ones(n_stars)]))
    gate = 10 ** rng.uniform(-3.5, -2)
    runs = np.sort(rng.integers(0, int(rng.integers(1, 4)), n_snap))
    rows, snap = [], []
    for s in range(n_snap):
        seen = stars[rng.random(n_stars) < 0.8]
        doubles = seen[rng.random(len(seen)) < 0.15]
        n_ghosts = int(rng.integers(0, 4))
        ghosts = _normalized(np.column_stack([rng.normal(0, 0.1, (n_ghosts, 2)), np.ones(n_ghosts)]))
        points = np.concatenate([seen + rng.normal(0, gate / 3, seen.shape),
                                 doubles + rng.normal(0, gate / 3, doubles.shape), ghosts])
        points = _normalized(points[rng.permutation(len(points))])
        rows.append(points)
        snap += [s] * len(points)
    snap = np.array(snap, dtype=int)
    common = np.concatenate(rows) if rows else np.zeros((0, 3))
    usable = rng.random(len(snap)) < 0.9
    return common, snap, runs[snap], usable, gate


def test_association_kernel_matches_the_numpy_loop_on_random_sequences():
    rng = np.random.default_rng(27)
    conflicts = 0
    for _ in range(400):
        common, snap, comp, usable, gate = _random_association(rng)
        expected, n = associate_reference(common, snap, comp, usable, gate)
        conflicts += n
        np.testing.assert_array_equal(linking._associate(common, snap, comp, usable, gate), expected)
    assert conflicts > 50  # the optimal assignment was needed often, not only the nearest tracks


@pytest.mark.parametrize("shape", [(1, 1), (3, 3), (2, 5), (5, 2), (7, 4), (4, 7)])
def test_min_cost_assignment_gives_scipys_pairs(shape):
    """Random costs, costs with many ties (small integers), and gated costs (most at one large value)."""
    rng = np.random.default_rng(shape)
    for k in range(300):
        if k % 3 == 0:
            cost = rng.random(shape)
        elif k % 3 == 1:
            cost = rng.integers(0, 3, shape).astype(float)
        else:
            cost = np.where(rng.random(shape) < 0.6, 10.0, rng.random(shape) * 1e-4)
        rows, cols = min_cost_assignment(cost)
        expected_rows, expected_cols = linear_sum_assignment(cost)
        np.testing.assert_array_equal(rows, expected_rows)
        np.testing.assert_array_equal(cols, expected_cols)


def test_min_cost_assignment_finds_the_optimum_a_greedy_choice_misses():
    # Row 0's cheapest column is 0, but giving it to row 1 (which has no other good column) is cheaper overall.
    cost = np.array([[1.0, 2.0], [1.5, 9.0]])
    rows, cols = min_cost_assignment(cost)
    assert list(zip(rows, cols)) == [(0, 1), (1, 0)]
    assert cost[rows, cols].sum() == 3.5


# --- the numpy scoring of rotation hypotheses, as it was before the kernel ------------------------------

def scores_reference(rotation, va_index, vb_index, vectors, score_gate):
    """motion._scores before the kernel: batched matmuls, in chunks of bounded memory."""
    n = vectors.shape[1]
    step = max(1, (1 << 21) // max(1, n * n))
    score = np.empty(len(rotation))
    for start in range(0, len(rotation), step):
        part = slice(start, start + step)
        pred = np.matmul(vectors[va_index[part]], np.swapaxes(rotation[part], -1, -2))
        dots = np.matmul(pred, np.swapaxes(vectors[vb_index[part]], -1, -2))
        d2 = 2.0 - 2.0 * dots.max(axis=2)
        score[part] = np.clip(1.0 - d2 / score_gate**2, 0.0, None).sum(axis=1)
    return score


def _score_rounding(vectors, gate):
    """How far two roundings of the scores may differ: a dot product near 1 is known to a few 1e-16 (numpy's
    matmul fuses its multiply-adds, the kernel does not), and each of the n terms divides 2 - 2 dot by g^2."""
    return vectors.shape[1] * 1e-15 / gate**2


def _random_snapshots(rng, n_snap, n, spread=0.15):
    """(n_snap, n, 3) one star field seen turned by (n_snap, 3, 3) small rotations, with noise, its ghosts
    and dropouts, the tail of each snapshot zero padding; and the rotations (v_s = R_s v)."""
    sky = _normalized(np.column_stack([rng.normal(0, spread, (n, 2)), np.ones(n)]))
    turn = rotation_from_rotvec(rng.normal(0, 0.03, (n_snap, 3)))
    vectors = _normalized(np.matmul(sky, np.swapaxes(turn, 1, 2)) + rng.normal(0, 1e-3, (n_snap, n, 3)))
    for s in range(n_snap):
        vectors[s] = vectors[s, rng.permutation(n)]
        ghosts = rng.random(n) < 0.2
        vectors[s, ghosts] = _normalized(np.column_stack([rng.normal(0, spread, (ghosts.sum(), 2)),
                                                         np.ones(ghosts.sum())]))
        vectors[s, int(rng.integers(1, n + 1)):] = 0.0
    return vectors, turn


def test_scores_kernel_matches_the_numpy_scores_on_random_hypotheses():
    """Snapshots related by small rotations; hypotheses near the true ones, some far off."""
    rng = np.random.default_rng(5)
    scoring, h = 0, 500
    for n in (1, 3, 10, 17, 40):
        vectors, turn = _random_snapshots(rng, 6, n)
        va, vb = rng.integers(0, 6, h), rng.integers(0, 6, h)
        error = rotation_from_rotvec(rng.normal(0, 0.003, (h, 3)) * rng.choice([1, 10], (h, 1)))
        rotation = error @ turn[vb] @ np.swapaxes(turn[va], 1, 2)  # v_b = R v_a, give or take the error
        gate = 0.01
        score = motion._scores(rotation, va, vb, vectors, gate)
        expected = scores_reference(rotation, va, vb, vectors, gate)
        scoring += np.count_nonzero(expected)
        np.testing.assert_allclose(score, expected, rtol=0, atol=_score_rounding(vectors, gate))
    assert scoring > 5 * h / 3  # many hypotheses score, not only zeros


@pytest.fixture(scope="module")
def recorded_calls():
    """The arguments of the extraction's kernels while extracting simulated sequences (ghosts, three cameras)."""
    calls = {"scores": []}
    scores = motion._scores

    def record_scores(*args):
        calls["scores"].append(args)
        return scores(*args)

    motion._scores = record_scores
    try:
        rng = np.random.default_rng(3)
        for scenario in ("ghosts3", "nominal", "sparse"):
            for camera in CAMERAS.values():
                extract(simulate_sequence(rng, camera, scenario)[0])
    finally:
        motion._scores = scores
    return calls


def test_scores_kernel_matches_the_numpy_scores_on_real_hypotheses(recorded_calls):
    assert len(recorded_calls["scores"]) >= 9
    for args in recorded_calls["scores"]:
        vectors, gate = args[3], args[4]
        np.testing.assert_allclose(motion._scores(*args), scores_reference(*args), rtol=0,
                                   atol=_score_rounding(vectors, gate))
