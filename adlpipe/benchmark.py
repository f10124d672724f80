"""Closed-loop evaluation on the seed's Table 2 benchmarks, Push-T and Franka Kitchen: trained policies act in the
environment from seeded initial conditions.

    python -m adlpipe.benchmark --models models/fm_cnn models/dp_cnn --steps 2 16 --episodes 50
    python -m adlpipe.benchmark --env kitchen --models models/fm_cnn models/dp_cnn --steps 2 16 --episodes 50

Each model (trained with `train --closed-loop --target action` on the environment's bags; Franka Kitchen's with
--no-image, on the state alone; on Push-T either: a --no-image policy sees the keypoint state, the T's 8 keypoints
and the agent, as in pipelines/pusht's state variant) runs from initial conditions seed0, seed0+1, ... (none of them
a training demonstration's: record uses 0..N-1, the default seed0 is 100,000), predicting Tp actions from To
observations, executing Ta, re-planning, until the environment's step limit (Push-T 300, Franka Kitchen 280). Per
model, checkpoint (--checkpoints: best validation, last) and step count: the mean score with its bootstrap interval,
the success rate with Wilson's, and milliseconds per plan; beside them, from the same initial conditions, the
references (the scripted demonstrator; on Push-T also the agent holding still, the coverage an episode starts with).
  Push-T: score = each episode's highest coverage of the goal (the seed's), success = coverage above 0.95.
  Franka Kitchen: score = the share of the four tasks (microwave, kettle, light switch, slide cabinet) done,
  success = all four; the table also gives each task's success rate.
--curve also runs every checkpoint train --save-every kept along training: the learning curves (a PNG) and the
seed's Table 2 columns, the best checkpoint's score and the mean over the last three.
Diffusion Policy samples with --dp-sampler (default DDPM on leading timesteps, as Diffusion Policy does; a
non-default sampler is named in the model's row).
Writes --metrics (headline), --details (per episode) and --table (the Table 2 replica).
"""

from __future__ import annotations

import sys
from pathlib import Path

from .envs.registry import BENCHMARKS
from .evaluation.benchmark_runs import CLIP_CHOICES, FIRST_SEED, BenchmarkConfig, run_benchmark
from .evaluation.benchmark_tables import compare, score_cell, success_cell
from .plumbing.atomic import check_outputs
from .plumbing.cli import SEED, Parser, config_from, float_range, int_range
from .plumbing.errors import AdlError, run_cli
from .policy.checkpoint import CHECKPOINTS
from .policy.objectives import DDPM


