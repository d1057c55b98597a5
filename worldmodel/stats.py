"""Intervals and tests the reports share, taken from scipy rather than written here (docs/design.md §6).

``wilson``: the Wilson score interval of a rate (``scipy.stats.binomtest``). ``paired_permutation_p``: the two-sided
p of a mean paired difference (``scipy.stats.permutation_test`` with the pairs' signs flipped; exact when the
pairs are few enough to enumerate every flip). ``paired_bootstrap_ci``: a percentile interval over resamples that
draw the same scenarios for every policy (``scipy.stats.bootstrap(paired=True)``).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

CONFIDENCE = 0.95  # every interval the reports give


def wilson(k: int, n: int) -> tuple[float, float]:
    """Wilson score interval of the proportion ``k / n``, in %; (nan, nan) without trials."""
    from scipy.stats import binomtest

    if n == 0:
        return (math.nan, math.nan)
    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=CONFIDENCE, method="wilson")
    return 100.0 * float(ci.low), 100.0 * float(ci.high)


def paired_permutation_p(a, b, flips: int = 10_000, seed: int = 0) -> float:
    """Two-sided p of the mean paired difference ``a - b`` under random sign flips of the pairs (the trials are
    shared, so each pair's difference is what may flip); 1 when no pair differs."""
    from scipy.stats import permutation_test

    d = np.asarray(a, float) - np.asarray(b, float)
    if not np.any(d):
        return 1.0
    if flips < 2 ** min(len(d), 63):
        return _sign_flip_p(d, flips, seed)
    result = permutation_test(  # few pairs: scipy enumerates every flip exactly
        (d,),
        lambda x, axis: np.mean(x, axis=axis),
        permutation_type="samples",
        n_resamples=flips,
        alternative="two-sided",
        vectorized=True,
        rng=np.random.default_rng(seed),
    )
    return float(result.pvalue)


# null draws computed at a time: an even number, so that every block but the last starts on a whole 64-bit draw; a
# block of 256 keeps its arrays in the cache (three times faster than all 10,000 at once, the same null means: each
# is its own row's sum)
FLIP_BLOCK = 256


def _sign_flip_p(d: np.ndarray, flips: int, seed: int) -> float:
    """``scipy.stats.permutation_test``'s two-sided p for the mean of ``d`` under random sign flips (permutation
    type "samples", one sample), from the very draws it makes, without its general indexing (about 20x faster).

    scipy flips pair i by shuffling [d_i, -d_i] with ``Generator.permuted``: one 32-bit draw per pair, taken low
    half then high half of each 64-bit output, and d_i keeps its sign where the draw's lowest bit is 1. The null
    means match scipy's to the last bits of their sum's order, which its tolerance (100 eps x the observed mean)
    absorbs; tests/test_report.py holds the p-values equal."""
    n = len(d)
    bits = np.random.default_rng(seed).bit_generator
    null = np.empty(flips)
    for start in range(0, flips, FLIP_BLOCK):  # each block takes the next draws of the one stream
        rows = min(FLIP_BLOCK, flips - start)
        raw = bits.random_raw((rows * n + 1) // 2)
        keep = np.empty(2 * len(raw), bool)  # each draw's lowest bit: the low half's bit 0, then the high half's
        keep[0::2], keep[1::2] = raw & 1, (raw >> 32) & 1
        null[start : start + rows] = np.where(keep[: rows * n].reshape(rows, n), d, -d).mean(axis=1)
    observed = d.mean()
    gamma = abs(np.finfo(float).eps * 100 * observed)
    less = (np.count_nonzero(null <= observed + gamma) + 1) / (flips + 1)
    greater = (np.count_nonzero(null >= observed - gamma) + 1) / (flips + 1)
    return float(np.clip(min(less, greater) * 2, 0.0, 1.0))


def paired_bootstrap_ci(samples, statistic, n: int, seed: int) -> tuple[float, float]:
    """Percentile interval of ``statistic(*samples, axis)`` over ``n`` paired resamples of the samples' common
    axis (``scipy.stats.bootstrap(paired=True)``): each resample draws the same items from every sample, as the
    policies of a bank share its scenarios. (nan, nan) when fewer than two items, or when the statistic is undefined
    (nan) on some resample: an interval over only the resamples where it is defined would be too narrow."""
    from scipy.stats import bootstrap

    samples = [np.asarray(s, float) for s in samples]
    if len(samples[0]) < 2:
        return (math.nan, math.nan)
    with warnings.catch_warnings():
        # a degenerate resampling distribution (every resample the same) is a valid, zero-width interval here
        warnings.simplefilter("ignore", category=RuntimeWarning)
        result = bootstrap(
            samples,
            statistic,
            paired=True,
            vectorized=True,
            n_resamples=n,
            confidence_level=CONFIDENCE,
            method="percentile",
            rng=np.random.default_rng(seed),
        )
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def rank_agreement(scores, costs, tie: float = 1e-6) -> dict[str, np.ndarray]:
    """Per row, how ``scores`` (lower is better) rank a row's options against their exact ``costs``: ``spearman``
    (NaN where every exact cost is equal, 0 where the scores are constant; costs within ``tie`` share a rank),
    ``pairs`` (option pairs whose costs differ by more than ``tie``) and ``agree`` (of those, the ones the scores
    order alike, a tie in the scores counting half: a constant agrees on half of every row's pairs)."""
    from scipy.stats import spearmanr

    scores, costs = np.asarray(scores, np.float64), np.asarray(costs, np.float64)
    rho = np.full(len(costs), np.nan)
    pairs, agree = np.zeros(len(costs), np.int64), np.zeros(len(costs))
    for i, (p, y) in enumerate(zip(scores, costs, strict=True)):
        dy, dp = y[:, None] - y[None, :], p[:, None] - p[None, :]
        mask = np.triu(np.abs(dy) > tie, 1)
        pairs[i] = int(mask.sum())
        agree[i] = float((np.sign(dp[mask]) == np.sign(dy[mask])).sum() + 0.5 * (dp[mask] == 0).sum())
        if pairs[i]:
            rho[i] = 0.0 if np.ptp(p) == 0 else float(spearmanr(p, np.round(y / tie)).statistic)
    return {"spearman": rho, "pairs": pairs, "agree": agree}
