"""bench/store.py's ideal-coder floor (ideal_context_bits): what it reports against cases whose
cost is known."""

import numpy as np
import pytest

from bench.store import ideal_context_bits


def test_a_plane_costs_nothing_and_noise_costs_its_entropy():
    i, j = np.mgrid[0:64, 0:80]
    assert ideal_context_bits(1000 + 3 * i - 7 * j) == 0.0  # the predictor is exact on a plane
    rng = np.random.default_rng(5)
    noise = rng.integers(0, 16, (300, 300))  # 4 bits a post, nothing to predict
    assert 3.9 < ideal_context_bits(noise) < 4.3  # a rounded mean predictor spreads it over 17 values
    smooth = np.cumsum(np.cumsum(rng.integers(-1, 2, (300, 300)), 0), 1)  # integrated noise: predictable
    assert ideal_context_bits(smooth) < 0.5 * ideal_context_bits(noise)
    with pytest.raises(ValueError, match="5 x 5"):
        ideal_context_bits(np.zeros((4, 9), np.int64))
