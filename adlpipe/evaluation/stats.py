"""Uncertainty of the figures the stages report, from scipy.stats (no hand-written formulas).

Success rates get Wilson's 95 % score interval (scipy.stats.binomtest(...).proportion_ci("wilson")); two policies
run on the same scenes are compared paired, by the exact binomial test on their discordant scenes (McNemar's exact
test: only the scenes one solves and the other does not carry information about which is better). Means (a score,
an error) get a percentile bootstrap interval over the episodes (scipy.stats.bootstrap, seeded: a table re-made
from the same episodes prints the same interval).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import binomtest, bootstrap

LEVEL = 0.95
RESAMPLES = 9999


def success_interval(k: int, n: int, level: float = LEVEL) -> tuple[float, float]:
    """Wilson's interval for k successes in n trials, as fractions; (0, 1) when n = 0."""
    if n == 0:
        return 0.0, 1.0
    ci = binomtest(k, n).proportion_ci(confidence_level=level, method="wilson")
    return float(ci.low), float(ci.high)


def rate_cell(k: int, n: int) -> str:
    """'28 [16, 43]': the success rate and its interval in percent."""
    lo, hi = success_interval(k, n)
    return f"{100 * k / n:.0f} [{100 * lo:.0f}, {100 * hi:.0f}]" if n else "-"


@dataclass(frozen=True)
class PairedSuccess:
    """Two policies on the same scenes: scenes only the first solved, only the second solved, and the exact
    two-sided p-value of the difference."""

    only_first: int
    only_second: int
    p_value: float

    def __str__(self) -> str:
        return f"{self.only_first} : {self.only_second} discordant scenes, exact McNemar p = {self.p_value:.2f}"


    n: int = 0  # scenes compared

    def verdict(self, alpha: float = 1 - LEVEL) -> str:
        """'better' / 'worse' (the first against the second) when McNemar's p is below alpha, otherwise 'not
        resolved at n = N' with about how many scenes would resolve it if the discordant share and its split held."""
        if self.p_value < alpha:
            return "better" if self.only_first > self.only_second else "worse"
        need = scenes_to_resolve(self.only_first, self.only_second, self.n, alpha)
        return f"not resolved at n = {self.n}" + (f" (about {need} scenes would resolve it at this effect)"
                                                   if need else " (no difference measured)")


def paired_success(first: Sequence[bool], second: Sequence[bool]) -> PairedSuccess:
    """McNemar's exact test on paired outcomes (the same scenes, in the same order)."""
    if len(first) != len(second):
        raise ValueError(f"paired outcomes of different lengths: {len(first)} and {len(second)}")
    b = sum(bool(x) and not bool(y) for x, y in zip(first, second, strict=True))
    c = sum(bool(y) and not bool(x) for x, y in zip(first, second, strict=True))
    return PairedSuccess(b, c, float(binomtest(b, b + c).pvalue) if b + c else 1.0, len(first))


def scenes_to_resolve(b: int, c: int, n: int, alpha: float = 1 - LEVEL, limit: int = 100_000) -> int | None:
    """The fewest scenes at which McNemar's exact test would reach p < alpha if b : c discordant scenes in n kept
    their share and split (None: no difference, or more than `limit` scenes)."""
    if n == 0 or b == c:
        return None
    share, split = (b + c) / n, b / (b + c)
    m = n
    while m <= limit:
        k = round(share * m)
        if k and binomtest(round(split * k), k).pvalue < alpha:
            return m
        m = max(m + 1, int(m * 1.05))
    return None


def mean_interval(values: Sequence[float] | np.ndarray, level: float = LEVEL) -> tuple[float, float]:
    """The percentile bootstrap interval of the mean over episodes; the value itself when all are equal or there is
    one."""
    x = np.asarray(values, float)
    if len(x) < 2 or np.ptp(x) == 0:
        m = float(x.mean()) if len(x) else float("nan")
        return m, m
    ci = bootstrap((x,), np.mean, confidence_level=level, n_resamples=RESAMPLES, method="percentile",
                   rng=np.random.default_rng(0)).confidence_interval
    return float(ci.low), float(ci.high)