def parse_args(argv: list[str] | None) -> BenchmarkConfig | list[Path]:
    """The options as the run's configuration, its outputs checked; with --compare, the details files to compare."""
    p = Parser("python -m adlpipe.benchmark", __doc__)
    p.add_argument("--env", choices=sorted(BENCHMARKS), default="pusht")
    p.add_argument("--models", nargs="+", type=Path)
    p.add_argument("--compare", type=Path, nargs="+", metavar="DETAILS",
                   help="run nothing: compare every two rows of a details file written before (or of several, "
                   "their rows named by file), paired on the initial conditions both ran (bootstrap of the score "
                   "difference, McNemar on success)")
    p.add_argument("--steps", nargs="+", type=int_range(1, 100), default=[2, 16],
                   help="sampling steps of the generative models (BC: its one prediction)")
    p.add_argument("--dp-sampler", choices=DDPM.methods, default="ddpm",
                   help="Diffusion Policy's sampler (default ddpm, leading timesteps as Diffusion Policy; "
                   "ddim_trailing: deterministic, starting from the last timestep, the fair few-step choice)")
    p.add_argument("--clip-sample", choices=CLIP_CHOICES, default="own",
                   help="the clean-sample estimate held in [-1, 1] at every sampling step: own (each objective's "
                   "default: Diffusion Policy's on, flow matching's off), on or off for every generative model alike")
    p.add_argument("--noise-scale", type=float_range(0.0, 4.0, lo_open=True), default=1.0,
                   help="the samplers' starting noise (and DDPM's ancestral noise) times this, every generative model "
                   "alike: a sampling temperature (1: the N(0, I) they were trained from)")
    p.add_argument("--max-steps", type=int_range(1, 100_000),
                   help="end each policy episode after this many steps instead of the environment's limit (Push-T "
                   "300, Franka Kitchen 280): does more time let a policy finish? (the references keep the limit)")
    p.add_argument("--checkpoints", nargs="+", choices=sorted(CHECKPOINTS), default=["best", "last"],
                   help="which of each model's checkpoints to run (default: both)")
    p.add_argument("--episodes", type=int_range(1, 100_000), default=50, help="initial conditions (the seed: 500)")
    p.add_argument("--seed", type=SEED, default=FIRST_SEED, help="the first initial condition")
    p.add_argument("--execute", type=int_range(1, 256), default=8, help="Ta: actions executed per plan")
    p.add_argument("--workers", type=int_range(1, 256), default=2)
    p.add_argument("--curve", action="store_true",
                   help="also run every checkpoint kept along training (train --save-every) at --curve-steps on "
                   "--curve-episodes initial conditions: the learning curves, and the seed's max and last-3 columns")
    p.add_argument("--curve-steps", type=int_range(1, 100), default=16,
                   help="sampling steps along the curve (default 16; BC: its one prediction)")
    p.add_argument("--curve-episodes", type=int_range(1, 100_000),
                   help="initial conditions per checkpoint (default: --episodes)")
    p.add_argument("--reference-episodes", type=int_range(1, 100_000),
                   help="run the references on the first this many initial conditions only (default: --episodes; "
                   "Push-T's demonstrator plans each push for seconds)")
    p.add_argument("--metrics", type=Path, help="default: metrics/<env>.json")
    p.add_argument("--details", type=Path, help="default: metrics/<env>_details.json")
    p.add_argument("--table", type=Path, help="default: reports/<env>.md")
    p.add_argument("--curve-plot", type=Path, help="with --curve; default: reports/<env>_curves.png")
    p.io(inputs=["models", "compare"], outputs=["metrics", "details", "table", "curve_plot"])
    args = p.parse_args(argv)
    if args.compare:
        return list(args.compare)
    if not args.models:
        p.error("--models is required (or --compare DETAILS)")
    if args.seed + max(args.episodes, args.curve_episodes or 0) - 1 > 2**32 - 1:
        p.error(f"--seed {args.seed} with {max(args.episodes, args.curve_episodes or 0)} initial conditions runs "
                "past the largest seed 2**32 - 1")
    if len(set(map(Path.resolve, args.models))) < len(args.models):
        raise AdlError("--models: a model is named twice")
    c = config_from(args, BenchmarkConfig, metrics=args.metrics or Path(f"metrics/{args.env}.json"),
                    details=args.details or Path(f"metrics/{args.env}_details.json"),
                    table=args.table or Path(f"reports/{args.env}.md"),
                    curve_plot=(args.curve_plot or Path(f"reports/{args.env}_curves.png")) if args.curve else None)
    check_outputs(c.metrics, c.details, c.table, *([c.curve_plot] if c.curve_plot else []))
    return c


def main(argv: list[str] | None = None) -> int:
    c = parse_args(argv)
    if isinstance(c, list):  # --compare: run nothing
        compare(c)
        return 0
    rows, curves = run_benchmark(c)
    for (m, s, ck), r in rows.items():
        print(f"{m} {s} steps ({ck}): score {score_cell(r)}, success {success_cell(r)}")
    for (m, s), cv in curves.items():
        print(f"{m} {s} steps along training: max {cv['max']['score']:.3f} at step {cv['max']['step']}, "
              f"last 3 {cv['last']['score']:.3f}")
    return 0

if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.benchmark", main))
