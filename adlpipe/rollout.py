"""Roll a closed-loop policy out on the training scenes and record each rollout as a bag the expert has labelled
(DAgger), or with an operator who takes over off the path (HG-DAgger). The bags go the way a lab's go: ingest them
with the demonstrations, train --target recovery (--init the previous round's model; HG-DAgger: --corrections-only).

    python -m adlpipe.rollout models/fm_cnn --data data/adl.h5 --out data/dagger/r1/fm_cnn --seed 1
    python -m adlpipe.rollout models/fm_cnn --data data/adl.h5 --out data/hg/r1/fm_cnn --operator 2 0.3 0.5

Each bag carries what a closed-loop trial's does (camera, joints, tf, the command, the executed plans on /adl/plan)
plus the scene's demonstrated path on the topic map's reference topic (what train --target recovery labels every
frame from), the expert's plan at each re-plan on /adl/expert_plan, and with --operator the take-over flag on the
topic map's intervention topic (std_msgs/Bool). Scenes: the split's train episodes, never its test ones.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .plumbing.cli import SEED, Parser, float_range, int_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, run_cli


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.rollout", __doc__)
    p.add_argument("model", type=Path, help="a closed-loop model folder (train --closed-loop)")
    p.add_argument("--data", type=Path, required=True, help="the dataset whose train split's scenes are rolled out on")
    p.add_argument("--split", type=Path, default=None, help="split JSON (default: split.json beside the data)")
    p.add_argument("--out", type=Path, required=True, help="folder for the rollouts' bags (one MCAP per rollout)")
    p.add_argument("--checkpoint", choices=["best", "last"], default="best")
    p.add_argument("--execute", type=int_range(1), default=8, help="Ta: waypoints executed per re-plan (default 8)")
    p.add_argument("--steps", type=int_range(1), default=None,
                   help="sampler steps (default: 1 for flow matching, 16 for diffusion)")
    p.add_argument("--seed", type=SEED, default=0, help="the samplers' noise (give each round its own)")
    p.add_argument("--operator", type=float_range(0.0, lo_open=True), nargs=3, default=None,
                   metavar=("OFF_CM", "HOLD_S", "BACK_CM"),
                   help="HG-DAgger: an operator takes over when the executed commands stay more than OFF_CM off the "
                   "demonstrated path for HOLD_S, and drives until the command is within BACK_CM (e.g. 2 0.3 0.5)")
    p.add_argument("--time-limit", type=float_range(0.1), default=1.0,
                   help="rollouts run this many times the demonstration's duration (default 1)")
    p.add_argument("--limit", type=int_range(1), default=None,
                   help="at most this many training scenes, every task's in turn (a smaller round)")
    p.add_argument("--workers", type=int_range(1), default=2)
    p.add_argument("--summary", type=Path, default=None, help="JSON: per rollout, success and the operator's share")
    p.add_force()
    p.io(inputs=["model", "data", "split"], outputs=["out", "summary"],
         implied=lambda a: [a.data.with_name("split.json")] if a.split is None else [])
    args = p.parse_args(argv)
    refuse_pipeline_outputs([args.out, args.summary], args.force)
    checkpoint = "best.pt" if args.checkpoint == "best" else "model.pt"
    if not (args.model / checkpoint).is_file():
        raise AdlError(f"{args.model}: no {args.checkpoint} checkpoint; train the model first")
    from .evaluation.rollouts import RolloutConfig, run_rollouts, write_summary
    from .policy.checkpoint import load_checkpoint
    from .policy.models import DEFAULT_STEPS, MODELS, ModelConfig
    from .sim.dagger import OperatorRule

    config = load_checkpoint(args.model / checkpoint).get("config", {})
    model = ModelConfig.from_dict(config)
    if not model.closed_loop:
        raise AdlError(f"{args.model}: not a closed-loop model (train --closed-loop); a rollout re-plans from frames")
    steps = args.steps or DEFAULT_STEPS[MODELS[model.model][0]]  # the objective's default sampler (FM-1, DP-16)
    cfg = RolloutConfig(args.model, args.data, args.split or args.data.with_name("split.json"), args.out, checkpoint,
                        args.execute, model.rate_hz, steps, args.seed,
                        OperatorRule(*args.operator) if args.operator else None, args.time_limit, args.workers,
                        args.limit)
    s = run_rollouts(cfg)
    if args.summary:
        write_summary(args.summary, s)
    who = f", the operator drove {s['operator_plans']} of {s['plans']} re-plans" if args.operator else ""
    print(f"{args.out}: {s['rollouts']} rollouts of {args.model.name}, success {100 * s['success']:.1f} %{who}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.rollout", main))
