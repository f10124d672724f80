"""Execute predicted trajectories in MuJoCo and score each task's success predicate (the paper's Table 2).

    python -m adlpipe.replay --models models/fm_cnn models/dp_cnn models/bc_transformer

Flow-matching models run at every --fm-steps (default 1 and 16), DP at --dp-steps (default 16), BC once; each
from its best validation checkpoint (--checkpoint best) unless told otherwise. Success is the task's predicate in
adlpipe.sim.tasks: no contact force on the manikin above 20 N, grasps within 1 cm, strokes in contact, the spoon
held at the mouth, objects where they belong.

Each test episode's scene is rebuilt from the initial object and manikin poses stored with it; the predicted 3D
trajectory (32 waypoints, base frame) is executed open loop over the demonstration's duration by the same arm
controller and grasp rule that recorded the demonstrations. `demo` (the recorded trajectory itself) is always
scored too, as the reference, and `blind` (each task's mean training trajectory, adlpipe.policy.blind) as the floor.
Works on bags recorded by adlpipe.record (their frames name the world's objects).

Timing: by default every trajectory runs over its demonstration's own duration (--speed-profile demo), which no
deployed policy knows; --speed-profile fixed runs it instead over its own path length at the task's median
demonstrated speed (training split), a timing a deployed policy can have; both together are two rows per policy.

Every replayed episode keeps which parts of the predicate failed and its peak force on the manikin; the table
breaks failures down by part, safety first (adlpipe.outcomes), and --failures writes a PNG strip per policy of a
few failed episodes.

Closed loop (--closed-loop TA [TA ...], models trained with train --closed-loop): the camera renders at the
recorded rate; from its last To frames and the end effector's position at each, the policy predicts the next Tp
waypoints (relative to where the end effector is); the arm executes TA of them and the policy re-plans, until the
demonstration's duration has passed. Each TA is a row of the table (the seed's Ta sweep).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import sys
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import h5py
import numpy as np
import torch
from tqdm import tqdm

from .atomic import check_outputs, json_text, write_all_atomic
from .cli import POSITIVE, SEED, Parser, int_range
from .dataset import schema
from .dataset.loader import (
    Normalizer,
    anchor_series,
    normalize_state,
    observation_from_arrays,
    relative_waypoints,
)
from .dataset.splits import load_split
from .dvc_outputs import refuse_pipeline_outputs
from .errors import AdlError, run_cli
from .outcomes import breakdown_lines, failure_strip, pick_failures
from .policy.blind import BLIND, blind_predictions, task_means
from .policy.checkpoint import CHECKPOINTS, load_policy
from .policy.inference import label_of, predict, predict_episodes, steps_for
from .runtime import Placement, add_device_args
from .stats import median_cell, rate_cell, success_interval
from .tables import FIXED


def _replay_one(job: tuple) -> tuple[str, str, str, bool, dict]:
    from .sim.episode import replay_trajectory, spec_from_objects

    label, name, task, names, objects, traj3d, duration = job
    run = replay_trajectory(spec_from_objects(task, names, objects), traj3d, duration)
    return label, name, task, run.success, {"failed": [k for k, ok in run.checks.items() if not ok],
                                            "peak_force_n": round(float(run.peak_force_n), 2)}


def _closed_loop_one(job: tuple) -> tuple[str, str, str, bool, dict]:
    """Closed-loop replay of one episode with one model, or with the oracle (runs in a pool process: loads the
    model itself). The oracle's plans are the demonstration's own future waypoints in the model's target format,
    normalised with its statistics: they take exactly the path a prediction takes from here on."""
    from .sim.episode import replay_closed_loop, spec_from_objects

    label, model_dir, checkpoint, ep, camera_hz, steps, execute, seed, placement, oracle = job
    target = oracle[0] if oracle is not None else None
    torch.set_num_threads(1)
    policy, ck = load_policy(Path(model_dir) / checkpoint, placement)
    cfg = policy.cfg
    norm = Normalizer(ck["stats"])
    gen = placement.generator(seed)
    state_dim = cfg.state_dim // cfg.n_obs  # 4: tcp and gripper (3: a model trained before the gripper joined)

    def predict_normalised(frames: list, elapsed: float) -> torch.Tensor:
        if oracle is not None:
            _, series_t, series_p = oracle
            now = np.array([[np.interp(elapsed, series_t, series_p[:, d]) for d in range(3)]])
            rel = relative_waypoints(np.array([elapsed]), now, series_t, series_p, cfg.horizon, cfg.rate_hz,
                                     ep.K, ep.T_base_camera)
            return norm.normalize(torch.from_numpy(rel))
        image = np.concatenate([observation_from_arrays(rgb, ep.affordance, depth, cfg.image_size, cfg.use_depth)
                                for rgb, depth, _, _ in frames])
        state = np.stack([np.append(tcp, grip) for _, _, tcp, grip in frames])[:, :state_dim]
        obs = (torch.from_numpy(image)[None], normalize_state(state, ck["stats"])[None])
        return predict(policy, obs, steps, None, gen, placement)

    def plan(frames: list, elapsed: float) -> np.ndarray:
        """Offsets (Tp, 3) from the anchor, in metres: the unnormalised prediction's x, y, z."""
        return norm.unnormalize(predict_normalised(frames, elapsed))[0, :, 2:].numpy()

    spec = spec_from_objects(ep.task, ep.object_names, ep.objects)
    run = replay_closed_loop(spec, plan, ep.duration_s, cfg.rate_hz, execute, cfg.n_obs, ep.rgb.shape[0], camera_hz,
                             anchor="measured" if (target or cfg.target) == "ee" else "command")
    demo_len = path_length(ep.ee_pos)
    demo_at_rate = np.stack([np.interp(np.arange(0, ep.duration_s, 1 / cfg.rate_hz), ep.ee_t, ep.ee_pos[:, d])
                             for d in range(3)], 1)
    diag = {"failed": [k for k, ok in run.checks.items() if not ok], "peak_force_n": round(float(run.peak_force_n), 2),
            "end_error_cm": round(100 * float(np.linalg.norm(run.command_path[-1] - ep.ee_pos[-1])), 2),
            "path_ratio": round(path_length(run.tcp_path) / demo_len, 3),
            "still_s": round(longest_still(run.command_path, cfg.rate_hz), 2),
            "demo_still_s": round(longest_still(demo_at_rate, cfg.rate_hz), 2)}
    return label, ep.name, ep.task, run.success, diag


