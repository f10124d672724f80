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

from .evaluation.evaluate_run import STEPS, EvaluateConfig, run_evaluation
from .plumbing.atomic import check_outputs
from .plumbing.cli import NON_NEGATIVE, POSITIVE, SEED, Parser, config_from, int_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import run_cli
from .plumbing.runtime import Placement, add_device_args


def parse_args(argv: list[str] | None) -> EvaluateConfig:
    """The options as the run's configuration, its outputs checked (writable, not a DVC stage's unless --force)."""
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
    c = config_from(args, EvaluateConfig, split=args.split or args.data.with_name("split.json"),
                    placement=Placement.from_args(args))
    check_outputs(c.metrics, c.details, c.plots, c.table)
    refuse_pipeline_outputs([c.metrics, c.details, c.plots, c.table], args.force)
    return c


def main(argv: list[str] | None = None) -> int:
    c = parse_args(argv)
    run_evaluation(c)
    return 0

if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.evaluate", main))
