"""A replay run, from its configuration to its outputs (`adlpipe replay` parses the options into a ReplayConfig and
calls run_replay): the scenes (the recorded test split, or fresh scenes built in a pool), the jobs (every policy,
open loop at each speed profile, or closed loop at each Ta, latency and execution), the until-decided batches, and
the details, metrics and table written atomically. The executor itself is adlpipe.evaluation.replay."""

from __future__ import annotations

import sys
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..dataset import schema
from ..dataset.splits import load_split
from ..plumbing.atomic import json_text, write_all_atomic
from ..plumbing.cli import read_token_file
from ..plumbing.errors import AdlError, read_json_object
from ..plumbing.journal import Journal, Section, fingerprint
from ..plumbing.runtime import Placement
from ..plumbing.workers import stoppable_pool
from ..policy.blind import BLIND, blind_predictions, task_means
from ..policy.checkpoint import CHECKPOINTS, load_policy
from ..policy.inference import label_of, predict_episodes, predict_scenes, steps_for
from .decision import Rule, decide_replay
from .jobs import run_jobs, success_summary
from .outcomes import failure_sections, failure_strips, success_table
from .replay import (
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
from .scenes import STILL_DEMO, ReplayScene, fresh_scene, from_episode
from .tables import FIXED


@dataclass(frozen=True)
class ReplayConfig:
    """What `adlpipe replay` was asked (its options, one field each: `adlpipe replay --help` says what each does)."""

    models: list[Path]
    data: Path
    split: Path  # the split JSON (the stage defaults it to split.json beside the data)
    metrics: Path
    details: Path
    table: Path
    placement: Placement
    fm_steps: list[int]
    dp_steps: list[int]
    checkpoint: str = "best"  # a key of CHECKPOINTS
    max_episodes: int | None = None
    scenes: int = 0  # fresh scenes per task; 0: the recorded test split
    scene_seed: int = 0
    scene_camera_size: int | None = None
    scene_camera_hz: float | None = None
    time_limit: float = 1.0
    moving_person: bool = False
    until_decided: bool = False
    batch: int = 5
    eval_details: Path = Path("metrics/eval_details.json")
    margin: float = 0.05
    alpha: float = 0.05
    workers: int = 1
    seed: int = 0
    speed_profile: list[str] = field(default_factory=lambda: ["demo"])
    failures: Path | None = None
    strip: int = 5
    closed_loop: list[int] | None = None
    temporal_ensemble: float | None = None
    oracle: list[str] | None = None
    latency: list[float | None] | None = None  # ms; None: each plan's measured time
    execution: list[str] = field(default_factory=lambda: ["sync"])
    server: str | None = None
    token_file: Path | None = None
    trial_bags: Path | None = None


def recorded_episodes(cfg: ReplayConfig, names: list[str]) -> tuple[list, list[float]]:
    """The named test episodes of the ADL world and their camera rates (one line for a foreign recording)."""
    from ..sim.tasks import TASKS
    from ..sim.world import SCENE_OBJECTS

    with schema.open_dataset(cfg.data, names) as f:
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


def fresh_scenes(cfg: ReplayConfig, tasks: list[str], names: list[str],
                 indices: range | None = None) -> list[ReplayScene]:
    """Fresh scenes `indices` (default: the first cfg.scenes) of each task, built in a pool (each runs the
    demonstrator once per draw), rendered live in closed loop at the rate of the recorded test episodes `names`
    unless told."""
    from ..sim.tasks import TASKS

    unknown = [t for t in tasks if t not in TASKS]
    if unknown:
        raise AdlError(f"--scenes: task(s) {unknown} of {cfg.data} are not tasks of the MuJoCo ADL world")
    with schema.open_dataset(cfg.data, names) as f:
        size, horizon = int(f.attrs["image_size"]), int(f.attrs["n_waypoints"])
        camera_hz = cfg.scene_camera_hz or float(np.median([camera_rate(f, n) for n in names]))
    jobs = [(t, i, cfg.scene_seed, cfg.scene_camera_size or size, size, horizon, camera_hz, cfg.moving_person)
            for t in tasks for i in (indices or range(cfg.scenes))]
    with stoppable_pool(cfg.workers) as pool:  # Ctrl-C stops the demonstrators at once
        return list(tqdm(pool.imap(_fresh_one, jobs, chunksize=2), total=len(jobs), desc="scenes", unit="scene",
                         file=sys.stderr, disable=None))


def open_loop_jobs(cfg: ReplayConfig, split: dict, scenes: list[ReplayScene], recorded: list[str] | None,
                   checkpoint: str, placement: Placement) -> tuple[list[tuple], dict[str, np.ndarray]]:
    """Every (policy, scene, timing) replay, with each policy's predicted waypoints (u, v, x, y, z) per scene."""
    trajs = {"demo": np.stack([np.concatenate([s.traj2d, s.traj3d], 1) for s in scenes])}
    if any(s.still_traj is not None for s in scenes):  # the person moves: open loop's ceiling, on the scenes whose
        # still twin is the same scene (NaN: the demonstrator failed with the person moving and the scene was redrawn)
        nan = np.full_like(trajs["demo"][0], np.nan)
        trajs[STILL_DEMO] = np.stack([nan if s.still_traj is None else s.still_traj for s in scenes])
    try:
        trajs[BLIND] = blind_predictions(task_means(cfg.data, split["train"]), [s.task for s in scenes])
    except AdlError as exc:  # a test task without training episodes: no floor to state
        print(f"no blind baseline row: {exc}")
    for d in cfg.models:
        if recorded is not None:
            trajs.update(predict_episodes(d, checkpoint, cfg.data, recorded, cfg.fm_steps, cfg.dp_steps,
                                          cfg.seed, placement))
        else:
            trajs.update(predict_scenes(d, checkpoint, scenes, cfg.fm_steps, cfg.dp_steps, cfg.seed, placement))
    speeds = demonstrated_speeds(cfg.data, split["train"]) if "fixed" in cfg.speed_profile else {}
    jobs = []
    for label, traj in trajs.items():
        for i, s in enumerate(scenes):
            if np.isnan(traj[i]).any():
                continue
            if "demo" in cfg.speed_profile:
                jobs.append((label, s.name, s.task, s.object_names, s.objects, traj[i, :, 2:], s.duration_s,
                             s.person))
            if "fixed" in cfg.speed_profile:
                if s.task not in speeds:
                    raise AdlError(f"--speed-profile fixed: no training episodes of task {s.task!r}")
                duration = max(path_length(traj[i, :, 2:]) / speeds[s.task], 1.0)
                jobs.append((label + FIXED, s.name, s.task, s.object_names, s.objects, traj[i, :, 2:], duration,
                             s.person))
    return jobs, trajs


def closed_loop_jobs(cfg: ReplayConfig, scenes: list[ReplayScene], checkpoint: str,
                     placement: Placement) -> list[tuple]:
    """Every (policy, Ta, latency row, scene) rollout, and the oracle's in the first model's format."""
    if not cfg.models:
        raise AdlError("--closed-loop needs --models")
    tas = cfg.closed_loop or []
    jobs = []
    for i, d in enumerate(cfg.models):
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
        if i == 0 and cfg.oracle:  # in the first model's format
            jobs += oracle_jobs(d, policy.cfg.horizon, checkpoint, scenes, cfg.oracle, tas, placement,
                                cfg.time_limit, cfg.temporal_ensemble, loop_options(cfg))
        for steps in steps_for(policy.family, cfg.fm_steps, cfg.dp_steps):
            for ta in tas:
                if ta > policy.cfg.horizon:
                    raise AdlError(f"--closed-loop {ta}: {d} predicts only {policy.cfg.horizon} waypoints")
                label = f"{label_of(d, policy.default_method, policy.family, steps)}/Ta-{ta}" + (
                    ENSEMBLED if cfg.temporal_ensemble is not None else "")
                for suffix, opts in loop_options(cfg):
                    jobs += [(label + suffix, str(d), checkpoint, sc, steps, ta, cfg.seed, placement, None,
                              cfg.time_limit, cfg.temporal_ensemble, opts) for sc in scenes]
    if cfg.trial_bags:  # trial k of every policy before trial k + 1 of any: the series a lab runs, alternating
        rows = [i for i, j in enumerate(jobs) if j[8] is None]  # not the oracle's: scenes in order per row
        order = sorted(range(len(rows)), key=lambda k: (k % len(scenes), k // len(scenes)))
        for trial, k in enumerate(order):
            i = rows[k]
            jobs[i] = (*jobs[i][:-1], replace(jobs[i][-1], trial_index=trial))
    return jobs


def loop_options(cfg: ReplayConfig) -> list[tuple[str, LoopOptions]]:
    """(label suffix, options) of every latency and execution row of a closed-loop replay."""
    token = read_token_file(cfg.token_file) if cfg.token_file else None
    trial_dir = str(cfg.trial_bags) if cfg.trial_bags else None
    base = LoopOptions(server=cfg.server, token=token, trial_dir=trial_dir)
    if not cfg.latency:
        return [("", base)]
    out = []
    for ms in cfg.latency:
        if ms == 0:  # nothing to wait for: holding and going on are the same rollout, one row
            out.append(("/lat-0ms", base))
            continue
        for mode in cfg.execution:
            name = "measured" if ms is None else f"{ms:g}ms"
            out.append((f"/lat-{name}-{mode}",
                        replace(base, latency_s=None if ms is None else ms / 1000.0, execution=mode)))
    return out


def test_tasks(data: Path, names: list[str]) -> list[str]:
    with schema.open_dataset(data, names) as f:
        return sorted({str(f[schema.EPISODES][n].attrs["task"]) for n in names})


def replay_until_decided(cfg: ReplayConfig, split: dict, tasks: list[str], names: list[str], checkpoint: str,
                         placement: Placement, journal: Journal) -> tuple[list, dict, tuple, dict]:
    """Batches of fresh scenes, every policy on each, until the decision rule is decided or the cap is reached.
    Every batch's outcomes go into the journal under its own key, so a killed run resumes at its batch."""
    ev = read_json_object(cfg.eval_details, "evaluate details")
    rule = Rule(cfg.margin, cfg.alpha)
    scenes: list[ReplayScene] = []
    trajs: dict[str, list] = {}
    wins: dict = defaultdict(lambda: defaultdict(list))
    per_episode: dict = defaultdict(dict)
    diagnostics: dict = defaultdict(dict)
    looks: list[dict] = []
    decision: dict = {}
    for start in range(0, cfg.scenes, cfg.batch):
        batch = fresh_scenes(cfg, tasks, names, range(start, min(start + cfg.batch, cfg.scenes)))
        jobs, got = open_loop_jobs(cfg, split, batch, None, checkpoint, placement)
        w, pe, dg = run_jobs(replay_one, jobs, cfg.workers, placement, Section(journal, f"batch{start}:"))
        scenes += batch
        for label, traj in got.items():
            trajs.setdefault(label, []).append(traj)
        for label in w:
            for task, oks in w[label].items():
                wins[label][task] += oks
            per_episode[label].update(pe[label])
            diagnostics[label].update(dg.get(label, {}))
        decided = decide_replay(ev, {"per_episode": per_episode, "diagnostics": diagnostics}, rule)
        if decided is None:
            raise AdlError(f"--until-decided: fewer than two of the policies in {cfg.eval_details} were replayed; "
                           "the rule chooses between evaluated models (--models)")
        decision = decided
        looks.append({"scenes": len(scenes), "status": decision["status"], "recommended": decision["recommended"]})
        print(f"after {len(scenes)} scenes: {decision['status']}"
              + (f" ({decision['recommended']})" if decision["recommended"] else ""))
        if decision["status"] == "decided":
            break
    reason = (f"decided after {len(scenes)} scenes" if decision["status"] == "decided"
              else f"the cap ({cfg.scenes} per task) reached, undecided")
    sequential = {"batch_per_task": cfg.batch, "cap_per_task": cfg.scenes, "scenes": len(scenes),
                  "reason": reason, "looks": looks, "rule": rule.__dict__}
    return scenes, {k: np.concatenate(v) for k, v in trajs.items()}, (wins, per_episode, diagnostics), sequential


def run_replay(cfg: ReplayConfig) -> dict[str, dict]:
    """Replay every policy of `cfg` and write its details, metrics and table (and failure strips): each policy's
    success summary. Every finished policy (or batch) is journalled beside the details, so a killed run resumes."""
    checkpoint = CHECKPOINTS[cfg.checkpoint]
    split = load_split(cfg.split)
    names = split["test"]
    if cfg.max_episodes and cfg.max_episodes < len(names) and not cfg.scenes:
        names = every_task_first(cfg.data, names, cfg.max_episodes)
    if not names:
        raise AdlError("the test split is empty: nothing to replay")
    placement = cfg.placement
    journal = Journal(cfg.details, fingerprint(cfg, [d / checkpoint for d in cfg.models], cfg.split, cfg.data))
    if journal.done:
        print(f"resuming: {len(journal.done)} policies replayed before ({journal.path})")
    trajs: dict[str, np.ndarray] = {}
    sequential = None
    if cfg.until_decided:
        tasks = test_tasks(cfg.data, names)
        with journal:
            scenes, trajs, (wins, per_episode, diagnostics), sequential = replay_until_decided(
                cfg, split, tasks, names, checkpoint, placement, journal)
        where = f"{len(scenes) // len(tasks)} fresh scenes per task (seed {cfg.scene_seed}), until decided"
    else:
        with journal:  # a clean refusal while building the jobs (a bad checkpoint, a foreign task) leaves none
            if cfg.scenes:
                scenes = fresh_scenes(cfg, test_tasks(cfg.data, names), names)
                person = ", the person moving" if cfg.moving_person else ""
                where = f"{cfg.scenes} fresh scenes per task (seed {cfg.scene_seed}{person})"
            else:
                eps, rates = recorded_episodes(cfg, names)
                scenes = (closed_loop_scenes(cfg.data, eps, rates) if cfg.closed_loop
                          else [from_episode(ep) for ep in eps])
                where = "test split"
            if cfg.closed_loop:
                worker, jobs = closed_loop_one, closed_loop_jobs(cfg, scenes, checkpoint, placement)
            else:
                worker = replay_one
                jobs, trajs = open_loop_jobs(cfg, split, scenes, None if cfg.scenes else names, checkpoint,
                                             placement)
            wins, per_episode, diagnostics = run_jobs(worker, jobs, cfg.workers, placement, journal)
    result = success_summary(wins)
    strips = {} if cfg.closed_loop else failure_strips(cfg.failures, scenes, trajs, diagnostics, per_episode,
                                                       cfg.strip)
    kind = ({"kind": "fresh", "per_task": len(scenes) // len({s.task for s in scenes}), "seed": cfg.scene_seed,
             "moving_person": cfg.moving_person} if cfg.scenes else {"kind": "recorded"})
    write_all_atomic({**strips,
        cfg.details: json_text({"episodes": len(scenes), "checkpoint": cfg.checkpoint, "scenes": kind,
                                "success": result, "tasks": {s.name: s.task for s in scenes},
                                "per_episode": per_episode, "diagnostics": diagnostics,
                                "training": training_summary(cfg.models),
                                **({"sequential": sequential} if sequential else {})}),
        cfg.metrics: json_text({"episodes": len(scenes), "checkpoint": cfg.checkpoint, "scenes": kind["kind"],
                                "success": {label: round(r["overall"], 4) for label, r in result.items()}}),
        cfg.table: success_table(result, scenes, bool(cfg.closed_loop), cfg.checkpoint, where)
                   + failure_sections(bool(cfg.closed_loop), diagnostics, per_episode)})
    journal.close()
    return result
