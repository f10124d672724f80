"""mechanism.py's figures along training (issue L3): one row per checkpoint pair of the 30-epoch runs (every 5
epochs; the last is the final pair), the fit at three noise levels and the teacher-forced plans at 2 and 16 steps.

    python pipelines/kitchen_levers/mechanism_along.py results/mechanism_along/epoch_*.json \
        results/mechanism_e30.json > results/mechanism_along.md
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path


def epoch_of(path: Path) -> int:
    found = re.search(r"epoch_(\d+)", path.name)
    return int(found.group(1)) if found else 30  # mechanism_e30.json: the final pair


def row(path: Path) -> str:
    r = json.loads(path.read_text())
    fit = {f["k"]: f["fm_mse"] / f["dp_mse"] for f in r["fit"]}
    plans = {(p["model"], p["steps"]): p["by_phase"] for p in r["plans"]}
    cells = [f"{fit[k]:.2f}" for k in (0, 50, 99)]
    for steps in (2, 16):
        fm, dp = plans["FM", steps], plans["DP", steps]
        cells += [f"{fm['all']['error']:.4f} / {dp['all']['error']:.4f}",
                  f"{fm['kettle']['error']:.4f} / {dp['kettle']['error']:.4f}",
                  f"{fm['all']['spread']:.4f} / {dp['all']['spread']:.4f}"]
    return f"| {epoch_of(path)} | " + " | ".join(cells) + " |"


def main() -> None:
    paths = sorted((Path(p) for p in sys.argv[1:]), key=epoch_of)
    print("| epoch | fit FM / DP at k 0 | k 50 | k 99 | 2 steps: error FM / DP | kettle | spread | "
          "16 steps: error FM / DP | kettle | spread |")
    print("| ---: |" + " ---: |" * 9)
    for p in paths:
        print(row(p))


if __name__ == "__main__":
    main()
