"""80/20 train/test split by episode, stratified per task, deterministic from a seed; stored beside the data.

    python -m adlpipe.split data/adl.h5 [-o data/split.json] [--test-fraction 0.2] [--seed 0]
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from .atomic import check_outputs, write_json_atomic
from .cli import NON_NEGATIVE, Parser, float_range
from .dataset import schema
from .errors import AdlError, run_cli


def make_split(tasks: dict[str, str], test_fraction: float, seed: int) -> dict[str, list[str]]:
    """tasks: episode name -> task. Every task with >= 2 episodes gets >= 1 test and >= 1 train episode."""
    by_task: dict[str, list[str]] = defaultdict(list)
    for name, task in tasks.items():
        by_task[task].append(name)
    train, test = [], []
    for i, task in enumerate(sorted(by_task)):
        names = sorted(by_task[task])
        rng = np.random.default_rng([seed, i])
        order = [names[j] for j in rng.permutation(len(names))]
        n_test = int(round(test_fraction * len(names)))
        if len(names) >= 2:
            n_test = min(max(n_test, 1), len(names) - 1)
        else:
            n_test = 0
        test += order[:n_test]
        train += order[n_test:]
    return {"train": sorted(train), "test": sorted(test)}


def load_split(path: Path) -> dict:
    try:
        split = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise AdlError(f"{path}: cannot read split ({exc}); run python -m adlpipe.split first") from exc
    if not isinstance(split, dict) or not {"train", "test"} <= set(split):
        raise AdlError(f"{path}: not a split file (needs 'train' and 'test' lists)")
    for part in ("train", "test"):
        names = split[part]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise AdlError(f"{path}: '{part}' must be a list of episode names (strings)")
    if set(split["train"]) & set(split["test"]):
        raise AdlError(f"{path}: episodes in both 'train' and 'test'")
    return split


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.split", __doc__)
    p.add_argument("data", type=Path, help="HDF5 dataset from adlpipe.ingest")
    p.add_argument("-o", "--output", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--test-fraction", type=float_range(0, 1, lo_open=True), default=0.2)
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    args = p.parse_args(argv)
    if not 0 < args.test_fraction < 1:
        raise AdlError("--test-fraction must be between 0 and 1")
    out = args.output or args.data.with_name("split.json")
    check_outputs(out)
    with schema.open_dataset(args.data) as f:
        tasks = {n: str(f[schema.EPISODES][n].attrs["task"]) for n in schema.episode_names(f)}
    if not tasks:
        raise AdlError(f"{args.data}: dataset has no episodes")
    split = make_split(tasks, args.test_fraction, args.seed)
    split.update({"seed": args.seed, "test_fraction": args.test_fraction, "data": str(args.data)})
    write_json_atomic(out, split)
    print(f"{out}: {len(split['train'])} train / {len(split['test'])} test episodes over "
          f"{len(set(tasks.values()))} task(s)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.split", main))
