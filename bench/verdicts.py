"""The interrupt benches' tally: run a randomly timed interrupt again and again, count what each run says."""

from __future__ import annotations

import random
import subprocess
import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path


def record_small(out: Path) -> list[Path]:
    """Six small bags (3 episodes of 2 tasks, 32 px, 5 Hz): what each interrupted run works on."""
    subprocess.run([sys.executable, "-m", "adlpipe.record", "--out", str(out), "--episodes", "3", "--size", "32",
                    "--camera-hz", "5", "--tasks", "comb the hair", "pass the water"], check=True, capture_output=True)
    return sorted(out.iterdir())


def tally(runs: int, span: float, seed: int, one_run: Callable[[float], str], title: str) -> int:
    """Run one_run(delay) `runs` times with delays drawn from 0.2 s to `span`; print each verdict and the counts;
    1 if any verdict is BAD."""
    rng = random.Random(seed)
    counts: Counter = Counter()
    for k in range(runs):
        verdict = one_run(rng.uniform(0.2, span))
        counts[verdict] += 1
        print(f"run {k + 1}: {verdict}", flush=True)
    print(f"\n{runs} runs {title}:")
    for verdict, n in counts.most_common():
        print(f"  {n:3d}  {verdict}")
    return 1 if any("BAD" in v for v in counts) else 0
