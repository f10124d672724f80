"""80/20 train/test split by episode, stratified per task, deterministic from a seed; stored beside the data.

The split orders each task's episodes by their recording key (the bag's file name and segment), not by the
episode names (the bags' sha256, which change when another host renders a pixel differently), so a re-recording
anywhere gives the same split; the names stay the integrity check.

    python -m adlpipe.split data/adl.h5 [-o data/split.json] [--test-fraction 0.2] [--seed 0] [--skip-bad]

Every stage after it reads the episodes the split names, so --skip-bad here is where a dataset with a damaged
episode file goes on without it: the split leaves such episodes out (each named on stderr, and in the split's
"skipped") and every later stage reads only what it names.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .dataset import schema
from .dataset.splits import make_split, recording_keys
from .plumbing.atomic import check_outputs, write_json_atomic
from .plumbing.cli import SEED, Parser, float_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, run_cli


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.split", __doc__)
    p.add_argument("data", type=Path, help="HDF5 dataset from adlpipe.ingest")
    p.add_argument("-o", "--output", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--test-fraction", type=float_range(0, 1, lo_open=True), default=0.2)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--extend", type=Path, default=None, metavar="SPLIT",
                   help="keep an earlier split of the same recordings: its test episodes stay the test split, and "
                   "every other episode of the data is train (DAgger rollouts join the training data; the test "
                   "split never moves)")
    p.add_argument("--skip-bad", action="store_true",
                   help="leave out episodes whose files cannot be read (each named) instead of stopping")
    p.add_force()
    p.io(inputs=["data", "extend"], outputs=["output"])
    args = p.parse_args(argv)
    if not 0 < args.test_fraction < 1:
        raise AdlError("--test-fraction must be between 0 and 1")
    out = args.output or args.data.with_name("split.json")
    check_outputs(out)
    refuse_pipeline_outputs([out], args.force)
    names, bad = schema.readable_episodes(args.data) if args.skip_bad else (None, [])
    for line in bad:
        print(f"adlpipe.split: skipped bad episode: {line}", file=sys.stderr)
    with schema.open_dataset(args.data, names) as f:
        tasks = {n: str(f[schema.EPISODES][n].attrs["task"]) for n in names or schema.episode_names(f)}
        keys = recording_keys(f, list(tasks))
    if not tasks:
        raise AdlError(f"{args.data}: dataset has no {'readable ' if bad else ''}episodes")
    split: dict = make_split(tasks, args.test_fraction, args.seed, keys) if args.extend is None else \
        extended_split(args.extend, list(tasks))
    split.update({"seed": args.seed, "test_fraction": args.test_fraction, "data": str(args.data)})
    if bad:
        split["skipped"] = bad
    write_json_atomic(out, split)
    print(f"{out}: {len(split['train'])} train / {len(split['test'])} test episodes over "
          f"{len(set(tasks.values()))} task(s)" + (f", {len(bad)} bad episode(s) left out" if bad else ""))
    return 0


def extended_split(earlier: Path, names: list[str]) -> dict:
    """An earlier split's test episodes as the test split, every other episode of the data as train."""
    from .dataset.splits import load_split

    test = list(load_split(earlier)["test"])
    have = set(names)
    gone = [n for n in test if n not in have]
    if gone:
        raise AdlError(f"--extend {earlier}: its test episode {gone[0]} is not in the data ({len(gone)} missing); "
                       "extend a split of the same recordings")
    held = set(test)
    return {"train": [n for n in names if n not in held], "test": test, "extends": str(earlier)}


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.split", main))
