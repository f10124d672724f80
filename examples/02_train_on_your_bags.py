"""Train a policy on your own bags: ingest them into a dataset, split it by task, train with the Python API.

    python examples/02_train_on_your_bags.py bags/*.mcap --work runs/mine --task "wipe the nose"
    python examples/02_train_on_your_bags.py bags/*.mcap --work runs/mine --config topics.yaml --model fm_cnn bc_cnn

A robot's bags rarely say which task they show: give it (--task) or name a task topic in the topic map
(--config; `adlpipe ingest --suggest-config BAG` drafts one). docs/guide/your-bags.md lists what a bag needs.
The same as commands: `adlpipe ingest`, `adlpipe split`, `adlpipe train`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from adlpipe import ingest, split
from adlpipe.training.run import TrainConfig, run_training


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="+")
    p.add_argument("--work", type=Path, required=True, help="folder for the dataset, its split and the models")
    p.add_argument("--task", help="the task of every bag (when the bags carry none)")
    p.add_argument("--config", help="your topic map (YAML)")
    p.add_argument("--size", type=int, default=128, help="stored image size in px")
    p.add_argument("--model", nargs="+", default=["fm_cnn"])
    p.add_argument("--epochs", type=int, default=800)
    args = p.parse_args()

    data, split_file = args.work / "robot.h5", args.work / "split.json"
    if not data.exists():
        given = [*(["--task", args.task] if args.task else []), *(["--config", args.config] if args.config else [])]
        ingest.main([*args.bags, "-o", str(data), "--size", str(args.size), *given])
        split.main([str(data), "-o", str(split_file)])
    for model in args.model:
        cfg, metrics = run_training(TrainConfig(model=model, data=data, split=split_file, out=args.work / model,
                                                epochs=args.epochs, batch_size=8, val_every=max(1, args.epochs // 4)))
        assert metrics is not None  # one process: it is rank 0
        print(f"{model}: {metrics['epochs']} epochs in {metrics['seconds']:.0f} s, test loss "
              f"{metrics['test_loss']:.4f}, val px best {metrics['val_px_best']}, converged {metrics['converged']}")


if __name__ == "__main__":
    main()
