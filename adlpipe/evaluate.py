"""Evaluate trained policies on the test split: trajectory error and inference time vs number of steps.

    python -m adlpipe.evaluate --models models/fm_cnn models/dp_cnn ... [--steps 1 2 4 8 16]

Both checkpoints of each model are evaluated: "best" (best.pt, the epoch with the lowest validation px) and "last"
(model.pt). Per checkpoint, sampler and step count: mean per-waypoint error in pixels of the stored image (its size
is stated; px224 is that figure rescaled by 224 / size, the paper's input size, not a measurement on 224 px images)
and centimetres (3D), per task and overall, each overall mean with its 95 % bootstrap interval over the test
episodes (adlpipe.evaluation.stats) and the per-episode errors kept for paired comparisons;
best-of-K error over K samples (how well the samples cover the demonstrated mode); mode commitment on the
two-mode tasks (the share of the K samples that lie nearer one of the scene's two demonstrated modes than their
average; both modes are rebuilt in the simulator from the stored scene, adlpipe.sim.modes); inference milliseconds
per sample (batch 1, encoder included, median of repeated runs). Writes the headline figures for `dvc metrics`
(--metrics, a few values per model), every figure with per-task detail (--details), a CSV of error/latency vs steps
for `dvc plots`, and a markdown table shaped like the paper's Table 1.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import torch

from .dataset import schema
from .dataset.splits import load_split
from .evaluation.accuracy import blind_rows, evaluate_models, reference_modes
from .evaluation.accuracy_tables import headline, steps_csv, table1
from .plumbing.atomic import check_outputs, json_text, write_all_atomic
from .plumbing.cli import NON_NEGATIVE, POSITIVE, SEED, Parser, int_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, run_cli
from .plumbing.journal import Journal, fingerprint
from .plumbing.runtime import Placement, add_device_args
from .policy.blind import BLIND
from .policy.checkpoint import CHECKPOINTS

STEPS = [1, 2, 4, 8, 16]


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.evaluate", __doc__)
    p.add_argument("--models", nargs="+", type=Path, required=True, help="model folders (holding model.pt)")
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--steps", nargs="+", type=int_range(1, 100), default=STEPS)
    p.add_argument("--fm-methods", nargs="+", default=["euler"], choices=["euler", "midpoint", "rk4"],
                   help="euler, midpoint, rk4")
    p.add_argument("--dp-methods", nargs="+", default=["ddpm", "ddim", "ddpm_trailing"],
                   choices=["ddpm", "ddim", "ddpm_trailing", "ddim_trailing"],
                   help="ddpm, ddim (leading spacing, as Diffusion Policy), ddpm_trailing, ddim_trailing")
    p.add_argument("--best-of", type=POSITIVE, default=8, help="K samples for the best-of-K error")
    p.add_argument("--repeats", type=POSITIVE, default=20, help="timed runs per latency figure (median)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--threads", type=NON_NEGATIVE, default=0)
    p.add_argument("--metrics", type=Path, default=Path("metrics/eval.json"), help="headline figures")
    p.add_argument("--details", type=Path, default=Path("metrics/eval_details.json"),
                   help="every figure, per checkpoint, sampler, step count and task")
    p.add_argument("--plots", type=Path, default=Path("metrics/steps.csv"))
    p.add_argument("--table", type=Path, default=Path("reports/table1.md"))
    p.add_argument("--workers", type=int_range(1, 256), default=min(2, os.cpu_count() or 1),
                   help="processes rebuilding the two-mode scenes in the simulator (mode commitment)")
    add_device_args(p, compile_option=True)
    p.add_force()
    p.io(inputs=["models", "data", "split"], outputs=["metrics", "details", "plots", "table"],
         implied=lambda a: [a.data.with_name("split.json")] if a.split is None else [])
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    placement = Placement.from_args(args)
    check_outputs(args.metrics, args.details, args.plots, args.table)
    refuse_pipeline_outputs([args.metrics, args.details, args.plots, args.table], args.force)
    split_path = args.split or args.data.with_name("split.json")
    split = load_split(split_path)
    if not split["test"]:
        raise AdlError("the test split is empty: record more episodes per task")
    with schema.open_dataset(args.data, split["test"]) as f:
        image_px = int(f[schema.EPISODES][split["test"][0]]["rgb"].shape[0])
    modes = reference_modes(args.data, split["test"], args.workers)
    for d in args.models:
        for name in CHECKPOINTS.values():
            if not (d / name).exists():
                raise AdlError(f"{d}: no {name}; train it first (python -m adlpipe.train)")
    journal = Journal(args.details, fingerprint(args, [d / n for d in args.models for n in CHECKPOINTS.values()],
                                                split_path, args.data))
    if journal.done:
        print(f"resuming: {len(journal.done)} model(s) evaluated before ({journal.path})")
    with journal:
        results, training = evaluate_models(args, journal, split["test"], image_px, modes, placement)
    try:
        blind = blind_rows(args.data, split, image_px, args.best_of)
        results[BLIND] = {"best": blind, "last": blind}
    except AdlError as exc:  # a test task without training episodes: no floor to state
        print(f"no blind baseline row: {exc}")
    title = "# Trajectory error and inference time on the test split\n\n"
    write_all_atomic({
        args.details: json_text({"n_test": len(split["test"]), "best_of": args.best_of, "training": training,
                                 "mode_scenes": len(modes),
                                 "device": str(placement.device), "precision": placement.precision,
                                 "compiled": placement.compile, "models": results}),
        args.metrics: json_text(headline(results, training, len(split["test"]))),
        args.plots: steps_csv(results, args.steps),
        args.table: title + table1(results, args.best_of, training)})
    journal.close()
    print(f"wrote {args.metrics}, {args.details}, {args.plots}, {args.table}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.evaluate", main))
