"""A study's training curves: training loss, held-out test loss and validation action error against optimiser
steps, one line per run (train's per-epoch CSVs), so that memorisation (the test loss turning up while the training
loss falls) shows per run. Run from a pipeline folder:

    python ../plot_losses.py metrics/train/*.csv -o reports/pusht_levers_losses.png --title "State Push-T"
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

from adlpipe.evaluation.training_log import read_training_log, validated_rows

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after the headless backend

PANELS = (("train_loss", "training loss (own objective)"), ("test_loss", "held-out test loss (own objective)"),
          ("val_px", "validation action error (own units)"))


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("logs", nargs="+", type=Path)
    p.add_argument("-o", "--out", type=Path, required=True)
    p.add_argument("--title", required=True, help="the benchmark's name, for the figure's title")
    args = p.parse_args(argv)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for log in sorted(args.logs):
        c = validated_rows(read_training_log(log), ("step", *(k for k, _ in PANELS)))
        for ax, (key, _) in zip(axes, PANELS, strict=True):
            ax.plot(c["step"], c[key], marker="o", markersize=3, label=log.stem)
    for ax, (_, label) in zip(axes, PANELS, strict=True):
        ax.set_xlabel("optimiser steps")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_yscale("log")
    axes[2].legend(fontsize=7)
    fig.suptitle(f"{args.title}: training curves per run (each objective's loss is on its own scale)")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
