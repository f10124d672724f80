"""Stress run of the ingest fuzzer: thousands of mutated bags (MCAP, ROS1 .bag, ROS2 .db3); with --dataset,
thousands of damaged datasets for the stages that read them.

    python bench/fuzz_ingest.py [--cases 5000] [--seed 0]
    python bench/fuzz_ingest.py --dataset [--cases 3000] [--train-every 20]

Byte mutations (truncate, flip, length, zero, duplicate, splice) and structure-aware ones (MCAP schema text,
summary statistics and declared array lengths; ROS1 connection headers; sqlite pages and the topics table; NUL bytes
in names), cycled over the three formats. Every case must end in an ingested episode or one clear AdlError line,
within a time limit, leaving no partial output. Prints the counts per format and mutation, and every failing case
with its seed to reproduce it.

--dataset: a three-episode sharded dataset is damaged one way per case (tests/dataset_fuzzing.py: the index's or an
episode file's bytes, a catalog row, a link's target, a dataset dropped, reshaped, retyped or made non-finite, an
attribute, an episode file removed); split and export run on every case, train and inspect on every
--train-every-th. Each must succeed or fail with one stderr line and a non-zero exit, leaving no output behind.
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


def fuzz_datasets(cases: int, seed: int, train_every: int) -> None:
    from dataset_fuzzing import DATASET_MUTATIONS, run_dataset_case

    with tempfile.TemporaryDirectory() as tmp:
        bags = Path(tmp) / "bags"
        subprocess.run([sys.executable, "-m", "adlpipe.record", "--episodes", "1", "--tasks", "wipe the nose",
                        "pass the water", "cover the food", "--size", "32", "--camera-hz", "2", "--out", str(bags)],
                       check=True, capture_output=True)
        base = Path(tmp) / "adl.h5"
        subprocess.run([sys.executable, "-m", "adlpipe.ingest", *map(str, sorted(bags.iterdir())), "-o", str(base),
                        "--size", "32"], check=True, capture_output=True)
        counts: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        failures = []
        t0 = time.time()
        for i in range(cases):
            mutation = DATASET_MUTATIONS[i % len(DATASET_MUTATIONS)]
            case_seed = seed * 1_000_003 + i
            for stage, out in run_dataset_case(base, mutation, case_seed, heavy=i % train_every == 0):
                counts[f"{mutation}/{stage}"][out.kind] += 1
                if not out.ok:
                    failures.append({"mutation": mutation, "seed": case_seed, "stage": stage, "kind": out.kind,
                                     "detail": out.detail[-600:]})
    report(cases, t0, counts, failures)


def report(cases: int, t0: float, counts: dict[str, collections.Counter], failures: list[dict]) -> None:
    total = collections.Counter()
    for c in counts.values():
        total.update(c)
    print(json.dumps({"cases": cases, "seconds": round(time.time() - t0, 1), "outcomes": dict(total),
                      "failures": len(failures), "by_case": {k: dict(v) for k, v in sorted(counts.items())}},
                     indent=1))
    for f in failures:
        print(json.dumps(f))
    sys.exit(1 if failures else 0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", type=int, default=5000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dataset", action="store_true", help="damage datasets for the reading stages instead of bags")
    p.add_argument("--train-every", type=int, default=20, help="--dataset: train and inspect on every N-th case")
    args = p.parse_args()
    if args.dataset:
        fuzz_datasets(args.cases, args.seed, args.train_every)
        return
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
    report(args.cases, t0, counts, failures)


if __name__ == "__main__":
    main()
