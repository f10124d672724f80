"""How far the recording with recoveries pushed its demonstrator off the path (adlpipe.evaluation.recoveries):

    python disturbances.py data/recoveries/adl.h5 --split data/recoveries/split.json \
        -o metrics/recoveries_recording.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from adlpipe.dataset.splits import load_split
from adlpipe.evaluation.recoveries import recording_disturbances, recording_line


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data", type=Path)
    p.add_argument("--split", type=Path, required=True)
    p.add_argument("-o", "--output", type=Path, required=True)
    args = p.parse_args(argv)
    split = load_split(args.split)
    got = recording_disturbances(args.data, sorted(split["train"] + split["test"]))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(got, indent=1))
    print(recording_line(got))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