STILL_M = 0.002  # a waypoint that moves less than this from the previous one (2 cm/s at 10 Hz) is standing still


def longest_still(waypoints: np.ndarray, rate_hz: float) -> float:
    """The longest stretch (s) of consecutive waypoints at rate_hz that each moved less than STILL_M: a stall where
    the demonstration dwells only briefly (a grasp dwells 0.8 s)."""
    still = np.linalg.norm(np.diff(waypoints, axis=0), axis=1) < STILL_M
    best = run = 0
    for s in still:
        run = run + 1 if s else 0
        best = max(best, run)
    return best / rate_hz


def oracle_jobs(model_dir: Path, horizon: int, checkpoint: str, data: Path, eps: list, rates: list[float],
                formats: list[str], execute: list[int], placement: Placement) -> list[tuple]:
    """Closed-loop jobs whose plans are each test demonstration's own future waypoints, in `model_dir`'s target
    format (horizon, rate, statistics) with the anchor of each format: "command" relative to the last command,
    "ee" relative to the measured tcp (the executor's ceiling for policies trained on each)."""
    jobs = []
    with schema.open_dataset(data, [ep.name for ep in eps]) as f:
        series = {fmt: [anchor_series(f[schema.EPISODES][ep.name], fmt, f"{ep.source_path}")[:2] for ep in eps]
                  for fmt in formats}
    for fmt in formats:
        for ta in execute:
            if ta > horizon:
                raise AdlError(f"--closed-loop {ta}: {model_dir} predicts only {horizon} waypoints")
            jobs += [(f"oracle-{fmt}/Ta-{ta}", str(model_dir), checkpoint, ep, rate, 1, ta, 0, placement, (fmt, *s))
                     for ep, rate, s in zip(eps, rates, series[fmt], strict=True)]
    return jobs


