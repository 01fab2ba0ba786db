"""The bright-pair index against the seed's definition, evaluated by brute force."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from app.catalogue import load_catalogue
from app.index import bright_pairs, build_index, hull_vertex_mask, load_index


def brute_force_bright_pairs(vectors: np.ndarray) -> set[tuple[int, int]]:
    """Edges of bright triangles, straight from the definition.

    Stars are sorted brightest first.  A triangle is bright when one of the
    two caps cut from the sphere by the plane through its corners holds no
    star brighter than its faintest corner.  (For triangles smaller than a
    hemisphere, which are all of them once a few stars cover the sky, that is
    the enclosing disc of the seed's definition.)
    """
    n = len(vectors)
    tri = np.array(list(itertools.combinations(range(n), 3)))
    a, b, c = vectors[tri[:, 0]], vectors[tri[:, 1]], vectors[tri[:, 2]]
    normal = np.cross(b - a, c - a)
    side = vectors @ normal.T - np.sum(normal * a, axis=1)  # (n, T)
    brighter = np.arange(n)[:, None] < tri.max(axis=1)[None, :]
    corner = np.zeros_like(brighter)
    for k in range(3):
        corner[tri[:, k], np.arange(len(tri))] = True
    others = brighter & ~corner
    above = ((side > 1e-12) & others).any(axis=0)
    below = ((side < -1e-12) & others).any(axis=0)
    edges = set()
    for t in tri[~(above & below)]:
        for i, j in ((t[0], t[1]), (t[0], t[2]), (t[1], t[2])):
            edges.add((int(i), int(j)))
    return edges


@pytest.fixture(scope="module")
def catalogue_vectors():
    return load_catalogue().brighter_than(6.5).mean_vectors(2000.0)


def test_whole_sky_bright_pairs_match_brute_force(catalogue_vectors):
    vectors = catalogue_vectors[:140]  # the brightest stars, spread over the whole sky
    a, b = bright_pairs(vectors)
    assert set(zip(a.tolist(), b.tolist())) == brute_force_bright_pairs(vectors)


def test_dense_region_bright_pairs_match_brute_force(catalogue_vectors):
    # A dense cap around the north pole: here most stars take the fast local
    # path (nearest brighter neighbours, proven complete by the disc check).
    rows = np.flatnonzero(catalogue_vectors[:, 2] > 0.94)[:150]
    vectors = catalogue_vectors[rows]
    a, b = bright_pairs(vectors)
    assert set(zip(a.tolist(), b.tolist())) == brute_force_bright_pairs(vectors)


def test_hull_vertex_test_on_a_square_with_centre():
    y = np.array([[[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]]], dtype=float)
    mask = hull_vertex_mask(y, np.ones((1, 5), dtype=bool))
    assert mask.tolist() == [[True, True, True, True, False]]


def test_about_six_pairs_per_star_and_sorted_lengths(catalogue_vectors):
    cat = load_catalogue()
    index = build_index(cat, mag_limit=4.5, max_edge_deg=180.0)
    assert 5.0 < index.n_pairs / index.n_stars < 7.0  # the seed's "roughly 6n"
    assert np.all(np.diff(index.length_rad) >= 0)
    assert np.all(index.star_a != index.star_b)


def test_cache_round_trip(tmp_path):
    built = load_index(mag_limit=4.0, cache_dir=tmp_path)
    files = list(tmp_path.glob("bright-pairs-*.npz"))
    assert len(files) == 1
    loaded = load_index(mag_limit=4.0, cache_dir=tmp_path)
    assert np.array_equal(built.star_a, loaded.star_a) and np.array_equal(built.length_rad, loaded.length_rad)
    # A damaged cache file is rebuilt, not trusted.
    files[0].write_bytes(b"not an npz file")
    again = load_index(mag_limit=4.0, cache_dir=tmp_path)
    assert np.array_equal(again.star_b, built.star_b)


def test_every_path_of_the_construction_agrees_with_brute_force():
    """Few candidates per star, so the second (wider) pass and the exact fallback both run."""
    rng = np.random.default_rng(8)
    spread = rng.normal(size=(100, 3))
    cluster = rng.normal(size=(50, 3)) * 0.03 + [0.0, 0.0, 1.0]  # a tight group: its stars' nearest are each other
    vectors = np.vstack([spread, cluster])
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    truth = brute_force_bright_pairs(vectors)
    for candidates in ((4, 12), (6,), (48, 384)):
        a, b = bright_pairs(vectors, candidates=candidates, chunk=64)
        assert set(zip(a.tolist(), b.tolist())) == truth, candidates
