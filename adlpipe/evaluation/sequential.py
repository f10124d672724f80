"""Anytime-valid paired tests: testing by betting, so that a comparison may be looked at after every scene or trial
and stopped as soon as it is decided, without inflating its error rate.

The test (Shafer 2021, "Testing by betting", JRSS A; Waudby-Smith & Ramdas 2024, "Estimating means of bounded random
variables by betting", JRSS B): for values x_i in [-1, 1] (a paired difference of two outcomes on the same scene)
and the null hypothesis "their mean is at most m", a gambler starts with wealth 1 and bets a fraction lambda_i,
chosen from x_1..x_(i-1) only, on each new x_i exceeding m: wealth_n = prod (1 + lambda_i (x_i - m)). Under the null
the wealth is a non-negative supermartingale, so by Ville's inequality it ever reaches 1 / alpha with probability
at most alpha, however often it is looked at and whenever one stops: rejecting the null the first time it does is
a level-alpha test under optional stopping (an e-process). The bet is the paper's aGRAPA rule, a predictable
plug-in of the growth-optimal fraction (mu - m) / (sigma^2 + (mu - m)^2), capped at half the largest admissible bet.

STEP (Snyder et al., RSS 2025) solves the same problem for two Bernoulli policies with precomputed tables; betting
also covers the margin of a non-inferiority claim and values that are not 0/1. No maintained Python library
implements it within adlpipe's dependencies (scipy has none; confseq needs a C++ build), so the dozen lines are here
and bench/sequential_tests.py checks their error rate by simulation.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

CAP = 0.5  # of the largest bet that keeps the wealth non-negative (Waudby-Smith & Ramdas' c)


class BettingTest:
    """The e-process against H0: E[x] <= m, for x in [-1, 1]; rejected once the wealth reached 1 / alpha. `shape`
    runs that many independent sequences side by side (a simulation); () is one."""

    def __init__(self, m: float, alpha: float, shape: tuple[int, ...] = ()) -> None:
        self.m, self.alpha, self.n = m, alpha, 0
        self.scalar = shape == ()  # one sequence: plain floats, ~20x faster per update than 0-d arrays (trials)
        zeros = (lambda: 0.0) if self.scalar else (lambda: np.zeros(shape))
        self.log_wealth = zeros()
        self.peak = zeros()  # a crossing stays a rejection: Ville's inequality holds for the supremum
        self.mean = zeros()
        self.squares = zeros()  # squared deviations from the mean (Welford), for the bet's variance
        self.at = 0 if self.scalar else np.zeros(shape, int)  # the observation at which it was rejected (0: not yet)

    def bet(self) -> np.ndarray | float:
        """The fraction bet on the next x, from the past ones only (predictable): aGRAPA, its estimates shrunk
        towards no difference before much is seen."""
        mu = self.mean * self.n / (self.n + 1)
        var = (0.25 + self.squares) / (self.n + 1)
        edge = mu - self.m
        if self.scalar:
            return min(max(edge / (var + edge * edge), 0.0), CAP / (1 + self.m))
        return np.clip(edge / (var + edge * edge), 0.0, CAP / (1 + self.m))

    def update(self, x: float | np.ndarray) -> None:
        if self.scalar:
            x = float(x)
            if abs(x) > 1.0:
                raise ValueError(f"betting test: value outside [-1, 1] ({x})")
            self.log_wealth += math.log1p(self.bet() * (x - self.m))
            self.n += 1
            delta = x - self.mean
            self.mean += delta / self.n
            self.squares += delta * (x - self.mean)
            self.peak = max(self.peak, self.log_wealth)
            if self.at == 0 and self.peak >= self.threshold:
                self.at = self.n
            return
        x = np.asarray(x, float)
        if np.any(np.abs(x) > 1.0):
            raise ValueError(f"betting test: values outside [-1, 1] ({x.min()}, {x.max()})")
        self.log_wealth = self.log_wealth + np.log1p(self.bet() * (x - self.m))
        self.n += 1
        delta = x - self.mean
        self.mean = self.mean + delta / self.n
        self.squares = self.squares + delta * (x - self.mean)
        self.peak = np.maximum(self.peak, self.log_wealth)
        self.at = np.where((self.at == 0) & (self.peak >= self.threshold), self.n, self.at)

    @property
    def threshold(self) -> float:
        return math.log(1 / self.alpha)

    @property
    def rejected(self) -> bool | np.ndarray:
        hit = self.peak >= self.threshold
        return bool(hit) if np.ndim(hit) == 0 else hit

    def more_needed(self) -> int | None:
        """About how many more observations would reject if the observed mean and spread held (the log wealth
        grows by about (mean - m)^2 / (2 var) per observation); None when the observed mean is not above m."""
        if self.rejected:
            return 0
        mean = float(self.mean)
        if self.n == 0 or mean <= self.m + 1e-9:
            return None
        growth = (mean - self.m) ** 2 / (2 * max(float(self.squares) / self.n, 1e-3))
        return math.ceil((self.threshold - float(self.log_wealth)) / growth)


def run_test(xs: Iterable[float], m: float, alpha: float) -> BettingTest:
    test = BettingTest(m, alpha)
    for x in xs:
        test.update(x)
    return test


@dataclass
class PairedComparison:
    """Policy a against policy b on the same scenes (d = a - b per scene, outcomes in [0, 1]): four one-sided
    e-processes, a better, b better, a not worse than b by more than the margin, and b not worse than a. At most two
    of their null hypotheses hold at once, so each runs at alpha / 2 and the pair's error rate is at most alpha."""

    a: str
    b: str
    margin: float
    alpha: float
    shape: tuple[int, ...] = ()  # sequences side by side (a simulation)
    tests: dict[str, BettingTest] = field(default_factory=dict)

    def __post_init__(self) -> None:
        level, sh = self.alpha / 2, self.shape
        self.tests = {"a_better": BettingTest(0.0, level, sh), "b_better": BettingTest(0.0, level, sh),
                      "a_not_worse": BettingTest(-self.margin, level, sh),
                      "b_not_worse": BettingTest(-self.margin, level, sh)}

    def update(self, a: float | np.ndarray, b: float | np.ndarray) -> None:
        d = np.asarray(a, float) - np.asarray(b, float)
        for key, t in self.tests.items():
            t.update(d if key.startswith("a_") else -d)

    def test_of(self, who: str, claim: str) -> BettingTest:
        """The test of `who` (a or b by name) making `claim` ("better" or "not_worse") against the other."""
        return self.tests[("a" if who == self.a else "b") + f"_{claim}"]

    def better(self, who: str) -> bool | np.ndarray:
        """Whether `who` is resolved better than the other."""
        return self.test_of(who, "better").rejected

    def not_worse(self, who: str) -> bool | np.ndarray:
        """Whether `who` is resolved not worse than the other by more than the margin."""
        return self.test_of(who, "not_worse").rejected
