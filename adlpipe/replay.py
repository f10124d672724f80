"""Execute predicted trajectories in MuJoCo and score each task's success predicate (the paper's Table 2).

    python -m adlpipe.replay --models models/fm_cnn models/dp_cnn models/bc_transformer

Flow-matching models run at every --fm-steps (default 1 and 16), DP at --dp-steps (default 16), BC once; each
from its best validation checkpoint (--checkpoint best) unless told otherwise. Success is the task's predicate in
adlpipe.sim.tasks: no contact force on the manikin above 20 N, grasps within 1 cm, strokes in contact, the spoon
held at the mouth, objects where they belong.

Scenes: --scenes N replays N fresh scenes per task (adlpipe.evaluation.scenes: the recorder's own scene generator at
indices no recording uses, the first frame rendered by the recordings' camera and stored as ingest stores it;
scene i of a task depends on (--scene-seed, task, i) alone, so every host replays the same scenes); without it,
the recorded test split. Each test episode's scene is rebuilt from the initial object and manikin poses stored
with it, a fresh scene from the poses it was drawn with; the predicted 3D
trajectory (32 waypoints, base frame) is executed open loop over the demonstration's duration by the same arm
controller and grasp rule that recorded the demonstrations. `demo` (the recorded trajectory itself) is always
scored too, as the reference, and `blind` (each task's mean training trajectory, adlpipe.policy.blind) as the floor.
Works on bags recorded by adlpipe.record (their frames name the world's objects).

Timing: by default every trajectory runs over its demonstration's own duration (--speed-profile demo), which no
deployed policy knows; --speed-profile fixed runs it instead over its own path length at the task's median
demonstrated speed (training split), a timing a deployed policy can have; both together are two rows per policy.

Every replayed episode keeps which parts of the predicate failed and its peak force on the manikin; the table
breaks failures down by part, safety first (adlpipe.evaluation.outcomes), and --failures writes a PNG strip per
policy of a few failed episodes.

Closed loop (--closed-loop TA [TA ...], models trained with train --closed-loop), on the recorded test split or on
fresh scenes (--scenes): the camera renders at the recorded rate (a fresh scene's: --scene-camera-hz, by default the
test episodes'); from its last To frames and the end effector's position at each, the policy predicts the next Tp
waypoints (relative to the last command); the arm executes TA of them and the policy re-plans, until the
demonstration's duration (times --time-limit) has passed. Each TA is a row of the table (the seed's Ta sweep);
replay's failure table says, per re-plan, how far the plan moves the arm against the demonstration from the same
phase, on and off the demonstrated path.

Until decided (--until-decided, open loop on fresh scenes): fresh scenes in batches of --batch per task, every
policy on the same scenes, until the decision rule (adlpipe.evaluation.decision: safety, then success with a
--margin non-inferiority margin, then latency from --eval) is decided by its anytime-valid tests, or --scenes per task
(the cap) are replayed. The details say where it stopped and why.

The person who moves (--moving-person, with --scenes): the same fresh scenes with the manikin's head and forearm
moving during the episode (adlpipe.sim.person), open or closed loop; open loop adds the row demo-still-person, the
still person's demonstration of the same scene run with the person moving (a perfect first-frame plan).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from .evaluation.replay_run import ReplayConfig, run_replay
from .plumbing.atomic import check_outputs
from .plumbing.cli import POSITIVE, SEED, Parser, config_from, float_range, int_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, run_cli
from .plumbing.runtime import Placement, add_device_args
from .policy.checkpoint import CHECKPOINTS

MAX_SCENES = 1000  # per task: 10,000 scenes' first frames, about 2 GB, fit a laptop; 1e9 were killed at 22 GB


def parse_args(argv: list[str] | None) -> ReplayConfig:
    """The options as the run's configuration, its outputs checked (writable, not a DVC stage's unless --force)."""
    p = Parser("python -m adlpipe.replay", __doc__)
    p.add_argument("--models", nargs="*", type=Path, default=[], help="model folders (holding model.pt)")
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--fm-steps", type=int_range(1, 100), nargs="+", default=[1, 16],
                   help="Euler steps of flow-matching models")
    p.add_argument("--dp-steps", type=int_range(1, 100), nargs="+", default=[16], help="DDPM steps of diffusion models")
    p.add_argument("--checkpoint", choices=sorted(CHECKPOINTS), default="best",
                   help="best: the epoch with the lowest validation px (default); last: the final epoch")
    p.add_argument("--max-episodes", type=POSITIVE,
                   help="replay at most this many test episodes, taken round-robin over the tasks")
    p.add_argument("--scenes", type=int_range(0, MAX_SCENES), default=0,
                   help="replay this many fresh scenes per task of the test split instead of the recorded test "
                   f"episodes, open or closed loop (0, default: the recorded test split; at most {MAX_SCENES}, "
                   "whose first frames are held in memory, about 0.2 MB each)")
    p.add_argument("--scene-seed", type=SEED, default=0,
                   help="the recording seed the fresh scenes are drawn with (record --seed; default 0)")
    p.add_argument("--scene-camera-size", type=int_range(16, 2048),
                   help="the recordings' camera size in px (record --size) at which fresh scenes are rendered before "
                   "they are resized as ingest resizes (default: the dataset's stored size)")
    p.add_argument("--time-limit", type=float_range(0.5, 10), default=1.0,
                   help="closed loop: run each rollout for this many times its demonstration's duration (default 1: "
                   "the duration itself, as open loop)")
    p.add_argument("--scene-camera-hz", type=float_range(0.1, 120),
                   help="the camera rate closed loop renders fresh scenes at (record --camera-hz; default: the "
                   "recorded test episodes' median rate)")
    p.add_argument("--moving-person", action="store_true",
                   help="fresh scenes (--scenes) in which the person moves: the head turns and nods and the forearm "
                   "lifts during the episode (adlpipe.sim.person; record --moving-person records such demonstrations)")
    p.add_argument("--until-decided", action="store_true",
                   help="open loop on fresh scenes: replay batches of --batch scenes per task until the decision rule "
                   "is decided (or --scenes per task, the cap, are replayed)")
    p.add_argument("--batch", type=POSITIVE, default=5, help="--until-decided: fresh scenes per task per batch")
    p.add_argument("--eval", type=Path, default=Path("metrics/eval_details.json"),
                   help="--until-decided: evaluate's details, for each policy's default sampler and latency")
    p.add_argument("--margin", type=float_range(0.0, 0.5), default=0.05,
                   help="--until-decided: the non-inferiority margin on success (default 0.05: 5 points)")
    p.add_argument("--alpha", type=float_range(0.001, 0.5), default=0.05,
                   help="--until-decided: the family-wise error rate per step of the rule (default 0.05)")
    p.add_argument("--workers", type=int_range(1, 256), default=min(2, os.cpu_count() or 1))
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--speed-profile", nargs="+", choices=["demo", "fixed"], default=["demo"],
                   help="open loop: run each trajectory over the demonstration's duration (demo), or over its own "
                   "path length at the task's median demonstrated speed (fixed, a row labelled @fixed-speed)")
    p.add_argument("--failures", type=Path, help="folder for a PNG strip per policy of up to --strip failed episodes")
    p.add_argument("--strip", type=int_range(1, 20), default=5, help="failed episodes per strip (one per task first)")
    p.add_argument("--closed-loop", type=POSITIVE, metavar="TA", nargs="+",
                   help="closed loop, for models trained with train --closed-loop: execute TA of the predicted "
                   "waypoints, then re-plan from new camera frames; several TA values are a sweep (e.g. 4 8 16)")
    p.add_argument("--temporal-ensemble", type=float_range(0, 10), metavar="M",
                   help="closed loop with --closed-loop 1: re-plan at every waypoint and execute the weighted mean "
                   "of every plan's waypoint for that step, weights exp(-M i) from the oldest plan on (ACT's temporal "
                   "ensembling; ACT uses M = 0.01); rows labelled Ta-1-ensemble")
    p.add_argument("--oracle", nargs="+", choices=["command", "ee"],
                   help="closed loop: also run each test demonstration's own future waypoints as plans, in the first "
                   "model's format (its horizon, rate and statistics) anchored as a policy of that target is: "
                   "command (relative to the last command) or ee (relative to the measured tcp); the executor's "
                   "ceiling")
    p.add_argument("--latency", nargs="+", type=latency_value, metavar="MS",
                   help="closed loop: the world goes on for MS milliseconds while each plan is computed (a number, or "
                   "'measured': each plan's own wall-clock time, a server's round trip included); several values are "
                   "a sweep, each a row labelled lat-MS-EXECUTION (lat-0ms: one row; default: none, the world waits "
                   "for every plan)")
    p.add_argument("--execution", nargs="+", choices=["sync", "async"], default=["sync"],
                   help="closed loop with --latency: the arm holds its last command while a plan is computed (sync, "
                   "default) or goes on with the previous plan's later waypoints (async, LeRobot's asynchronous "
                   "inference); both: two rows")
    p.add_argument("--server", metavar="URL",
                   help="closed loop: plan through a running policy server (python -m adlpipe.serve MODEL), e.g. "
                   "ws://127.0.0.1:8765, instead of in-process; --models names the model it serves (its format)")
    p.add_argument("--token-file", type=Path, help="--server: the file holding the server's shared token")
    p.add_argument("--trial-bags", type=Path, metavar="DIR",
                   help="closed loop: write every rollout to DIR as a trial bag (MCAP: frames, plans on /adl/plan, "
                   "/adl/policy, /adl/outcome), which ingest keeps and python -m adlpipe.trials decides from")
    p.add_argument("--metrics", type=Path, default=Path("metrics/replay.json"), help="overall success per policy")
    p.add_argument("--details", type=Path, default=Path("metrics/replay_details.json"), help="success per task")
    p.add_argument("--table", type=Path, default=Path("reports/table2.md"))
    add_device_args(p, compile_option=True)
    p.add_force()
    p.io(inputs=["models", "data", "split", "token_file"], outputs=["metrics", "details", "table", "failures",
                                                                    "trial_bags"],
         implied=lambda a: ([a.data.with_name("split.json")] if a.split is None else [])
         + ([a.eval] if a.until_decided else []))
    args = p.parse_args(argv)
    if args.moving_person and not args.scenes:
        raise AdlError("--moving-person: the person's motion is drawn with fresh scenes; add --scenes N")
    if args.temporal_ensemble is not None and args.closed_loop != [1]:
        raise AdlError("--temporal-ensemble: re-plans at every waypoint; use it with --closed-loop 1")
    if (args.latency or args.server or args.trial_bags) and not args.closed_loop:
        raise AdlError("--latency, --server and --trial-bags are closed-loop options; add --closed-loop TA")
    if args.server and len(args.models or []) != 1:
        raise AdlError("--server: give the one model the server serves with --models (its format and name)")
    if args.until_decided and (not args.scenes or args.closed_loop):
        raise AdlError("--until-decided: replays fresh scenes open loop; add --scenes N (the cap per task) and drop "
                       "--closed-loop")
    if args.until_decided and not args.eval.is_file():
        raise AdlError(f"--eval {args.eval}: no such file; --until-decided reads each policy's latency from "
                       "evaluate's details (python -m adlpipe.evaluate --details ...)")
    cfg = config_from(args, ReplayConfig, split=args.split or args.data.with_name("split.json"),
                      eval_details=args.eval, placement=Placement.from_args(args))
    check_outputs(cfg.metrics, cfg.details, cfg.table)
    refuse_pipeline_outputs([cfg.metrics, cfg.details, cfg.table, cfg.failures], args.force)
    return cfg


def latency_value(text: str) -> float | None:
    """--latency: milliseconds (0 to 10,000), or 'measured' (None)."""
    if text == "measured":
        return None
    return float_range(0, 10_000)(text)


def main(argv: list[str] | None = None) -> int:
    cfg = parse_args(argv)
    result = run_replay(cfg)
    for label, r in result.items():
        print(f"{label}: success {100 * r['overall']:.0f}% over {r['n']} {'scenes' if cfg.scenes else 'episodes'}")
    return 0

if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.replay", main))