def failure_table(diagnostics: dict[str, dict[str, dict]], per_episode: dict[str, dict[str, bool]]) -> str:
    """Where closed-loop rollouts fail: per policy, how many failed rollouts missed each part of the predicate,
    how far the last command ended from the demonstration's end (median, cm), how much of the demonstration's path
    length the arm travelled, and the longest time the command stood still against the demonstration's longest
    dwell (medians over the failed rollouts)."""
    parts = ["force", "touches", "stroke", "dwell", "placed"]
    lines = ["\n## Where the failed rollouts fail\n",
             "Failed rollouts per missed part of the predicate (a rollout may miss several); end error: the last "
             "command from the demonstration's end; path: the arm's path length over the demonstration's; still: "
             f"the longest stretch the command moved under {1000 * STILL_M:.0f} mm per waypoint, against the "
             "demonstration's (medians over the failed rollouts, with their 95 % bootstrap intervals).\n",
             "| policy | failed | " + " | ".join(parts) + " | end error cm | path | still s (demo) |",
             "| --- | ---: |" + " ---: |" * (len(parts) + 3)]
    for label, diags in diagnostics.items():
        bad = [d for name, d in diags.items() if not per_episode[label].get(name, False)]
        counts = " | ".join(str(sum(p in d["failed"] for d in bad)) for p in parts)
        err = median_cell([d["end_error_cm"] for d in bad]) if bad else "-"
        path = median_cell([d["path_ratio"] for d in bad], 2) if bad else "-"
        still = (f"{median_cell([d['still_s'] for d in bad])} ({median_cell([d['demo_still_s'] for d in bad])})"
                 if bad else "-")
        lines.append(f"| {label} | {len(bad)} of {len(diags)} | {counts} | {err} | {path} | {still} |")
    return "\n".join(lines) + "\n"


def path_length(traj3d: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(traj3d, axis=0), axis=1).sum())


def demonstrated_speeds(data: Path, train: list[str]) -> dict[str, float]:
    """task -> the median over its training demonstrations of path length / duration (m/s): the one speed a
    deployed policy may run every predicted path at, knowing the task but not this scene's demonstration."""
    per: dict[str, list[float]] = defaultdict(list)
    with schema.open_dataset(data, train) as f:
        for name in train:
            g = f[schema.EPISODES][name]
            per[str(g.attrs["task"])].append(path_length(g["traj3d"][()]) / max(float(g.attrs["duration_s"]), 1e-6))
    return {t: float(np.median(v)) for t, v in per.items()}


def every_task_first(data: Path, names: list[str], n: int) -> list[str]:
    """n episodes taken round-robin over the tasks (in split order within a task): a subset that still covers
    every task evenly."""
    with schema.open_dataset(data, names=[]) as f:
        task = {r["name"]: r["task"] for r in schema.read_catalog(f)}
    per: dict[str, list[str]] = defaultdict(list)
    for name in names:
        per[task.get(name, "")].append(name)
    out: list[str] = []
    for k in range(max(len(v) for v in per.values())):
        out += [v[k] for _t, v in sorted(per.items()) if k < len(v)]
    return out[:n]


def training_summary(models: list[Path]) -> dict[str, dict]:
    """Each model's convergence as training wrote it (metrics.json), for the report."""
    out = {}
    for d in models:
        try:
            m = json.loads((d / "metrics.json").read_text())
        except (OSError, ValueError):
            continue  # a model folder without metrics: nothing to say about its convergence
        out[d.name] = {k: m.get(k) for k in ("converged", "val_px_best", "val_px_best_ci", "optimizer_steps",
                                            "epochs")}
    return out


def camera_rate(f: h5py.File, name: str) -> float:
    """The recorded camera rate of an episode (median frame interval), at which closed-loop replay renders."""
    t = f[schema.EPISODES][name]["frames/t"][()]
    return float(1.0 / np.median(np.diff(t))) if len(t) > 1 else 15.0


