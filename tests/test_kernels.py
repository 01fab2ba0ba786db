"""The compiled kernels (issue 27) against the numpy code they replaced, kept here as the reference.

Each kernel replaced numpy code in the program; that code survives only
here, where the two are run on the same inputs: random ones and the real
hypotheses of simulated patterns of the three cameras (true attitudes,
chance fits, ghosts, sparse fields), so that both small sets (the subset
search) and large ones (leave-one-out rejection) are compared.  The optics
fit's kernel is compared with the numpy Gauss-Newton of a calibration in
``tests/test_camera_fit.py``; the hypothesis check's with the KD-tree in
``tests/test_speed_equivalence.py``.
"""

from __future__ import annotations

import functools
from itertools import combinations

import numpy as np
import pytest

from app.attitude import solve_wahba
from app.identification.verify import (FINAL_REJECT_SIGMAS, RAYLEIGH_QUARTILE, SMALL_SET, Refined, StarField, chord,
                                       chord_to_angle,
                                       refine, refine_many)


# --- the numpy refinement, as it was before the kernel (commit 3319b75) -----------------------------------

def match_points_many(rotations: np.ndarray, pattern_vectors: np.ndarray, field: StarField,
                      tolerance_rad: np.ndarray, nearest: bool = True
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`match_points` for a stack of rotations (K, 3, 3): (K, m) arrays, one KD-tree query for all.

    ``tolerance_rad`` is (m,) or (K, m).  A KD-tree query of a dozen points
    costs ~50 microseconds of call overhead, more than the search itself:
    one query for every hypothesis of a batch pays it once.  With
    ``nearest=False`` the search stops at the largest tolerance (faster;
    the nearest angle is then inf where no star lies within it).
    """
    K, m = len(rotations), len(pattern_vectors)
    d, idx = _query(rotations, pattern_vectors, field, None if nearest else np.max(tolerance_rad))
    ang = chord_to_angle(d).reshape(K, m)
    return _assign(ang, idx.reshape(K, m), tolerance_rad) + (ang,)


def _query(rotations: np.ndarray, pattern_vectors: np.ndarray, field: StarField, within_rad: float | None = None):
    """Chord to the nearest star (and its field position) of every rotated point, flattened (K m,).

    ``within_rad``: stop the search there (the tree answers inf, angle pi, beyond it): enough to match at
    any tolerance up to it, and faster for the points far from every star.
    """
    sky = np.matmul(pattern_vectors[None], rotations).reshape(-1, 3)  # rows R^T p
    if within_rad is None:
        return field.tree.query(sky, k=1)
    # Slightly beyond the bound, so that rounding never loses a star at exactly the tolerance.
    return field.tree.query(sky, k=1, distance_upper_bound=float(chord(within_rad)) * (1 + 1e-9) + 1e-15)


def _assign(ang: np.ndarray, idx: np.ndarray, tolerance_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(star_of_point, residual) (K, m) from each point's nearest star (field position ``idx``, angle ``ang``)."""
    star = np.where(ang <= tolerance_rad, idx, -1)
    # One point per star: among points of one hypothesis claiming the same star, the closest keeps it.
    ordered = np.sort(star, axis=1)
    if ((ordered[:, 1:] == ordered[:, :-1]) & (ordered[:, 1:] >= 0)).any():
        k, i = np.nonzero(star >= 0)
        claimed = star[k, i]
        order = np.lexsort((ang[k, i], claimed, k))
        repeat = (claimed[order][1:] == claimed[order][:-1]) & (k[order][1:] == k[order][:-1])
        lose = order[1:][repeat]
        star[k[lose], i[lose]] = -1
    return star, np.where(star >= 0, ang, np.nan)


#: After the fit, a matched point whose leave-one-out residual exceeds this
#: many of its sigmas (or of the residuals' own robust scale, if larger) is
#: let go: a displaced star or a blend inside the match tolerance would bias
#: the fit.


#: Up to this many matched points, outliers are found by trying every subset.


@functools.lru_cache(maxsize=None)
def _subsets(n: int) -> np.ndarray:
    """(S, n) masks of every subset of at least 3 of n points, smallest first."""
    return np.array([[i in c for i in range(n)] for k in range(3, n + 1) for c in combinations(range(n), k)])


def consensus_subsets(body: np.ndarray, ref: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """:func:`consensus_subset` for G sets of n points at once: (G, n, 3), (G, n, 3), (G, n) -> (G, n)."""
    G, n = weights.shape
    if n == 3:  # one subset: it wins whether or not all three agree
        return np.ones((G, 3), dtype=bool)
    agree, chi2 = _subset_fits(body, ref, weights, _subsets(n))
    count = agree.sum(axis=-1)
    # Most points agreeing, then the smallest chi-square; the first subset on a tie.
    best = np.argmin(np.where(count == count.max(axis=1, keepdims=True), chi2, np.inf), axis=1)
    out = agree[np.arange(G), best]
    out[out.sum(axis=1) < 3] = True
    return out


def _subset_fits(body: np.ndarray, ref: np.ndarray, weights: np.ndarray,
                 subsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wahba's fit of each subset (S, n) of each set: which points agree with it (G, S, n), and its chi2 (G, S)."""
    sigma = 1.0 / np.sqrt(weights)
    w = subsets[None] * weights[:, None, :]  # (G, S, n)
    B = np.einsum("gsn,gni,gnj->gsij", w, body, ref)
    U, _, Vt = np.linalg.svd(B)
    D = np.broadcast_to(np.eye(3), B.shape).copy()
    D[..., 2, 2] = np.linalg.det(U) * np.linalg.det(Vt)
    R = U @ D @ Vt
    predicted = np.einsum("gsij,gnj->gsni", R, ref)
    b = body[:, None]
    resid = np.arctan2(np.linalg.norm(np.cross(b, predicted), axis=-1), np.sum(b * predicted, axis=-1))  # (G, S, n)
    agree = resid <= FINAL_REJECT_SIGMAS * sigma[:, None, :]
    chi2 = np.where(agree, (resid / sigma[:, None, :]) ** 2, 0.0).sum(axis=-1)
    return agree, chi2


def leave_one_out_residuals(body: np.ndarray, ref: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Angle between each ``body_i`` and ``R_(-i) ref_i``, with ``R_(-i)`` Wahba's fit without point i.

    All fits at once: ``B_(-i) = B - w_i b_i r_i^T``, a stack of 3x3 SVDs.
    """
    outer = weights[:, None, None] * body[:, :, None] * ref[:, None, :]
    B = outer.sum(axis=0)[None] - outer
    U, _, Vt = np.linalg.svd(B)
    d = np.linalg.det(U) * np.linalg.det(Vt)
    D = np.zeros((len(body), 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = U @ D @ Vt
    predicted = np.einsum("nij,nj->ni", R, ref)
    return np.arctan2(np.linalg.norm(np.cross(body, predicted), axis=1), np.sum(body * predicted, axis=1))


def _wahba_masked(pattern_vectors: np.ndarray, star_vectors: np.ndarray, weights: np.ndarray,
                  use: np.ndarray) -> np.ndarray:
    """Wahba's rotation of each row's points where ``use`` (K, m): a zero weight leaves a point out."""
    body = np.broadcast_to(pattern_vectors, star_vectors.shape)
    return solve_wahba(body, star_vectors, np.where(use, weights, 0.0))


def numpy_refine_many(rotations: np.ndarray, pattern_vectors: np.ndarray, weights: np.ndarray, field: StarField,
                final_tolerance_rad: np.ndarray, start_tolerance_rad: np.ndarray,
                iterations: int = 4) -> list[Refined]:
    """:func:`refine` of K hypotheses (rotations (K, 3, 3), start tolerances (K,)) at once.

    Why a batch: a refinement is some 150 small numpy operations (KD-tree
    queries, 3x3 SVDs) on a dozen points, where the call overhead is most of
    the cost; the steps of all hypotheses run as one operation each.  Each
    hypothesis follows exactly the steps :func:`refine` describes (its own
    number of iterations, its own outlier rejection), so its result does not
    depend on the others in the batch.
    """
    R = np.array(rotations, dtype=float).reshape(-1, 3, 3)
    K, m = len(R), len(pattern_vectors)
    start = np.broadcast_to(np.asarray(start_tolerance_rad, dtype=float).reshape(-1), (K,))
    final_tol = np.asarray(final_tolerance_rad, dtype=float)
    stars_xyz = field.vectors
    fitted = np.full((K, m), -1)
    active = np.ones(K, dtype=bool)
    have_final = np.zeros(K, dtype=bool)
    star = np.full((K, m), -1)
    resid = np.full((K, m), np.nan)
    # Only the stars within the tolerances are looked for while iterating (a bounded query is faster); the
    # nearest star of every point (the deviation) is asked for the rotations the iterations end at.
    for it in range(iterations):
        a = np.flatnonzero(active)
        if len(a) == 0:
            break
        f = it / max(1, iterations - 1)
        tol = np.maximum(final_tol, start[a, None] * (1 - f) + final_tol * f)
        d, idx = _query(R[a], pattern_vectors, field, np.max(tol))
        ang, idx = chord_to_angle(d).reshape(len(a), m), idx.reshape(len(a), m)
        s, _ = _assign(ang, idx, tol)
        go = (s >= 0).sum(axis=1) >= 2
        if it > 0:
            # Converged: refitting gives the same R, and once the final tolerance keeps these matches
            # too, so does every tolerance between.  (The final tolerance is the smallest: the same
            # query answers it.)
            same = go & (s == fitted[a]).all(axis=1)
            if same.any():
                f_star, f_resid = _assign(ang[same], idx[same], final_tol)
                done = (f_star == s[same]).all(axis=1)
                rows = a[same][done]
                star[rows], resid[rows] = f_star[done], f_resid[done]
                have_final[rows] = True
                go[np.flatnonzero(same)[done]] = False
        active[a[~go]] = False
        rows = a[go]
        if len(rows):
            s = s[go]
            R[rows] = _wahba_masked(pattern_vectors, stars_xyz[s], weights, s >= 0)
            fitted[rows] = s
    # The nearest star of every point under the rotations reached: the last match of the rows that
    # converged, the final match of the others, and every point's nearest star (the deviation).
    d, idx = _query(R, pattern_vectors, field)
    nearest, idx = chord_to_angle(d).reshape(K, m), idx.reshape(K, m)
    rest = np.flatnonzero(~have_final)
    if len(rest):
        star[rest], resid[rest] = _assign(nearest[rest], idx[rest], final_tol)
    sigma = 1.0 / np.sqrt(weights)
    if m >= 3:
        # Few points: leave-one-out cannot unmask two outliers among five, so
        # among the points near a star (twice the tolerance: a biased fit may
        # have pushed a good one out) the largest subset that fits within the
        # noise wins (ties: lowest chi-square).
        small = np.flatnonzero((star >= 0).sum(axis=1) <= SMALL_SET)
        near, _ = _assign(nearest[small], idx[small], 2 * final_tol)
        count = (near >= 0).sum(axis=1)
        fit = (count >= 3) & (count <= SMALL_SET)
        rejected = np.zeros((len(small), m), dtype=bool)
        for n in np.unique(count[fit]).tolist():
            g = np.flatnonzero(count == n)
            cols = np.nonzero(near[g] >= 0)[1].reshape(len(g), n)  # each row's points near a star, in order
            body = pattern_vectors[cols]
            ref = stars_xyz[near[g][np.arange(len(g))[:, None], cols]]
            agree = consensus_subsets(body, ref, weights[cols])
            R[small[g]] = solve_wahba(body, ref, np.where(agree, weights[cols], 0.0))
            rejected[g[:, None], cols] = ~agree
        rows = small[fit]
        if len(rows):
            d, idx = _query(R[rows], pattern_vectors, field)
            nearest[rows] = chord_to_angle(d).reshape(len(rows), m)
            fresh, f_resid = _assign(nearest[rows], idx.reshape(len(rows), m), final_tol)
            star[rows] = np.where(~rejected[fit] & (fresh >= 0), fresh, -1)
            resid[rows] = np.where(star[rows] >= 0, f_resid, np.nan)
    for k in np.flatnonzero((star >= 0).sum(axis=1) > SMALL_SET):
        # Judge each point by the fit of the others: an outlier cannot hide by pulling the fit.  (Large
        # sets are the true matches, one or two per search: one at a time.)
        s = star[k]
        for _ in range(max(1, m // 3)):
            ok = np.flatnonzero(s >= 0)
            if len(ok) <= SMALL_SET:  # small sets had their subset search; LOO needs redundancy
                break
            loo = leave_one_out_residuals(pattern_vectors[ok], stars_xyz[s[ok]], weights[ok])
            # The lower quartile: outliers pull the fit, inflating the others' residuals and the median.
            scale = np.maximum(sigma[ok], np.quantile(loo, 0.25) / RAYLEIGH_QUARTILE)
            worst = int(np.argmax(loo / scale))
            if loo[worst] <= FINAL_REJECT_SIGMAS * scale[worst]:
                break
            s = s.copy()
            s[ok[worst]] = -1
            keep = s >= 0
            R[k] = solve_wahba(pattern_vectors[keep], stars_xyz[s[keep]], weights[keep])
            star1, resid1, ang1 = match_points_many(R[k][None], pattern_vectors, field, final_tol)
            fresh, f_resid, nearest[k] = star1[0], resid1[0], ang1[0]
            s = np.where(keep & (fresh >= 0), fresh, -1)  # a rejected point stays out
            resid[k] = np.where(s >= 0, f_resid, np.nan)
        star[k] = s
    return [Refined(rotation=R[k], star_of_point=star[k], residual_rad=resid[k], nearest_rad=nearest[k])
            for k in range(K)]




# --- the comparisons ----------------------------------------------------------------------------------------

def _same(kernel, reference) -> None:
    """The same stars; the same rotations, residuals and nearest angles to rounding (1e-10 rad = 20 micro-arcsec:
    a Wahba fit of 3 points amplifies the last bits of the sums, which numpy's BLAS orders otherwise)."""
    for got, want in zip(kernel, reference):
        assert np.array_equal(got.star_of_point, want.star_of_point)
        np.testing.assert_allclose(got.rotation, want.rotation, rtol=0, atol=1e-10)
        np.testing.assert_allclose(got.residual_rad, want.residual_rad, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(got.nearest_rad, want.nearest_rad, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("name, scenario, seed", [("tubsat-752x582-20deg", "single", 21),
                                                  ("tubsat-752x582-20deg", "ghosts3", 22),
                                                  ("liebe-576x604-30deg", "sparse", 23),
                                                  ("narrow-1024x1024-12deg", "single", 24),
                                                  ("liebe-576x604-30deg", "nominal", 25)])
def test_the_compiled_refinement_is_the_numpy_refinement(sky, name, scenario, seed):
    """The best 40 hypotheses of a pattern's first batches and 40 chosen at random: the same stars, and the
    same rotations, residuals and nearest angles to rounding."""
    from app.camera import CAMERAS
    from app.extraction import extract
    from app.identification.candidates import prepare_pattern
    from app.identification.hypotheses import bright_pair_batches
    from app.identification.options import SearchOptions
    from app.identification.verify import check_hypotheses
    from app.simulate import simulate_sequence

    camera = CAMERAS[name]
    rng = np.random.default_rng(seed)
    sequence, _ = simulate_sequence(rng, camera, scenario)
    extraction = extract(sequence)
    sky = sky.for_camera(camera)
    p = prepare_pattern(extraction.pattern, camera, sequence.snapshots[extraction.reference].time, sky)
    hyp, tol, _ = next(bright_pair_batches(p, sky, SearchOptions()))
    n_match, dev = check_hypotheses(hyp.rotations, p.vectors, p.field, tol)
    chosen = np.r_[np.lexsort((dev, -n_match))[:40], rng.choice(len(hyp), 40)]
    kernel = refine_many(hyp.rotations[chosen], p.vectors, p.weights, p.field, p.match_tol, tol[chosen])
    reference = numpy_refine_many(hyp.rotations[chosen], p.vectors, p.weights, p.field, p.match_tol, tol[chosen])
    _same(kernel, reference)
    matched = [r.n_matched for r in reference]
    assert max(matched) > SMALL_SET or scenario == "sparse"  # leave-one-out took part
    assert any(3 <= k <= SMALL_SET for k in matched)  # and the subset search
    # One at a time, the same as in a batch.
    for k in (0, 1, 45):
        _same([refine(hyp.rotations[chosen[k]], p.vectors, p.weights, p.field, p.match_tol, float(tol[chosen[k]]))],
              [kernel[k]])


def test_the_compiled_refinement_on_random_skies_and_patterns():
    """Random stars (no sky's cell map: the refinement makes its own), random patterns made from them with
    noise, outliers and missing stars, random starting errors: the numpy refinement's answers."""
    rng = np.random.default_rng(7)
    stars = rng.normal(size=(3000, 3))
    stars /= np.linalg.norm(stars, axis=1, keepdims=True)
    field = StarField.from_vectors(stars, np.arange(len(stars)))
    compared = 0
    for trial in range(60):
        centre = stars[rng.integers(len(stars))]
        near = np.flatnonzero(stars @ centre > np.cos(0.2))[:rng.integers(3, 14)]
        m = len(near)
        if m < 3:
            continue
        from scipy.spatial.transform import Rotation

        R_true = Rotation.random(random_state=trial).as_matrix()
        body = stars[near] @ R_true.T + rng.normal(scale=2e-4, size=(m, 3))
        outliers = rng.random(m) < 0.2
        body[outliers] += rng.normal(scale=5e-3, size=(outliers.sum(), 3))
        body /= np.linalg.norm(body, axis=1, keepdims=True)
        weights = np.full(m, 1 / 2e-4 ** 2) * rng.uniform(0.5, 2, m)
        final_tol = np.full(m, 1e-3)
        starts = Rotation.from_rotvec(rng.normal(scale=2e-3, size=(5, 3))).as_matrix() @ R_true
        start_tol = rng.uniform(1e-3, 5e-3, 5)
        kernel = refine_many(starts, body, weights, field, final_tol, start_tol)
        reference = numpy_refine_many(starts, body, weights, field, final_tol, start_tol)
        _same(kernel, reference)
        compared += 5
    assert compared >= 200


def numpy_rotation_from_pair(b1, b2, r1, r2):
    """The numpy construction :func:`app.attitude.rotation_from_pair` compiled (before issue 27)."""
    def triad(u, v):
        n = np.cross(u, v)
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        return np.stack([u, n, np.cross(n, u)], axis=-1)  # columns u, n, w

    return triad(b1, b2) @ np.swapaxes(triad(r1, r2), -1, -2)


def test_the_compiled_rotation_from_pair_is_the_numpy_triads():
    """Random pairs (a pattern edge against thousands of catalogue pairs, as the hypotheses use it, and stacks
    of both): the same rotations to rounding, proper, mapping r1 onto b1 and r2 into the plane of b1, b2."""
    from app.attitude import rotation_from_pair

    rng = np.random.default_rng(5)

    def unit(*shape):
        v = rng.normal(size=shape + (3,))
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    b1, b2 = unit(), unit()
    r1, r2 = unit(2000), unit(2000)
    for args in ((b1, b2, r1, r2), (unit(300), unit(300), unit(300), unit(300)), (b1, b2, r1[0], r2[0])):
        got = rotation_from_pair(*args)
        want = numpy_rotation_from_pair(*(np.broadcast_to(a, np.broadcast_shapes(*(x.shape for x in args)))
                                          for a in args))
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-14)
    R = rotation_from_pair(b1, b2, r1, r2)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, r1), np.broadcast_to(b1, r1.shape), atol=1e-14)
    normal = np.cross(b1, b2)
    assert np.abs(np.einsum("nij,nj->ni", R, np.cross(r1, r2)) @ normal
                  - np.linalg.norm(np.cross(r1, r2), axis=1) * np.linalg.norm(normal)).max() < 1e-12
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-13)


# --- the sequence fit's Gauss-Newton, as numpy computed it before its kernel ---------------------------------

def _numpy_left_jacobian(phi: np.ndarray) -> np.ndarray:
    t = np.linalg.norm(phi, axis=1)
    small = t < 1e-6
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t ** 2 / 24, (1 - np.cos(ts)) / ts ** 2)
    b = np.where(small, 1 / 6 - t ** 2 / 120, (ts - np.sin(ts)) / ts ** 3)
    K = np.zeros((len(phi), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    K -= np.swapaxes(K, 1, 2)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def _numpy_residuals_and_jacobian(R_obs, dt, W, R0, c, w):
    from scipy.spatial.transform import Rotation

    phi = -w[None, :] * dt[:, None]
    turn = Rotation.from_rotvec(phi).as_matrix()
    pred = turn @ (Rotation.from_rotvec(c).as_matrix() @ R0)
    r = Rotation.from_matrix(R_obs @ np.swapaxes(pred, 1, 2)).as_rotvec()
    J = np.concatenate([-turn, dt[:, None, None] * _numpy_left_jacobian(phi)], axis=2)
    return np.einsum("sij,sj->si", W, r).reshape(-1), np.einsum("sij,sjk->sik", W, J).reshape(-1, 6)


@pytest.mark.parametrize("turn", [1e-9, 1e-3, 0.3, 3.0])
def test_the_compiled_sequence_fit_steps_are_numpys(turn):
    """Residuals (rotation vectors of the misfit, up to turns near 180 deg) and Jacobian of the sequence fit."""
    from scipy.spatial.transform import Rotation

    from app.attitude.sequence import _residuals_and_jacobian, left_jacobian

    rng = np.random.default_rng(int(turn * 1e9) % 1000)
    S = 12
    R0 = Rotation.random(random_state=1).as_matrix()
    w = rng.normal(size=3) * turn / 20
    dt = np.linspace(-10, 10, S)
    R_obs = Rotation.from_rotvec(rng.normal(size=(S, 3)) * turn).as_matrix() @ R0
    W = np.linalg.cholesky(np.linalg.inv(np.stack([np.diag(rng.uniform(1e-9, 1e-8, 3)) for _ in range(S)])))
    W = np.ascontiguousarray(np.swapaxes(W, 1, 2))
    c = rng.normal(size=3) * 1e-4
    f, J = _residuals_and_jacobian(R_obs, dt, W, R0, c, w)
    f0, J0 = _numpy_residuals_and_jacobian(R_obs, dt, W, R0, c, w)
    assert np.allclose(f, f0, rtol=1e-9, atol=1e-9 * np.abs(f0).max())
    assert np.allclose(J, J0, rtol=1e-12, atol=1e-12 * np.abs(J0).max())
    phi = rng.normal(size=(6, 3)) * turn
    assert np.allclose(np.stack([left_jacobian(*p) for p in phi]), _numpy_left_jacobian(phi), rtol=1e-13, atol=1e-15)


# --- pixels to camera-frame vectors, as numpy computed them before the kernel ---------------------------------

def _numpy_pixels_to_vectors(camera, xy):
    ad = (xy[:, 0] - camera.cx) / camera.focal_length_px
    bd = (xy[:, 1] - camera.cy) / camera.focal_length_px
    if camera.k1 != 0.0 or camera.k2 != 0.0:
        k1, k2 = camera.k1, camera.k2
        rho_d = np.hypot(ad, bd)
        rho = rho_d.copy()
        for _ in range(8):
            r2 = rho * rho
            step = (rho * (1.0 + k1 * r2 + k2 * r2 * r2) - rho_d) / (1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2)
            rho -= step
            if not np.any(np.abs(step) > 1e-15 * rho):
                break
        scale = np.divide(rho, rho_d, out=np.ones_like(rho), where=rho_d > 0)
        ad, bd = ad * scale, bd * scale
    v = np.column_stack([ad, bd, np.ones_like(ad)])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("k1, k2", [(0.0, 0.0), (0.05, 0.0), (-0.2, 0.0), (0.1, -0.05)])
def test_the_compiled_pixels_to_vectors_is_numpys(k1, k2):
    """The centre pixel, the corners and random pixels, with and without radial distortion (and back)."""
    from dataclasses import replace

    from app.camera import CAMERAS

    camera = replace(CAMERAS["tubsat-752x582-20deg"], k1=k1, k2=k2)
    rng = np.random.default_rng(3)
    xy = np.vstack([[[camera.cx, camera.cy], [0, 0], [751, 581]], rng.uniform([0, 0], [751, 581], size=(200, 2))])
    v = camera.pixels_to_vectors(xy)
    assert np.allclose(v, _numpy_pixels_to_vectors(camera, xy), rtol=0, atol=1e-15)
    assert np.allclose(camera.vectors_to_pixels(v)[0], xy, rtol=0, atol=1e-9)
