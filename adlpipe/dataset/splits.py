"""Train/test splits by episode: made stratified per task and seeded, read back with their types checked (the
split stage writes them; every stage after it reads them)."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path, PurePath

import h5py
import numpy as np

from ..plumbing.errors import AdlError
from . import schema


def make_split(tasks: dict[str, str], test_fraction: float, seed: int,
               keys: dict[str, str] | None = None) -> dict[str, list[str]]:
    """tasks: episode name -> task. Every task with >= 2 episodes gets >= 1 test and >= 1 train episode.

    keys: episode name -> what orders it within its task before the seeded shuffle (default: the name). The
    split stage passes each episode's recording key (its bag's file name and segment), which a re-recording on
    another host keeps, where the name (the bag's sha256) changes with every rendered pixel."""
    keys = keys or {}
    by_task: dict[str, list[str]] = defaultdict(list)
    for name, task in tasks.items():
        by_task[task].append(name)
    train, test = [], []
    for i, task in enumerate(sorted(by_task)):
        names = sorted(by_task[task], key=lambda n: (keys.get(n, n), n))
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


def recording_keys(f: h5py.File, names: list[str]) -> dict[str, str]:
    """episode name -> its recording key: the source bag's file name, with the segment for a bag of several
    demonstrations. It does not depend on the host that recorded the bag (the sha256 does: see make_split)."""
    out = {}
    for n in names:
        a = f[schema.EPISODES][n].attrs
        seg = int(a.get("segment", -1))
        out[n] = PurePath(str(a["source_path"])).name + (f"#{seg}" if seg >= 0 else "")
    return out


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