def main(argv: list[str] | None = None) -> int:
    from .sim.tasks import TASKS
    from .sim.world import SCENE_OBJECTS

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
    p.add_argument("--oracle", nargs="+", choices=["command", "ee"],
                   help="closed loop: also run each test demonstration's own future waypoints as plans, in the first "
                   "model's format (its horizon, rate and statistics) anchored as a policy of that target is: "
                   "command (relative to the last command) or ee (relative to the measured tcp); the executor's "
                   "ceiling")
    p.add_argument("--metrics", type=Path, default=Path("metrics/replay.json"), help="overall success per policy")
    p.add_argument("--details", type=Path, default=Path("metrics/replay_details.json"), help="success per task")
    p.add_argument("--table", type=Path, default=Path("reports/table2.md"))
    add_device_args(p, compile_option=True)
    p.add_force()
    args = p.parse_args(argv)
    placement = Placement.from_args(args)
    if min(args.fm_steps + args.dp_steps) < 1:
        raise AdlError("--fm-steps and --dp-steps must be >= 1")
    checkpoint = CHECKPOINTS[args.checkpoint]
    check_outputs(args.metrics, args.details, args.table)
    refuse_pipeline_outputs([args.metrics, args.details, args.table, args.failures], args.force)
    split = load_split(args.split or args.data.with_name("split.json"))
    names = split["test"]
    if args.max_episodes and args.max_episodes < len(names):
        names = every_task_first(args.data, names, args.max_episodes)
    if not names:
        raise AdlError("the test split is empty: nothing to replay")
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
    if args.closed_loop:
        if not args.models:
            raise AdlError("--closed-loop needs --models")
        worker = _closed_loop_one
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
                jobs += oracle_jobs(d, policy.cfg.horizon, checkpoint, args.data, eps, rates, args.oracle,
                                    args.closed_loop, placement)
            for steps in steps_for(policy.family, args.fm_steps, args.dp_steps):
                for ta in args.closed_loop:
                    if ta > policy.cfg.horizon:
                        raise AdlError(f"--closed-loop {ta}: {d} predicts only {policy.cfg.horizon} waypoints")
                    label = f"{label_of(d, policy.default_method, policy.family, steps)}/Ta-{ta}"
                    jobs += [(label, str(d), checkpoint, ep, rate, steps, ta, args.seed, placement, None)
                             for ep, rate in zip(eps, rates, strict=True)]
    else:
        worker = _replay_one
        trajs = {"demo": np.stack([np.concatenate([ep.traj2d, ep.traj3d], 1) for ep in eps])}
        try:
            trajs[BLIND] = blind_predictions(task_means(args.data, split["train"]), [ep.task for ep in eps])
        except AdlError as exc:  # a test task without training episodes: no floor to state
            print(f"no blind baseline row: {exc}")
        for d in args.models:
            trajs.update(predict_episodes(d, checkpoint, args.data, names, args.fm_steps, args.dp_steps, args.seed,
                                     placement))
        speeds = demonstrated_speeds(args.data, split["train"]) if "fixed" in args.speed_profile else {}
        jobs = []
        for label, traj in trajs.items():
            for i, ep in enumerate(eps):
                if "demo" in args.speed_profile:
                    jobs.append((label, ep.name, ep.task, ep.object_names, ep.objects, traj[i, :, 2:], ep.duration_s))
                if "fixed" in args.speed_profile:
                    if ep.task not in speeds:
                        raise AdlError(f"--speed-profile fixed: no training episodes of task {ep.task!r}")
                    duration = max(path_length(traj[i, :, 2:]) / speeds[ep.task], 1.0)
                    jobs.append((label + FIXED, ep.name, ep.task, ep.object_names, ep.objects, traj[i, :, 2:],
                                 duration))
    wins: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    per_episode: dict[str, dict[str, bool]] = defaultdict(dict)
    diagnostics: dict[str, dict[str, dict]] = defaultdict(dict)
    # CUDA cannot be used in a forked child of a process that has used it: closed-loop workers on a GPU are spawned
    context = multiprocessing.get_context("spawn") if placement.device.type == "cuda" else None
    with ProcessPoolExecutor(max_workers=max(1, args.workers), mp_context=context) as pool:
        for label, name, task, ok, diag in tqdm(pool.map(worker, jobs, chunksize=4), total=len(jobs),
                                                desc="replay", unit="ep", file=sys.stderr, disable=None):
            wins[label][task].append(ok)
            per_episode[label][name] = bool(ok)
            if diag:
                diagnostics[label][name] = diag
    result = {}
    for label, per in wins.items():
        every = [o for v in per.values() for o in v]
        result[label] = {"overall": float(np.mean(every)), "n": len(every),
                         "interval": list(success_interval(sum(every), len(every))),
                         "per_task": {t: float(np.mean(v)) for t, v in sorted(per.items())},
                         "per_task_n": {t: len(v) for t, v in sorted(per.items())}}
    tasks = sorted({ep.task for ep in eps})
    per_task_n = {t: sum(ep.task == t for ep in eps) for t in tasks}
    lines = ["| policy | overall [95 %] | n | " + " | ".join(f"{t} (n = {per_task_n[t]})" for t in tasks) + " |",
             "| --- | ---: | ---: |" + " ---: |" * len(tasks)]
    for label, r in result.items():
        cells = " | ".join(rate_cell(round(r["per_task"][t] * r["per_task_n"][t]), r["per_task_n"][t])
                           if t in r["per_task"] else "-" for t in tasks)
        lines.append(f"| {label} | {rate_cell(round(r['overall'] * r['n']), r['n'])} | {r['n']} | {cells} |")
    mode = ("closed-loop (execute Ta of the predicted waypoints, then re-plan)" if args.closed_loop
            else "open-loop")
    title = (f"# Success rate (%) of {mode} execution in MuJoCo, test split, {args.checkpoint} checkpoints\n\n"
             "Success: the task's predicate, with any contact force on the manikin above 20 N a failure. Overall: "
             "the rate with Wilson's 95 % interval over n scenes; per task likewise over its n scenes (few: wide).\n\n")
    failures = failure_table(diagnostics, per_episode) if args.closed_loop else ""
    outcome = breakdown_lines(diagnostics, per_episode)
    if outcome:
        failures = ("\n## How the policies fail, safety first\n\nPer policy: its failed episodes; those with a "
                    "contact force on the person above 20 N (of all its episodes, Wilson's 95 % interval) and the "
                    "peak force over all of them; the failures missing each other part of the predicate (an episode "
                    "may miss several).\n\n" + "\n".join(outcome) + "\n" + failures)
    strips: dict[Path, bytes] = {}
    if args.failures is not None and not args.closed_loop:
        by_name = {ep.name: (i, ep) for i, ep in enumerate(eps)}
        tasks_of = {ep.name: ep.task for ep in eps}
        for label, diags in diagnostics.items():
            if label.endswith(FIXED):
                continue  # the same trajectories as the label's own strip, timed differently
            picked = pick_failures(diags, per_episode[label], tasks_of, args.strip)
            if picked:
                traj = trajs[label.removesuffix(FIXED)]
                strips[args.failures / f"{label.replace('/', '_')}.png"] = failure_strip(label, [
                    {"task": tasks_of[n], "rgb": by_name[n][1].rgb, "demo_px": by_name[n][1].traj2d,
                     "pred_px": traj[by_name[n][0], :, :2], **diags[n]} for n in picked])
    write_all_atomic({**strips,
        args.details: json_text({"episodes": len(eps), "checkpoint": args.checkpoint, "success": result,
                                 "tasks": {ep.name: ep.task for ep in eps}, "per_episode": per_episode,
                                 "diagnostics": diagnostics,
                                 "training": training_summary(args.models)}),
        args.metrics: json_text({"episodes": len(eps), "checkpoint": args.checkpoint,
                                 "success": {label: round(r["overall"], 4) for label, r in result.items()}}),
        args.table: title + "\n".join(lines) + "\n" + failures})
    for label, r in result.items():
        print(f"{label}: success {100 * r['overall']:.0f}% over {r['n']} episodes")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.replay", main))
