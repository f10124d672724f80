"""Does the sequential decision keep its error rate, and how many scenes does it save? A simulation.

    python bench/sequential_tests.py [--sequences 2000] [--out results/bench/sequential_tests.md]

Two policies run on the same scenes (paired Bernoulli outcomes; on each scene both share a scene's difficulty with
probability 0.5, so about as many scenes are discordant as in adlpipe's replays). After every batch of 50 scenes
(replay --until-decided's default: 5 per task), up to a cap of 1,000:

- betting: adlpipe.evaluation.sequential.PairedComparison, the test replay --until-decided and adlpipe.trials use
  (alpha 0.05, margin 5 points), stopping at the first look where a difference is resolved;
- naive: McNemar's exact test (scipy.stats.binom) at 0.05 after every batch, stopping at the first p < 0.05: the
  procedure the anytime-valid test replaces;
- fixed n: McNemar's exact test once, at the smallest multiple of 50 scenes with at least the betting test's power.

Rows with equal rates count false decisions ("A better" or "B better"); rows at the margin count false "B not worse
than A by more than 5 points"; rows with a difference count power and scenes used.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.stats import binom

from adlpipe.evaluation.sequential import PairedComparison

BATCH, CAP, ALPHA, MARGIN, SHARED = 50, 1000, 0.05, 0.05, 0.5


def outcomes(pa: float, pb: float, n: int, k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n, k) paired outcomes of k sequences: on a scene, B reuses A's uniform draw with probability SHARED."""
    u1, u2 = rng.random((n, k)), rng.random((n, k))
    same = rng.random((n, k)) < SHARED
    return (u1 < pa).astype(float), (np.where(same, u1, u2) < pb).astype(float)


def mcnemar_p(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Exact two-sided McNemar p-value per sequence, from the first axis's scenes."""
    only_a, only_b = ((a == 1) & (b == 0)).sum(0), ((a == 0) & (b == 1)).sum(0)
    n = only_a + only_b
    return np.where(n > 0, np.minimum(1.0, 2 * binom.cdf(np.minimum(only_a, only_b), np.maximum(n, 1), 0.5)), 1.0)


def betting(a: np.ndarray, b: np.ndarray) -> tuple[PairedComparison, np.ndarray]:
    """The comparison over the first CAP scenes, and per sequence the scenes at the first look that decided a
    difference (CAP + 1: never)."""
    k = a.shape[1]
    pc = PairedComparison("A", "B", MARGIN, ALPHA, shape=(k,))
    stop = np.full(k, CAP + 1)
    for i in range(CAP):
        pc.update(a[i], b[i])
        if (i + 1) % BATCH == 0:
            decided = pc.better("A") | pc.better("B")
            stop = np.where((stop > CAP) & decided, i + 1, stop)
    return pc, stop


def naive(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per sequence: whether McNemar at ALPHA after any batch ever said 'different'."""
    hit = np.zeros(a.shape[1], bool)
    for n in range(BATCH, CAP + 1, BATCH):
        hit |= mcnemar_p(a[:n], b[:n]) < ALPHA
    return hit


def fixed_n_for(power: float, a: np.ndarray, b: np.ndarray) -> tuple[int | None, float]:
    """The smallest multiple of BATCH at which McNemar once at ALPHA has at least `power` (and its power)."""
    for n in range(BATCH, a.shape[0] + 1, BATCH):
        got = float((mcnemar_p(a[:n], b[:n]) < ALPHA).mean())
        if got >= power:
            return n, got
    return None, float("nan")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sequences", type=int, default=4000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("results/bench/sequential_tests.md"))
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    k = args.sequences
    lines = [f"# Sequential decisions: {k} simulated sequences per row, looks every {BATCH} scenes, cap {CAP}",
             "", f"`python bench/sequential_tests.py --sequences {k}` (adlpipe.evaluation.sequential; alpha 0.05, "
             "margin 5 points)", "",
             "## Equal success rates: false decisions (A or B declared better), nominal 5 %", "",
             "| A = B | betting (any look) | naive McNemar after every batch | McNemar once at 1,000 |",
             "| ---: | ---: | ---: | ---: |"]
    for rate in (0.3, 0.5, 0.7):
        a, b = outcomes(rate, rate, CAP, k, rng)
        pc, stop = betting(a, b)
        false_bet = float((stop <= CAP).mean())
        lines.append(f"| {rate:.0%} | {false_bet:.2%} | {naive(a, b).mean():.2%} | "
                     f"{(mcnemar_p(a, b) < ALPHA).mean():.2%} |")
    lines += ["", "## At the margin (B worse than A by exactly 5 points): false 'B not worse', nominal 2.5 %", "",
              "| A | B | betting at 1,000 scenes (any look) |", "| ---: | ---: | ---: |"]
    for pa in (0.5, 0.7):
        a, b = outcomes(pa, pa - MARGIN, CAP, k, rng)
        pc, _ = betting(a, b)
        lines.append(f"| {pa:.0%} | {pa - MARGIN:.0%} | {pc.not_worse('B').mean():.2%} |")
    lines += ["", "## A difference: scenes to a decision, against McNemar once at the fixed n of the same power", "",
              "| A | B | betting power by 1,000 | betting scenes used: mean (median) | fixed n, same power | "
              "scenes saved | betting: scenes by which 80 % decided | fixed n at 80 % power |",
              "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for pa, pb in ((0.5, 0.6), (0.5, 0.65), (0.4, 0.6), (0.5, 0.7)):
        a, b = outcomes(pa, pb, 3 * CAP, k, rng)
        _, stop = betting(a, b)
        power = float((stop <= CAP).mean())
        used = np.minimum(stop, CAP)  # a sequence that never decides costs the cap
        n_fixed, _ = fixed_n_for(power, a, b)
        saved = f"{1 - used.mean() / n_fixed:.0%}" if n_fixed else "-"
        at80 = f"{np.quantile(stop, 0.8):.0f}" if np.quantile(stop, 0.8) <= CAP else "> 1,000"
        n80, _ = fixed_n_for(0.8, a, b)
        lines.append(f"| {pa:.0%} | {pb:.0%} | {power:.1%} | {used.mean():.0f} ({np.median(used):.0f}) | "
                     f"{n_fixed or '> 3,000'} | {saved} | {at80} | {n80 or '> 3,000'} |")
    lines += ["", "## Equal rates: scenes to 'equivalent within 5 points' (both not-worse tests resolved)", "",
              "| A = B | decided by 1,000 | scenes used: median of those decided |", "| ---: | ---: | ---: |"]
    for rate in (0.5, 0.9):
        a, b = outcomes(rate, rate, CAP, k, rng)
        pc, _ = betting(a, b)
        at = np.maximum(pc.test_of("A", "not_worse").at, pc.test_of("B", "not_worse").at)
        done = pc.not_worse("A") & pc.not_worse("B")
        med = f"{np.median(at[done]):.0f}" if done.any() else "-"
        lines.append(f"| {rate:.0%} | {done.mean():.1%} | {med} |")
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
