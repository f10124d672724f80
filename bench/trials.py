"""adlpipe trials on a long series: the rule after every trial must stay linear in the trials.

    python bench/trials.py --rows 200000          # two equal policies: the rule never stops, every row is read

Writes a CSV of alternating trials of two policies with the same success rate and runs the rule with no margin
(--margin 0: equal policies are never shown better nor not worse, so no decision ends the series early and every
row costs its update); runs `python -m adlpipe.trials` on it and prints the wall time, the rows per
second and the peak memory of the stage's process (getrusage of the child).
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", type=int, default=200_000)
    args = p.parse_args()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "trials.csv"
        ok = rng.random(args.rows) < 0.6
        csv.write_text("policy,success\n" + "".join(f"{'ab'[i % 2]},{int(s)}\n" for i, s in enumerate(ok)))
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "adlpipe.trials", str(csv), "--margin", "0"],
                              capture_output=True, text=True)
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(proc.stderr)
    read = sum(1 for line in proc.stdout.splitlines() if line.startswith("trial "))
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(f"{args.rows} rows, {read} decided on: {wall:.1f} s ({read / wall:,.0f} trials/s), peak {peak_mb:.0f} MB; "
          f"last: {proc.stdout.splitlines()[-1][:100]}")


if __name__ == "__main__":
    main()
