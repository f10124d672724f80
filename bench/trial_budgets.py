"""What a lab's 30-100 trials can decide, at which margin and alpha: a simulation of `adlpipe trials`' test.

    python bench/trial_budgets.py [--sequences 4000] [--out results/bench/trial_budgets.md]

Two policies tried on a robot alternately (each A trial paired with the next B trial; paired Bernoulli outcomes,
sharing a trial's difficulty with probability 0.5 as in bench/sequential_tests.py), the test looked at after every
pair as `adlpipe trials` does (adlpipe.evaluation.sequential.PairedComparison, anytime-valid). B is the faster
policy: the decision recommends it once it is resolved not worse than A by more than the margin, and A once A is
resolved better. Per row: the share of sequences decided by 30, 60 and 100 pairs, and what was decided.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from adlpipe.evaluation.sequential import PairedComparison

SHARED = 0.5
CAPS = (30, 60, 100)


def simulate(pa: float, pb: float, margin: float, alpha: float, k: int,
             rng: np.random.Generator) -> dict[int, tuple[float, float, float]]:
    """Per cap: (share stopped with 'A better', with 'B not worse' (B recommended), with 'B better')."""
    n = CAPS[-1]
    u1, u2 = rng.random((n, k)), rng.random((n, k))
    a = (u1 < pa).astype(float)
    b = (np.where(rng.random((n, k)) < SHARED, u1, u2) < pb).astype(float)
    pc = PairedComparison("A", "B", margin, alpha, shape=(k,))
    verdict = np.zeros(k, int)  # 0 undecided, 1 A better, 2 B not worse (recommended), 3 B better
    out = {}
    for i in range(n):
        pc.update(a[i], b[i])
        now = np.where(pc.better("B"), 3, np.where(pc.better("A"), 1, np.where(pc.not_worse("B"), 2, 0)))
        verdict = np.where(verdict == 0, now, verdict)  # the first decision stops the series
        if i + 1 in CAPS:
            out[i + 1] = tuple(float((verdict == v).mean()) for v in (1, 2, 3))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sequences", type=int, default=4000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("results/bench/trial_budgets.md"))
    a = p.parse_args()
    rng = np.random.default_rng(a.seed)
    lines = [f"# What 30, 60 and 100 trial pairs decide: {a.sequences} simulated series per row",
             "", f"`python bench/trial_budgets.py --sequences {a.sequences}` (adlpipe.evaluation.sequential, a look "
             "after every pair; B is the faster policy)", "",
             "| A | B | margin | alpha | decided by 30 pairs | by 60 | by 100 | at 100: A better / B not worse / "
             "B better |", "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for pa, pb in ((0.6, 0.6), (0.7, 0.6), (0.7, 0.5), (0.8, 0.4)):
        for margin in (0.05, 0.10, 0.20):
            for alpha in (0.05, 0.10):
                r = simulate(pa, pb, margin, alpha, a.sequences, rng)
                cells = " | ".join(f"{100 * sum(r[c]):.0f} %" for c in CAPS)
                last = " / ".join(f"{100 * x:.0f}" for x in r[CAPS[-1]])
                lines.append(f"| {pa:.0%} | {pb:.0%} | {100 * margin:.0f} pts | {alpha:g} | {cells} | {last} % |")
    lines += ["", "Decided: the series stopped with A resolved better, B resolved better, or B (the faster) resolved "
              "not worse than A by more than the margin (then recommended for its speed)."]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
