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

import argparse
import os
import sys
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .dataset import schema
from .dataset.splits import load_split
from .evaluation.decision import Rule, decide_replay
from .evaluation.jobs import run_jobs, success_summary
from .evaluation.outcomes import failure_sections, failure_strips, success_table
from .evaluation.replay import (
    ENSEMBLED,
    LoopOptions,
    camera_rate,
    closed_loop_one,
    closed_loop_scenes,
    demonstrated_speeds,
    every_task_first,
    oracle_jobs,
    path_length,
    replay_one,
    training_summary,
)
from .evaluation.scenes import STILL_DEMO, ReplayScene, fresh_scene, from_episode
from .evaluation.tables import FIXED
from .plumbing.atomic import check_outputs, json_text, write_all_atomic
from .plumbing.cli import POSITIVE, SEED, Parser, float_range, int_range, read_token_file
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, read_json_object, run_cli
from .plumbing.journal import Journal, Section, fingerprint
from .plumbing.runtime import Placement, add_device_args
from .plumbing.workers import stoppable_pool
from .policy.blind import BLIND, blind_predictions, task_means
from .policy.checkpoint import CHECKPOINTS, load_policy
from .policy.inference import label_of, predict_episodes, predict_scenes, steps_for

MAX_SCENES = 1000  # per task: 10,000 scenes' first frames, about 2 GB, fit a laptop; 1e9 were killed at 22 GB


def parse_args(argv: list[str] | None) -> argparse.Namespace:
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
    return args


def recorded_episodes(args: argparse.Namespace, names: list[str]) -> tuple[list, list[float]]:
    """The named test episodes of the ADL world and their camera rates (one line for a foreign recording)."""
    from .sim.tasks import TASKS
    from .sim.world import SCENE_OBJECTS

    with schema.open_dataset(args.data, names) as f:
        eps = [schema.read_episode(f, n) for n in names]
        rates = [camera_rate(f, n) for n in names]
    for ep in eps:
        if ep.task not in TASKS:
            raise AdlError(f"{ep.source_path}: task {ep.task!r} is not a task of the MuJoCo ADL world")
        unknown = set(ep.object_names) - SCENE_OBJECTS
        if unknown:
            raise AdlError(f"{ep.source_path}: frames {sorted(unknown)} are not objects of the ADL world; "
                           "replay works on bags recorded by adlpipe.record")
    return eps, rates


def _fresh_one(job: tuple) -> ReplayScene:
    return fresh_scene(*job)


def fresh_scenes(args: argparse.Namespace, tasks: list[str], names: list[str],
                 indices: range | None = None) -> list[ReplayScene]:
    """Fresh scenes `indices` (default: the first args.scenes) of each task, built in a pool (each runs the
    demonstrator once per draw), rendered live in closed loop at the rate of the recorded test episodes `names`
    unless told."""
    from .sim.tasks import TASKS

    unknown = [t for t in tasks if t not in TASKS]
    if unknown:
        raise AdlError(f"--scenes: task(s) {unknown} of {args.data} are not tasks of the MuJoCo ADL world")
    with schema.open_dataset(args.data, names) as f:
        size, horizon = int(f.attrs["image_size"]), int(f.attrs["n_waypoints"])
        camera_hz = args.scene_camera_hz or float(np.median([camera_rate(f, n) for n in names]))
    jobs = [(t, i, args.scene_seed, args.scene_camera_size or size, size, horizon, camera_hz, args.moving_person)
            for t in tasks for i in (indices or range(args.scenes))]
    with stoppable_pool(args.workers) as pool:  # Ctrl-C stops the demonstrators at once
        return list(tqdm(pool.imap(_fresh_one, jobs, chunksize=2), total=len(jobs), desc="scenes", unit="scene",
                         file=sys.stderr, disable=None))


