"""The anytime-valid paired tests and the decision rule: error rates under optional stopping, and the rule's steps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom

from adlpipe.evaluation.decision import Rule, decide, scene_order
from adlpipe.evaluation.sequential import BettingTest, PairedComparison, run_test

LOOK, CAP, ALPHA = 20, 400, 0.05


def paired(pa: float, pb: float, n: int, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u1, u2, same = rng.random((n, k)), rng.random((n, k)), rng.random((n, k)) < 0.5
    return (u1 < pa).astype(float), (np.where(same, u1, u2) < pb).astype(float)


def false_rate_betting(a: np.ndarray, b: np.ndarray) -> float:
    """Share of sequences in which the betting comparison declared either policy better at any look."""
    pc = PairedComparison("A", "B", 0.05, ALPHA, shape=(a.shape[1],))
    hit = np.zeros(a.shape[1], bool)
    for i in range(a.shape[0]):
        pc.update(a[i], b[i])
        if (i + 1) % LOOK == 0:
            hit |= pc.better("A") | pc.better("B")
    return float(hit.mean())


def false_rate_naive(a: np.ndarray, b: np.ndarray) -> float:
    """The same looks with McNemar's exact test at ALPHA after each: what optional stopping does to a fixed-n test."""
    hit = np.zeros(a.shape[1], bool)
    for n in range(LOOK, a.shape[0] + 1, LOOK):
        x, y = ((a[:n] == 1) & (b[:n] == 0)).sum(0), ((a[:n] == 0) & (b[:n] == 1)).sum(0)
        p = np.where(x + y > 0, np.minimum(1, 2 * binom.cdf(np.minimum(x, y), np.maximum(x + y, 1), 0.5)), 1)
        hit |= p < ALPHA
    return float(hit.mean())


def test_betting_keeps_its_error_rate_under_optional_stopping_where_repeated_mcnemar_does_not() -> None:
    a, b = paired(0.5, 0.5, CAP, 600, seed=1)  # equal policies: every "better" is a false decision
    assert false_rate_betting(a, b) <= ALPHA
    assert false_rate_naive(a, b) > 2 * ALPHA  # the naive procedure fails the same assertion (about 15 % here)


def test_betting_finds_a_real_difference_and_stops_early() -> None:
    a, b = paired(0.4, 0.65, CAP, 300, seed=2)
    pc = PairedComparison("A", "B", 0.05, ALPHA, shape=(300,))
    for i in range(CAP):
        pc.update(a[i], b[i])
    at = pc.test_of("B", "better").at
    assert pc.better("B").mean() > 0.95 and not pc.better("A").any()
    assert np.median(at[at > 0]) < 200


def test_non_inferiority_holds_its_level_at_the_margin() -> None:
    a, b = paired(0.6, 0.55, CAP, 600, seed=3)  # B worse by exactly the 5-point margin
    pc = PairedComparison("A", "B", 0.05, ALPHA, shape=(600,))
    for i in range(CAP):
        pc.update(a[i], b[i])
    assert pc.not_worse("B").mean() <= ALPHA / 2


def test_one_sequence_of_a_betting_test() -> None:
    t = run_test([1.0] * 12, 0.0, 0.05)  # twelve wins in a row: the wealth passes 20
    assert t.rejected and t.at is not None and 3 < int(t.at) <= 12
    flat = run_test([1.0, -1.0] * 50, 0.0, 0.05)
    assert not flat.rejected and flat.more_needed() is None
    leaning = run_test([1.0, 0.0, 0.0, -1.0, 1.0] * 4, 0.0, 0.05)
    assert not leaning.rejected and leaning.more_needed() > 0
    with pytest.raises(ValueError, match="outside"):
        BettingTest(0.0, 0.05).update(2.0)


def scenes(n: int) -> list[str]:
    return [f"fresh/task/{1_000_000 + i}" for i in range(n)]


def outcomes(rate: float, n: int, seed: int) -> dict[str, bool]:
    rng = np.random.default_rng(seed)
    return dict(zip(scenes(n), (rng.random(n) < rate).tolist(), strict=True))


def test_the_rule_puts_safety_first_then_success_then_latency() -> None:
    n = 300
    base = outcomes(0.6, n, 0)
    success = {"careful": base, "rough": dict(base), "fast": dict(base)}
    force = {"careful": {s: 5.0 for s in scenes(n)}, "fast": {s: 5.0 for s in scenes(n)},
             "rough": {s: 30.0 if i % 3 == 0 else 5.0 for i, s in enumerate(scenes(n))}}  # 1 in 3 above 20 N
    d = decide(success, force, {"careful": 30.0, "rough": 1.0, "fast": 3.0})
    assert d["out_safety"] == {"rough": ["careful", "fast"]}  # the fastest, but it hurts the person
    assert d["recommended"] == "fast"  # the same successes as careful, and ten times faster
    assert any("**Recommended: fast**" in line for line in d["lines"])


def test_the_rule_drops_a_resolved_worse_policy_and_says_when_it_cannot_decide() -> None:
    n = 300
    good, bad = outcomes(0.8, n, 1), outcomes(0.3, n, 2)
    safe = {s: 0.0 for s in scenes(n)}
    d = decide({"good": good, "bad": bad}, {"good": safe, "bad": safe}, {"good": 30.0, "bad": 3.0})
    assert d["out_success"] == {"bad": ["good"]} and d["recommended"] == "good"
    close = outcomes(0.55, 60, 3)
    other = outcomes(0.5, 60, 4)
    d = decide({"a": close, "b": other}, {}, {"a": 3.0, "b": 4.0}, Rule(margin=0.05))
    assert d["status"] == "undecided" and d["recommended"] is None
    assert any("**Undecided** after 60 scenes" in line for line in d["lines"])


def test_scene_order_reads_the_ith_scene_of_every_task_first() -> None:
    names = ["fresh/b/1000001", "fresh/a/1000001", "fresh/b/1000000", "fresh/a/1000000"]
    assert scene_order(names) == ["fresh/a/1000000", "fresh/b/1000000", "fresh/a/1000001", "fresh/b/1000001"]
