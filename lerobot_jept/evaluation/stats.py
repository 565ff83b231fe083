"""Intervals over training seeds and over episodes, used by every report."""

import math

import numpy as np


def t_interval(values: list[float], confidence: float) -> tuple[float, float]:
    """Student's t interval of the mean of ``values`` (two or more) at ``confidence``."""
    from scipy import stats

    n = len(values)
    mean = float(np.mean(values))
    half = float(stats.t.ppf(0.5 + confidence / 2, n - 1) * np.std(values, ddof=1) / math.sqrt(n))
    return mean - half, mean + half


def interval(values: list[float]) -> tuple[float, float, float]:
    """Mean and 95% t interval over seeds (the mean twice with one seed)."""
    values = [v for v in values if v == v]
    if not values:
        return math.nan, math.nan, math.nan
    mean = float(np.mean(values))
    if len(values) < 2:
        return mean, math.nan, math.nan
    low, high = t_interval(values, 0.95)
    return mean, low, high


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson interval of a success rate, in %."""
    if n == 0:
        return math.nan, math.nan
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return 100 * max(centre - half, 0.0), 100 * min(centre + half, 1.0)
