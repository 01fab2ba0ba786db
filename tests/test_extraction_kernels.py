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

from app.attitude import solve_wahba
from app.attitude.rotations import rotation_from_rotvec
from app.camera import CAMERAS
from app.extraction import extract, linking, motion
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
    """The arguments of the extraction's kernels (and of the numpy steps around them) while extracting
    simulated sequences of the three cameras."""
    kernels = {"scores": (motion, "_scores"), "mutual_matches": (motion, "_mutual_matches"),
               "refit": (motion, "_refit"), "refine_to_common": (linking, "_refine_to_common")}
    originals = {name: getattr(module, attribute) for name, (module, attribute) in kernels.items()}
    calls = {name: [] for name in kernels}

    def recorder(name):
        def record(*args):
            calls[name].append(tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args))
            return originals[name](*args)
        return record

    for name, (module, attribute) in kernels.items():
        setattr(module, attribute, recorder(name))
    try:
        rng = np.random.default_rng(3)
        for scenario in ("ghosts3", "nominal", "sparse"):
            for camera in CAMERAS.values():
                extract(simulate_sequence(rng, camera, scenario)[0])
    finally:
        for name, (module, attribute) in kernels.items():
            setattr(module, attribute, originals[name])
    return calls


def test_scores_kernel_matches_the_numpy_scores_on_real_hypotheses(recorded_calls):
    assert len(recorded_calls["scores"]) >= 9
    for args in recorded_calls["scores"]:
        vectors, gate = args[3], args[4]
        np.testing.assert_allclose(motion._scores(*args), scores_reference(*args), rtol=0,
                                   atol=_score_rounding(vectors, gate))


# --- the numpy mutual matches and Wahba re-solves, as they were before the kernels ---------------------

def mutual_matches_reference(rotation, va_index, vb_index, vectors, gate_sq):
    """motion's nearest chords and mutual matches before the kernel: (H, N, N) chords, argmins both ways;
    returned as the kernel returns them (matches -1 and squared chords 0 where not mutual)."""
    va, vb = vectors[va_index], vectors[vb_index]
    d2 = 2.0 - 2.0 * np.matmul(np.matmul(va, np.swapaxes(rotation, -1, -2)), np.swapaxes(vb, -1, -2))
    nearest_b = np.argmin(d2, axis=2)
    nearest_a = np.argmin(d2, axis=1)
    back = np.take_along_axis(nearest_a, nearest_b, axis=1)
    best = np.take_along_axis(d2, nearest_b[..., None], axis=2)[..., 0]
    mutual = (back == np.arange(d2.shape[1])) & (best < gate_sq)
    return np.where(mutual, nearest_b, -1), np.where(mutual, best, 0.0)


def refit_reference(rotation, va_index, vb_index, vectors, gate):
    """motion._refit before the kernels: numpy matches, app.attitude.solve_wahba (SVD)."""
    va, vb = vectors[va_index], vectors[vb_index]
    match, _ = mutual_matches_reference(rotation, va_index, vb_index, vectors, gate**2)
    mutual = match >= 0
    refined = solve_wahba(np.take_along_axis(vb, np.maximum(match, 0)[..., None], axis=1), va, mutual.astype(float))
    return np.where((mutual.sum(axis=1) >= 2)[:, None, None], refined, rotation)


def _random_hypotheses(rng, n, h=300):
    """Hypotheses relating random snapshots (see _random_snapshots): the true rotation give or take an
    error, some far off."""
    vectors, turn = _random_snapshots(rng, 6, n)
    va, vb = rng.integers(0, 6, h), rng.integers(0, 6, h)
    error = rotation_from_rotvec(rng.normal(0, 2e-3, (h, 3)) * rng.choice([1, 30], (h, 1)))
    return error @ turn[vb] @ np.swapaxes(turn[va], 1, 2), va, vb, vectors


def _assert_same_matches(rotation, va, vb, vectors, gate_sq):
    match, match_sq, profiles = motion._mutual_matches(rotation, va, vb, vectors, gate_sq)
    expected_match, expected_sq = mutual_matches_reference(rotation, va, vb, vectors, gate_sq)
    np.testing.assert_array_equal(match, expected_match)
    np.testing.assert_allclose(match_sq, expected_sq, rtol=0, atol=1e-15)
    # the profile solve_wahba forms from the matches: B = (w v_b)^T v_a
    body = np.take_along_axis(vectors[vb], np.maximum(match, 0)[..., None], axis=1) * (match >= 0)[..., None]
    np.testing.assert_allclose(profiles, np.swapaxes(body, 1, 2) @ vectors[va], rtol=0, atol=1e-14)
    return np.count_nonzero(match >= 0)


