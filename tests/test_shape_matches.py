"""The bright triangles' shape lookup (app.identification.triangle_index.shape_matches, a compiled loop over the
run of the first ratio) against numpy's plain filter of the whole table."""

from __future__ import annotations

import numpy as np

from app.identification.triangle_index import shape_matches


def test_the_shape_lookup_is_the_plain_filter_of_every_triangle(sky):
    triangles = sky.bright_triangles()
    rng = np.random.default_rng(31)
    found = 0
    for _ in range(300):
        row = int(rng.integers(len(triangles)))  # a query near a real triangle, so that some match
        ratio1 = triangles.ratio1[row] + rng.normal(scale=0.003)
        ratio2 = triangles.ratio2[row] + rng.normal(scale=0.003)
        sense = int(rng.choice([-1, 1]))
        tolerance = float(rng.uniform(0.002, 0.02))
        longest = triangles.longest_rad[row]
        lo, hi = longest * rng.uniform(0.85, 1.0), longest * rng.uniform(1.0, 1.15)
        star_limit = int(rng.integers(100, sky.index.n_stars + 1))
        want = np.flatnonzero((triangles.ratio1 >= ratio1 - tolerance) & (triangles.ratio1 < ratio1 + tolerance)
                              & (np.abs(triangles.ratio2 - ratio2) <= tolerance) & (triangles.sense == sense)
                              & (triangles.longest_rad >= lo) & (triangles.longest_rad <= hi)
                              & (triangles.faintest < star_limit))
        got = shape_matches(triangles, ratio1, ratio2, sense, tolerance, lo, hi, star_limit)
        assert np.array_equal(got, want)
        found += len(got)
    assert found > 300
