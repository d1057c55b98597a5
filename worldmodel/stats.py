"""Intervals and tests the reports share, taken from scipy rather than written here (docs/design.md §6).

``wilson``: the Wilson score interval of a rate (``scipy.stats.binomtest``). ``paired_permutation_p``: the two-sided
p of a mean paired difference (``scipy.stats.permutation_test`` with the pairs' signs flipped; exact when the
pairs are few enough to enumerate every flip).
"""

from __future__ import annotations

import math

import numpy as np


def wilson(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of the proportion ``k / n``, in %; (nan, nan) without trials."""
    from scipy.stats import binomtest

    if n == 0:
        return (math.nan, math.nan)
    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return 100.0 * float(ci.low), 100.0 * float(ci.high)


def paired_permutation_p(a, b, flips: int = 10_000, seed: int = 0) -> float:
    """Two-sided p of the mean paired difference ``a - b`` under random sign flips of the pairs (the trials are
    shared, so each pair's difference is what may flip); 1 when no pair differs."""
    from scipy.stats import permutation_test

    d = np.asarray(a, float) - np.asarray(b, float)
    if not np.any(d):
        return 1.0
    result = permutation_test(
        (d,),
        lambda x, axis: np.mean(x, axis=axis),
        permutation_type="samples",
        n_resamples=flips,
        alternative="two-sided",
        vectorized=True,
        rng=np.random.default_rng(seed),
    )
    return float(result.pvalue)