def test_mutual_matches_kernel_matches_the_numpy_argmins_on_random_hypotheses():
    rng = np.random.default_rng(9)
    matched = sum(_assert_same_matches(*_random_hypotheses(rng, n), 0.005**2) for n in (1, 3, 10, 25, 40))
    assert matched > 2000


def test_mutual_matches_kernel_matches_the_numpy_argmins_on_real_hypotheses(recorded_calls):
    assert len(recorded_calls["mutual_matches"]) >= 27
    assert sum(_assert_same_matches(*args) for args in recorded_calls["mutual_matches"]) > 1000


def test_wahba_rotations_give_the_svd_optimum():
    """Random attitude profiles (half of them with a reflection as U V^T, which the SVD method must flip)
    and profiles of matched stars, as few as two."""
    rng = np.random.default_rng(21)
    profiles = rng.normal(size=(2000, 3, 3))
    U, _, Vt = np.linalg.svd(profiles)
    assert 0.4 < np.mean(np.linalg.det(U @ Vt) < 0) < 0.6
    expected = solve_wahba(np.swapaxes(profiles, 1, 2), np.broadcast_to(np.eye(3), profiles.shape))  # B = body^T I
    np.testing.assert_allclose(motion.wahba_rotations(profiles), expected, rtol=0, atol=1e-12)
    for n in (2, 3, 10):
        a = _normalized(np.column_stack([rng.normal(0, 0.1, (n, 2)), np.ones(n)]))
        turn = rotation_from_rotvec(rng.normal(0, 1.0, 3))
        b = a @ turn.T + rng.normal(0, 1e-4, (n, 3))
        rotation = motion.wahba_rotations((b.T @ a)[None])[0]
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(rotation) > 0
        # two stars 0.1 rad apart barely fix the turn about them: the two methods agree to 1e-10 there
        np.testing.assert_allclose(rotation, solve_wahba(b, a), rtol=0, atol=1e-12 if n > 2 else 1e-10)


def test_refit_matches_the_numpy_svd_refit(recorded_calls):
    rng = np.random.default_rng(10)
    for n in (3, 10, 25):
        rotation, va, vb, vectors = _random_hypotheses(rng, n)
        np.testing.assert_allclose(motion._refit(rotation, va, vb, vectors, 0.005),
                                   refit_reference(rotation, va, vb, vectors, 0.005), rtol=0, atol=1e-10)
    assert len(recorded_calls["refit"]) >= 18
    for args in recorded_calls["refit"]:
        np.testing.assert_allclose(motion._refit(*args), refit_reference(*args), rtol=0, atol=1e-10)


# --- the numpy re-solve of each snapshot's rotation into the common frame, before the kernel ----------

def refine_to_common_reference(vectors, snap, label, to_common):
    n_snap = len(to_common)
    sizes = np.bincount(label[label >= 0]) if np.any(label >= 0) else np.zeros(0, dtype=int)
    size = np.where(label >= 0, sizes[np.maximum(label, 0)] if len(sizes) else 0, 0)
    in_track = size >= 2
    if not np.any(in_track):
        return to_common
    common = np.matmul(to_common[snap], vectors[:, :, None])[:, :, 0]
    live = np.where(in_track, label, -1)
    sums = np.zeros((int(live.max()) + 1, 3))
    np.add.at(sums, live[live >= 0], common[live >= 0])
    means = _normalized(sums[label[in_track]])
    rows = snap[in_track]
    counts = np.bincount(rows, minlength=n_snap)
    slots = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)
    width = int(counts.max())
    body = np.zeros((n_snap, width, 3))
    ref = np.zeros((n_snap, width, 3))
    weight = np.zeros((n_snap, width))
    body[rows, slots] = means
    ref[rows, slots] = vectors[in_track]
    weight[rows, slots] = 1.0
    refined = solve_wahba(body, ref, weight)
    return np.where((counts >= 2)[:, None, None], refined, to_common)


