"""Train/test splits by episode: made stratified per task and seeded, read back with their types checked (the
split stage writes them; every stage after it reads them)."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from ..errors import AdlError


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
