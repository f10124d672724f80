"""The closed-loop models' plans with their true observation history and with one that shows the arm standing still,
on the recorded test episodes (adlpipe.evaluation.history): does a model copy the motion it sees?

    python history.py models/fm_cnn models/dp_cnn models/bc_cnn --execute 8 -o metrics/history.json \
        --table reports/history.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from adlpipe.dataset.splits import load_split
from adlpipe.evaluation.history import MOVING_M, plan_lengths
from adlpipe.evaluation.stats import median_cell


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("models", nargs="+", type=Path)
    p.add_argument("--data", type=Path, default=Path("../../data/adl.h5"))
    p.add_argument("--split", type=Path, default=Path("../../data/split.json"))
    p.add_argument("--execute", type=int, default=8, help="Ta: the waypoints of a plan compared")
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--table", type=Path, required=True)
    args = p.parse_args(argv)
    names = load_split(args.split)["test"]
    rows, out = [], {}
    for d in args.models:
        steps = 16 if d.name.startswith("dp") else 1
        got = plan_lengths(d, "best.pt", args.data, names, args.execute, steps)
        moving = got["demo"] > MOVING_M
        true, frozen = got["true"][moving] / got["demo"][moving], got["frozen"][moving] / got["demo"][moving]
        out[d.name] = {k: v.round(4).tolist() for k, v in got.items()}
        first = got["first"] > 0
        rows.append(f"| {d.name} | {moving.sum()} | {median_cell(true, 2)} | {median_cell(frozen, 2)} | "
                    f"{median_cell(100 * got['true'][~moving], 1)} | {median_cell(100 * got['frozen'][~moving], 1)} | "
                    f"{median_cell(100 * got['error'][first], 1)} | {median_cell(100 * got['error'][~first], 1)} |")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(out))
    args.table.parent.mkdir(parents=True, exist_ok=True)
    args.table.write_text("\n".join([
        f"Over {len(names)} recorded test episodes, 12 evenly spaced frames each; Ta = {args.execute} waypoints. "
        f"Moving: windows whose demonstrated plan moves the arm at least {100 * MOVING_M:.0f} cm; ratio: the model's "
        "plan path over the demonstration's (median [95 %]). Dwell: the other windows, the plan's path in cm. Error: "
        f"how far the plan's waypoint {args.execute} lies from the demonstration's, cm, from an episode's first frame "
        "(the arm at home) and from the others.", "",
        "| model | moving windows | ratio, true history | ratio, history standing still | dwell cm, true | "
        "dwell cm, standing still | error cm, first frame | error cm, other frames |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |", *rows, ""]))
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    sys.exit(main(sys.argv[1:]))
