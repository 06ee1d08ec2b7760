"""Small statistics for results over episodes and seeds (scipy does the work)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def iqm(values: Sequence[float]) -> float:
    """Interquartile mean (Agarwal et al. 2021): the mean of the middle 50% (scipy's trimmed mean)."""
    from scipy.stats import trim_mean

    return float(trim_mean(np.asarray(values, dtype=np.float64), 0.25))


def bootstrap_ci(values: Sequence[float], confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile-bootstrap interval of the mean (scipy.stats.bootstrap, 10k resamples). One value or no
    spread: the value itself at both ends."""
    from scipy.stats import bootstrap

    x = np.asarray(values, dtype=np.float64)
    if len(x) < 2 or np.ptp(x) == 0.0:
        return float(np.mean(x)), float(np.mean(x))
    res = bootstrap((x,), np.mean, confidence_level=confidence, n_resamples=10_000, method="percentile",
                    random_state=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a success rate (scipy.stats.binomtest): sensible at 0/n and n/n, where
    the normal approximation collapses to a zero-width interval."""
    from scipy.stats import binomtest

    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n and n >= 1, got {successes}/{n}")
    ci = binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)
