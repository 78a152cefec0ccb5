"""Statistics every report uses (pure): one percentile definition and the Wilson interval.

:func:`percentile` is the linear interpolation between closest ranks (numpy's default,
``method='linear'``; Hyndman & Fan type 7): for sorted values x₀..xₙ₋₁ and q in [0, 100] it
returns x at the fractional rank (n − 1)·q/100. Campaign reports, the latency bench and the
golden comparison all call it, so their p50/p95/p99 mean the same thing.
"""

from __future__ import annotations

from collections.abc import Iterable
import math


def percentile(values: Iterable[float], q: float) -> float:
    """The ``q``-th percentile (q in [0, 100]) by linear interpolation; NaN for no data."""
    xs = sorted(values)
    if not xs:
        return math.nan
    if not 0.0 <= q <= 100.0:
        raise ValueError(f'percentile q must be in [0, 100], got {q!r}')
    pos = (len(xs) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (pos - lo)


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054
                    ) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (default 95 %); (0, 1) for n = 0.

    Wilson, "Probable inference, the law of succession, and statistical inference",
    J. Am. Stat. Assoc. 22 (1927) 209-212. Unlike the normal approximation it stays inside
    [0, 1] and is not degenerate at 0 or n successes (100 of 100 gives [0.963, 1]).
    """
    if n <= 0:
        return 0.0, 1.0
    if not 0 <= successes <= n:
        raise ValueError(f'successes must be in [0, {n}], got {successes!r}')
    p = successes / n
    z2 = z * z
    den = 1.0 + z2 / n
    centre = (p + z2 / (2.0 * n)) / den
    half = z * math.sqrt(p * (1.0 - p) / n + z2 / (4.0 * n * n)) / den
    return max(0.0, centre - half), min(1.0, centre + half)
