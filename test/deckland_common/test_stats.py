"""deckland_common.stats: the one percentile definition and the Wilson interval."""

import math
import random

from deckland_common.stats import percentile, wilson_interval
import numpy as np
import pytest


def test_percentile_equals_numpy_linear_method():
    rng = random.Random(5)
    for n in (1, 2, 3, 10, 101):
        xs = [rng.uniform(-5, 5) for _ in range(n)]
        for q in (0, 5, 50, 95, 99, 100):
            assert percentile(xs, q) == pytest.approx(float(np.percentile(xs, q)), abs=1e-12)


def test_percentile_empty_is_nan_and_bad_q_raises():
    assert math.isnan(percentile([], 50))
    with pytest.raises(ValueError, match='q must be in'):
        percentile([1.0], 101)


def test_wilson_interval_known_values():
    # 100 of 100: the classic "rule of three"-like lower bound ~0.963
    lo, hi = wilson_interval(100, 100)
    assert hi == 1.0 and lo == pytest.approx(0.96301, abs=1e-4)
    # 50 of 100: symmetric about 0.5, half-width ~0.0962
    lo, hi = wilson_interval(50, 100)
    assert lo == pytest.approx(0.40383, abs=1e-4) and hi == pytest.approx(0.59617, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        wilson_interval(5, 3)


def test_wilson_interval_covers_the_true_rate():
    rng = random.Random(11)
    p, n, trials = 0.97, 200, 2000
    covered = 0
    for _ in range(trials):
        k = sum(rng.random() < p for _ in range(n))
        lo, hi = wilson_interval(k, n)
        covered += lo <= p <= hi
    assert 0.92 <= covered / trials <= 0.98   # nominal 95 %