def open_loop_jobs(args: argparse.Namespace, split: dict, scenes: list[ReplayScene], recorded: list[str] | None,
                   checkpoint: str, placement: Placement) -> tuple[list[tuple], dict[str, np.ndarray]]:
    """Every (policy, scene, timing) replay, with each policy's predicted waypoints (u, v, x, y, z) per scene."""
    trajs = {"demo": np.stack([np.concatenate([s.traj2d, s.traj3d], 1) for s in scenes])}
    if any(s.still_traj is not None for s in scenes):  # the person moves: open loop's ceiling, on the scenes whose
        # still twin is the same scene (NaN: the demonstrator failed with the person moving and the scene was redrawn)
        nan = np.full_like(trajs["demo"][0], np.nan)
        trajs[STILL_DEMO] = np.stack([nan if s.still_traj is None else s.still_traj for s in scenes])
    try:
        trajs[BLIND] = blind_predictions(task_means(args.data, split["train"]), [s.task for s in scenes])
    except AdlError as exc:  # a test task without training episodes: no floor to state
        print(f"no blind baseline row: {exc}")
    for d in args.models:
        if recorded is not None:
            trajs.update(predict_episodes(d, checkpoint, args.data, recorded, args.fm_steps, args.dp_steps,
                                          args.seed, placement))
        else:
            trajs.update(predict_scenes(d, checkpoint, scenes, args.fm_steps, args.dp_steps, args.seed, placement))
    speeds = demonstrated_speeds(args.data, split["train"]) if "fixed" in args.speed_profile else {}
    jobs = []
    for label, traj in trajs.items():
        for i, s in enumerate(scenes):
            if np.isnan(traj[i]).any():
                continue
            if "demo" in args.speed_profile:
                jobs.append((label, s.name, s.task, s.object_names, s.objects, traj[i, :, 2:], s.duration_s,
                             s.person))
            if "fixed" in args.speed_profile:
                if s.task not in speeds:
                    raise AdlError(f"--speed-profile fixed: no training episodes of task {s.task!r}")
                duration = max(path_length(traj[i, :, 2:]) / speeds[s.task], 1.0)
                jobs.append((label + FIXED, s.name, s.task, s.object_names, s.objects, traj[i, :, 2:], duration,
                             s.person))
    return jobs, trajs