def test_refine_to_common_matches_the_numpy_re_solve_on_random_tracks():
    """Stars seen from turned snapshots, rotations into the common frame a little off; labels with one
    sighting, unlabelled sources, and snapshots with fewer than two tracked sources (kept as they are)."""
    rng = np.random.default_rng(13)
    kept = 0
    for _ in range(200):
        n_snap, n_stars = int(rng.integers(2, 8)), int(rng.integers(1, 15))
        sky = _normalized(np.column_stack([rng.normal(0, 0.1, (n_stars, 2)), np.ones(n_stars)]))
        turn = rotation_from_rotvec(rng.normal(0, 0.03, (n_snap, 3)))
        seen = rng.random((n_snap, n_stars)) < 0.7
        snap, star = np.nonzero(seen)
        vectors = _normalized(np.einsum("kij,kj->ki", turn[snap], sky[star]) + rng.normal(0, 1e-4, (len(snap), 3)))
        label = np.where(rng.random(len(snap)) < 0.9, star, -1)
        to_common = rotation_from_rotvec(rng.normal(0, 1e-3, (n_snap, 3))) @ np.swapaxes(turn, 1, 2)
        refined = linking._refine_to_common(vectors, snap, label, to_common)
        expected = refine_to_common_reference(vectors, snap, label, to_common)
        # as few as two sightings, 0.1 rad apart, barely fix the turn about them (see the Wahba test)
        np.testing.assert_allclose(refined, expected, rtol=0, atol=1e-10)
        kept += int(np.sum(np.all(refined == to_common, axis=(1, 2))))
    assert kept > 20  # snapshots with too few tracked sources were among them


def test_refine_to_common_matches_the_numpy_re_solve_on_real_tracks(recorded_calls):
    assert len(recorded_calls["refine_to_common"]) >= 18
    for args in recorded_calls["refine_to_common"]:
        np.testing.assert_allclose(linking._refine_to_common(*args), refine_to_common_reference(*args),
                                   rtol=0, atol=1e-12)


# --- the warm-up compiles what extraction calls ----------------------------------------------------------

def test_extraction_calls_its_kernels_only_with_the_types_the_warm_up_compiled(monkeypatch):
    """A kernel called with other argument types (a strided array, another integer type) than its warm-up's
    compiles again, for a second or more, in the middle of a search.  The argument types of every call of
    every extraction kernel, while extracting sequences of six scenarios (single snapshots, ghosts, the
    Earth, sparse fields), with and without known hot pixels, must be among those the warm-ups passed."""
    import numba

    kernels = [(motion, "_scores"), (motion, "_mutual_matches"), (motion, "wahba_rotations"),
               (linking, "wahba_rotations"), (linking, "_associate_kernel"), (linking, "_snapshot_profiles")]
    seen = {"warm-up": set(), "extraction": set()}
    phase = ["warm-up"]

    def recorder(name, kernel):
        def record(*args):
            seen[phase[0]].add((name, tuple(numba.typeof(a) for a in args)))
            return kernel(*args)
        return record

    for module, name in kernels:
        monkeypatch.setattr(module, name, recorder(name.removeprefix("_"), getattr(module, name)))
    motion._warm_up_motion()
    linking._warm_up_association()
    phase[0] = "extraction"
    rng = np.random.default_rng(8)
    for scenario in ("nominal", "ghosts3", "single", "sparse", "earth", "planet"):
        for camera in CAMERAS.values():
            sequence = simulate_sequence(rng, camera, scenario)[0]
            extract(sequence)
            extract(sequence, known_hot=[np.arange(s.n_sources) % 5 == 0 for s in sequence.snapshots])
    # both sources of the second snapshot want the first track (the second track is beyond the gate): the
    # nearer one gets it, and the kernel is called again, settled
    common = _normalized(np.array([[0.0, 0.0, 1.0], [0.0, 1e-3, 1.0], [0.0, 1e-5, 1.0], [1.5e-5, 0.0, 1.0]]))
    assert linking._associate(common, np.array([0, 0, 1, 1]), np.zeros(4, dtype=int), np.ones(4, dtype=bool),
                              1e-4).tolist() == [0, 1, 0, 2]
    called = {name for name, _ in seen["extraction"]}
    assert called == {"scores", "mutual_matches", "wahba_rotations", "associate_kernel", "snapshot_profiles"}
    assert seen["extraction"] <= seen["warm-up"], seen["extraction"] - seen["warm-up"]
