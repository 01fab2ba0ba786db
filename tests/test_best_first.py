"""engine.best_first: the first k of numpy's lexsort by (most matches, smallest deviation, earliest), checked
against the full lexsort it stands in for on arrays full of ties (the focal scan's chance 3-point catches)."""

from __future__ import annotations

import numpy as np
import pytest

from app.identification.engine import best_first


@pytest.mark.parametrize("seed", range(40))
def test_best_first_is_the_head_of_the_full_lexsort(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3000))
    n_match = rng.choice([3, 3, 3, 3, 4, 5, 9], size=n)
    dev = rng.choice(np.r_[rng.uniform(0, 1e-3, 50), np.nan], size=n)  # repeated deviations: ties on both keys
    for k in (1, 3, 16, n, n + 5):
        expected = np.lexsort((dev, -n_match))[:k]
        assert np.array_equal(best_first(n_match, dev, k), expected), (n, k)