def closed_loop_jobs(args: argparse.Namespace, scenes: list[ReplayScene], checkpoint: str,
                     placement: Placement) -> list[tuple]:
    if not args.models:
        raise AdlError("--closed-loop needs --models")
    jobs = []
    for i, d in enumerate(args.models):
        policy = load_policy(d / checkpoint)[0]
        if not policy.cfg.closed_loop:
            raise AdlError(f"{d}: trained on first frames only; closed loop needs a model trained with "
                           "python -m adlpipe.train --closed-loop")
        if policy.cfg.target == "action":
            raise AdlError(f"{d}: predicts the bags' action stream, not end-effector waypoints; run it with "
                           "python -m adlpipe.benchmark (Push-T)")
        if policy.cfg.views > 1:
            raise AdlError(f"{d}: sees cameras {', '.join(policy.cfg.cameras)}; the ADL world renders one "
                           "camera, so closed-loop replay cannot feed it")
        if i == 0 and args.oracle:  # in the first model's format
            jobs += oracle_jobs(d, policy.cfg.horizon, checkpoint, scenes, args.oracle, args.closed_loop, placement,
                                args.time_limit, args.temporal_ensemble, loop_options(args))
        for steps in steps_for(policy.family, args.fm_steps, args.dp_steps):
            for ta in args.closed_loop:
                if ta > policy.cfg.horizon:
                    raise AdlError(f"--closed-loop {ta}: {d} predicts only {policy.cfg.horizon} waypoints")
                label = f"{label_of(d, policy.default_method, policy.family, steps)}/Ta-{ta}" + (
                    ENSEMBLED if args.temporal_ensemble is not None else "")
                for suffix, opts in loop_options(args):
                    jobs += [(label + suffix, str(d), checkpoint, sc, steps, ta, args.seed, placement, None,
                              args.time_limit, args.temporal_ensemble, opts) for sc in scenes]
    if args.trial_bags:  # trial k of every policy before trial k + 1 of any: the series a lab runs, alternating
        policy = [i for i, j in enumerate(jobs) if j[8] is None]  # not the oracle's: scenes in order per row
        order = sorted(range(len(policy)), key=lambda k: (k % len(scenes), k // len(scenes)))
        for trial, k in enumerate(order):
            i = policy[k]
            jobs[i] = (*jobs[i][:-1], replace(jobs[i][-1], trial_index=trial))
    return jobs


def latency_value(text: str) -> float | None:
    """--latency: milliseconds (0 to 10,000), or 'measured' (None)."""
    if text == "measured":
        return None
    return float_range(0, 10_000)(text)


def loop_options(args: argparse.Namespace) -> list[tuple[str, LoopOptions]]:
    """(label suffix, options) of every latency and execution row of a closed-loop replay."""
    token = read_token_file(args.token_file) if args.token_file else None
    trial_dir = str(args.trial_bags) if args.trial_bags else None
    base = LoopOptions(server=args.server, token=token, trial_dir=trial_dir)
    if not args.latency:
        return [("", base)]
    out = []
    for ms in args.latency:
        if ms == 0:  # nothing to wait for: holding and going on are the same rollout, one row
            out.append(("/lat-0ms", base))
            continue
        for mode in args.execution:
            name = "measured" if ms is None else f"{ms:g}ms"
            out.append((f"/lat-{name}-{mode}",
                        replace(base, latency_s=None if ms is None else ms / 1000.0, execution=mode)))
    return out


def test_tasks(data: Path, names: list[str]) -> list[str]:
    with schema.open_dataset(data, names) as f:
        return sorted({str(f[schema.EPISODES][n].attrs["task"]) for n in names})


def replay_until_decided(args: argparse.Namespace, split: dict, tasks: list[str], names: list[str], checkpoint: str,
                         placement: Placement, journal: Journal) -> tuple[list, dict, tuple, dict]:
    """Batches of fresh scenes, every policy on each, until the decision rule is decided or the cap is reached.
    Every batch's outcomes go into the journal under its own key, so a killed run resumes at its batch."""
    ev = read_json_object(args.eval, "evaluate details")
    rule = Rule(args.margin, args.alpha)
    scenes: list[ReplayScene] = []
    trajs: dict[str, list] = {}
    wins: dict = defaultdict(lambda: defaultdict(list))
    per_episode: dict = defaultdict(dict)
    diagnostics: dict = defaultdict(dict)
    looks, decision = [], None
    for start in range(0, args.scenes, args.batch):
        batch = fresh_scenes(args, tasks, names, range(start, min(start + args.batch, args.scenes)))
        jobs, got = open_loop_jobs(args, split, batch, None, checkpoint, placement)
        w, pe, dg = run_jobs(replay_one, jobs, args.workers, placement, Section(journal, f"batch{start}:"))
        scenes += batch
        for label, traj in got.items():
            trajs.setdefault(label, []).append(traj)
        for label in w:
            for task, oks in w[label].items():
                wins[label][task] += oks
            per_episode[label].update(pe[label])
            diagnostics[label].update(dg.get(label, {}))
        decision = decide_replay(ev, {"per_episode": per_episode, "diagnostics": diagnostics}, rule)
        if decision is None:
            raise AdlError(f"--until-decided: fewer than two of the policies in {args.eval} were replayed; the rule "
                           "chooses between evaluated models (--models)")
        looks.append({"scenes": len(scenes), "status": decision["status"], "recommended": decision["recommended"]})
        print(f"after {len(scenes)} scenes: {decision['status']}"
              + (f" ({decision['recommended']})" if decision["recommended"] else ""))
        if decision["status"] == "decided":
            break
    reason = (f"decided after {len(scenes)} scenes" if decision["status"] == "decided"
              else f"the cap ({args.scenes} per task) reached, undecided")
    sequential = {"batch_per_task": args.batch, "cap_per_task": args.scenes, "scenes": len(scenes),
                  "reason": reason, "looks": looks, "rule": rule.__dict__}
    return scenes, {k: np.concatenate(v) for k, v in trajs.items()}, (wins, per_episode, diagnostics), sequential


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    placement = Placement.from_args(args)
    checkpoint = CHECKPOINTS[args.checkpoint]
    check_outputs(args.metrics, args.details, args.table)
    refuse_pipeline_outputs([args.metrics, args.details, args.table, args.failures], args.force)
    split_path = args.split or args.data.with_name("split.json")
    split = load_split(split_path)
    names = split["test"]
    if args.max_episodes and args.max_episodes < len(names) and not args.scenes:
        names = every_task_first(args.data, names, args.max_episodes)
    if not names:
        raise AdlError("the test split is empty: nothing to replay")
    journal = Journal(args.details, fingerprint(args, [d / checkpoint for d in args.models], split_path, args.data))
    if journal.done:
        print(f"resuming: {len(journal.done)} policies replayed before ({journal.path})")
    trajs: dict[str, np.ndarray] = {}
    sequential = None
    if args.until_decided:
        tasks = test_tasks(args.data, names)
        with journal:
            scenes, trajs, (wins, per_episode, diagnostics), sequential = replay_until_decided(
                args, split, tasks, names, checkpoint, placement, journal)
        where = f"{len(scenes) // len(tasks)} fresh scenes per task (seed {args.scene_seed}), until decided"
    else:
        with journal:  # a clean refusal while building the jobs (a bad checkpoint, a foreign task) leaves none
            if args.scenes:
                scenes = fresh_scenes(args, test_tasks(args.data, names), names)
                person = ", the person moving" if args.moving_person else ""
                where = f"{args.scenes} fresh scenes per task (seed {args.scene_seed}{person})"
            else:
                eps, rates = recorded_episodes(args, names)
                scenes = (closed_loop_scenes(args.data, eps, rates) if args.closed_loop
                          else [from_episode(ep) for ep in eps])
                where = "test split"
            if args.closed_loop:
                worker, jobs = closed_loop_one, closed_loop_jobs(args, scenes, checkpoint, placement)
            else:
                worker = replay_one
                jobs, trajs = open_loop_jobs(args, split, scenes, None if args.scenes else names, checkpoint,
                                             placement)
            wins, per_episode, diagnostics = run_jobs(worker, jobs, args.workers, placement, journal)
    result = success_summary(wins)
    strips = {} if args.closed_loop else failure_strips(args.failures, scenes, trajs, diagnostics, per_episode,
                                                        args.strip)
    kind = ({"kind": "fresh", "per_task": len(scenes) // len({s.task for s in scenes}), "seed": args.scene_seed,
             "moving_person": args.moving_person} if args.scenes else {"kind": "recorded"})
    write_all_atomic({**strips,
        args.details: json_text({"episodes": len(scenes), "checkpoint": args.checkpoint, "scenes": kind,
                                 "success": result, "tasks": {s.name: s.task for s in scenes},
                                 "per_episode": per_episode, "diagnostics": diagnostics,
                                 "training": training_summary(args.models),
                                 **({"sequential": sequential} if sequential else {})}),
        args.metrics: json_text({"episodes": len(scenes), "checkpoint": args.checkpoint, "scenes": kind["kind"],
                                 "success": {label: round(r["overall"], 4) for label, r in result.items()}}),
        args.table: success_table(result, scenes, bool(args.closed_loop), args.checkpoint, where)
                     + failure_sections(bool(args.closed_loop), diagnostics, per_episode)})
    journal.close()
    for label, r in result.items():
        print(f"{label}: success {100 * r['overall']:.0f}% over {r['n']} {'scenes' if args.scenes else 'episodes'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.replay", main))
