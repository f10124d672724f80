"""The lever study's training curves: held-out test loss and validation action error against optimiser steps,
one line per run (train's per-epoch CSVs), so that memorisation (the test loss turning up while the training loss
falls) shows per data size.

    python plot_losses.py metrics/train/*.csv -o reports/pusht_levers_losses.png
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after the headless backend


def read(path: Path) -> dict[str, list[float]]:
    """The rows of a training log that carry a validation (test loss and val px), as columns."""
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["test_loss"] and r["val_px"]]
    return {k: [float(r[k]) for r in rows] for k in ("step", "train_loss", "test_loss", "val_px")}


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("logs", nargs="+", type=Path)
    p.add_argument("-o", "--out", type=Path, required=True)
    args = p.parse_args(argv)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for log in sorted(args.logs):
        c = read(log)
        for ax, key in zip(axes, ("train_loss", "test_loss", "val_px"), strict=True):
            ax.plot(c["step"], c[key], marker="o", markersize=3, label=log.stem)
    for ax, label in zip(axes, ("training loss (own objective)", "held-out test loss (own objective)",
                                "validation action error (px of 512)"), strict=True):
        ax.set_xlabel("optimiser steps")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_yscale("log")
    axes[2].legend(fontsize=7)
    fig.suptitle("State Push-T: training curves per run (each objective's loss is on its own scale)")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