def median_interval(values: Sequence[float], level: float = LEVEL) -> tuple[float, float]:
    """The percentile bootstrap interval of the median (e.g. of repeated latency measurements); the value itself
    when all are equal or there is one."""
    x = np.asarray(values, float)
    if len(x) < 2 or np.ptp(x) == 0:
        m = float(np.median(x)) if len(x) else float("nan")
        return m, m
    ci = bootstrap((x,), np.median, confidence_level=level, n_resamples=RESAMPLES, method="percentile",
                   rng=np.random.default_rng(0)).confidence_interval
    return float(ci.low), float(ci.high)


def median_cell(values: Sequence[float], digits: int = 1) -> str:
    """The median of `values` and its bootstrap interval, as a table cell."""
    return interval_cell(float(np.median(values)), median_interval(values), digits)


def ratio_interval(numerators: Sequence[float], denominators: Sequence[float],
                   level: float = LEVEL) -> tuple[float, float]:
    """The percentile bootstrap interval of sum(numerators) / sum(denominators), resampling their pairs (clusters:
    e.g. a scene's samples that went one way out of those that committed at all)."""
    num, den = np.asarray(numerators, float), np.asarray(denominators, float)
    ratio = float(num.sum() / den.sum())
    if len(num) < 2 or np.ptp(num / np.where(den > 0, den, 1)) == 0:
        return ratio, ratio

    def statistic(a: np.ndarray, b: np.ndarray, axis: int = -1) -> np.ndarray:
        d = b.sum(axis)
        return np.where(d > 0, a.sum(axis) / np.where(d > 0, d, 1), np.nan)

    ci = bootstrap((num, den), statistic, paired=True, confidence_level=level, n_resamples=RESAMPLES,
                   method="percentile", rng=np.random.default_rng(0)).confidence_interval
    return float(ci.low), float(ci.high)


def interval_cell(value: float, interval: Sequence[float], digits: int = 3) -> str:
    """'0.912 [0.897, 0.925]': a figure and its interval, as every table prints them."""
    lo, hi = interval
    return f"{value:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def mean_cell(values: Sequence[float], digits: int = 3) -> str:
    """The mean of `values` and its bootstrap interval, as a table cell."""
    return interval_cell(float(np.mean(values)), mean_interval(values), digits)


@dataclass(frozen=True)
class PairedDifference:
    """The mean of per-episode differences first - second (lower is better: an error), its 95 % bootstrap interval
    and the number of episodes; verdict() applies the claim rule."""

    mean: float
    low: float
    high: float
    n: int

    def verdict(self) -> str:
        """'supported' when the interval lies below zero (first lower, as claimed), 'contradicted' when above,
        otherwise 'not resolved at n = N' with about how many episodes would resolve it at this effect size (the
        interval's half-width shrinks as 1/sqrt(n))."""
        if self.high < 0:
            return "supported"
        if self.low > 0:
            return "contradicted"
        half = (self.high - self.low) / 2
        if self.mean == 0 or half == 0:
            return f"not resolved at n = {self.n}"
        need = math.ceil(self.n * (half / abs(self.mean)) ** 2)
        return f"not resolved at n = {self.n} (about {need} episodes would resolve it at this effect size)"

    def __str__(self) -> str:
        return f"paired difference {self.mean:+.2f} [{self.low:+.2f}, {self.high:+.2f}], n = {self.n}"


def paired_difference(first: Sequence[float], second: Sequence[float], scale: float = 1.0) -> PairedDifference:
    """The paired bootstrap of first_i - scale * second_i over episodes (the same episodes, in the same order):
    scale 1.1 tests "first within 10 % of second or better"."""
    if len(first) != len(second):
        raise ValueError(f"paired figures of different lengths: {len(first)} and {len(second)}")
    d = np.asarray(first, float) - scale * np.asarray(second, float)
    lo, hi = mean_interval(d)
    return PairedDifference(float(d.mean()), lo, hi, len(d))
