"""Uncertainty of the figures the stages report, from scipy.stats (no hand-written formulas).

Success rates get Wilson's 95 % score interval (scipy.stats.binomtest(...).proportion_ci("wilson")); two policies
run on the same scenes are compared paired, by the exact binomial test on their discordant scenes (McNemar's exact
test: only the scenes one solves and the other does not carry information about which is better). Means (a score,
an error) get a percentile bootstrap interval over the episodes (scipy.stats.bootstrap, seeded: a table re-made
from the same episodes prints the same interval).
"""

from __future__ import annotations

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


def paired_success(first: Sequence[bool], second: Sequence[bool]) -> PairedSuccess:
    """McNemar's exact test on paired outcomes (the same scenes, in the same order)."""
    if len(first) != len(second):
        raise ValueError(f"paired outcomes of different lengths: {len(first)} and {len(second)}")
    b = sum(bool(x) and not bool(y) for x, y in zip(first, second, strict=True))
    c = sum(bool(y) and not bool(x) for x, y in zip(first, second, strict=True))
    return PairedSuccess(b, c, float(binomtest(b, b + c).pvalue) if b + c else 1.0)


def mean_interval(values: Sequence[float], level: float = LEVEL) -> tuple[float, float]:
    """The percentile bootstrap interval of the mean over episodes; the value itself when all are equal or there is
    one."""
    x = np.asarray(values, float)
    if len(x) < 2 or np.ptp(x) == 0:
        m = float(x.mean()) if len(x) else float("nan")
        return m, m
    ci = bootstrap((x,), np.mean, confidence_level=level, n_resamples=RESAMPLES, method="percentile",
                   rng=np.random.default_rng(0)).confidence_interval
    return float(ci.low), float(ci.high)


def mean_cell(values: Sequence[float], digits: int = 3) -> str:
    """'0.912 [0.897, 0.925]': the mean and its bootstrap interval."""
    lo, hi = mean_interval(values)
    return f"{np.mean(values):.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"
