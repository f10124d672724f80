"""Stress run of the ingest fuzzer: thousands of mutated bags (MCAP, ROS1 .bag, ROS2 .db3).

    python bench/fuzz_ingest.py [--cases 5000] [--seed 0]

Byte mutations (truncate, flip, length, zero, duplicate, splice) and structure-aware ones (MCAP schema text,
summary statistics and declared array lengths; ROS1 connection headers; sqlite pages and the topics table; NUL bytes
in names), cycled over the three formats. Every case must end in an ingested episode or one clear AdlError line,
within a time limit, leaving no partial output. Prints the counts per format and mutation, and every failing case
with its seed to reproduce it.
"""

from __future__ import annotations

import argparse
import collections
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from fuzzing import MUTATIONS, STRUCTURED, run_case  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--cases", type=int, default=5000)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bases = {}
        for fmt, img in (("mcap", "raw"), ("bag", "jpeg"), ("db3", "png")):
            d = Path(tmp) / fmt
            subprocess.run([sys.executable, "-m", "adlpipe.record", "--episodes", "1", "--tasks", "wipe the nose",
                            "--format", fmt, "--image-format", img, "--size", "32", "--camera-hz", "2", "--out",
                            str(d)], check=True, capture_output=True)
            bases[fmt] = next(d.iterdir())
        counts: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        failures = []
        t0 = time.time()
        plan = [(fmt, m) for fmt in bases for m in MUTATIONS + STRUCTURED[fmt]]
        for i in range(args.cases):
            fmt, mutation = plan[i % len(plan)]
            seed, recover = args.seed * 1_000_003 + i, bool(i % 2)
            out = run_case(bases[fmt], mutation, seed, recover=recover)
            counts[f"{fmt}/{mutation}"][out.kind] += 1
            if not out.ok:
                failures.append({"format": fmt, "mutation": mutation, "seed": seed, "recover": recover,
                                 "kind": out.kind, "detail": out.detail[-600:]})
    total = collections.Counter()
    for c in counts.values():
        total.update(c)
    print(json.dumps({"cases": args.cases, "seconds": round(time.time() - t0, 1), "outcomes": dict(total),
                      "failures": len(failures), "by_case": {k: dict(v) for k, v in sorted(counts.items())}},
                     indent=1))
    for f in failures:
        print(json.dumps(f))
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
