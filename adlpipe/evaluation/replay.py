"""The replay executor: open-loop and closed-loop jobs run in MuJoCo pool processes, and what replay tables of
them (success per task, where closed-loop rollouts fail). The replay stage (adlpipe.replay) parses, calls, writes."""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
import torch

from ..dataset import schema
from ..dataset.loader import (
    command_series,
    relative_waypoints,
)
from ..geometry.transforms import path_at
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Placement
from .stats import median_cell


def replay_one(job: tuple) -> tuple[str, str, str, bool, dict]:
    from ..sim.episode import replay_trajectory, spec_from_objects

    label, name, task, names, objects, traj3d, duration, person = job
    run = replay_trajectory(spec_from_objects(task, names, objects, person), traj3d, duration)
    return label, name, task, run.success, {"failed": [k for k, ok in run.checks.items() if not ok],
                                            "peak_force_n": round(float(run.peak_force_n), 2)}


@dataclass(frozen=True)
class LoopOptions:
    """How a closed-loop rollout reaches its policy and what the world does meanwhile: in-process or through a
    running `adlpipe serve` (server: its ws:// address), the latency the world goes on for while a plan is computed
    (seconds; None: the measured time of each plan) and whether the arm holds ("sync") or goes on with the previous
    plan ("async") meanwhile; trial_dir: write each rollout there as a trial bag."""

    server: str | None = None
    token: str | None = None
    latency_s: float | None = 0.0
    execution: str = "sync"
    trial_dir: str | None = None
    trial_index: int = 0  # the trial's place in the series (its bag's clock: trials are read in this order)
    # A labelled rollout (DAgger; adlpipe.sim.dagger): the expert's plan at every re-plan and the scene's
    # demonstrated path go into the trial bag; with an operator rule, the operator takes over off the path
    labelled: bool = False
    operator: object | None = None  # adlpipe.sim.dagger.OperatorRule


def closed_loop_one(job: tuple) -> tuple[str, str, str, bool, dict]:
    """Closed-loop replay of one scene (a recorded test episode's or a fresh one) with one model, or with the oracle
    (runs in a pool process: loads the model itself, or talks to a policy server). The oracle's plans are the
    demonstration's own future waypoints in the model's target format, normalised with its statistics: they take
    exactly the path a prediction takes from here on. Through a server, the session is seeded as the in-process
    generator is: the same plans."""
    from ..deploy.planner import Observation, Planner
    from ..sim.episode import replay_closed_loop, spec_from_objects

    label, model_dir, checkpoint, sc, steps, execute, seed, placement, oracle, time_limit, ensemble, *rest = job
    opts: LoopOptions = rest[0] if rest else LoopOptions()
    torch.set_num_threads(1)
    planner = Planner.at(Path(model_dir) / checkpoint, placement, steps)
    cfg = planner.cfg
    gen = placement.generator(seed)
    state_dim = cfg.state_dim // cfg.n_obs  # 4: tcp and gripper (3: a model trained before the gripper joined)
    series_t, series_p = sc.series(oracle) if oracle is not None else (None, None)
    client = None
    if opts.server is not None and oracle is None:
        from ..deploy.client import PolicyClient

        client = PolicyClient(opts.server, opts.token, seed=seed)

    def observation(frames: list, anchor: np.ndarray) -> Observation:
        return Observation(rgb=np.stack([f[0] for f in frames]), affordance=sc.affordance.astype(np.float32),
                           depth=np.stack([f[1] for f in frames]) if cfg.use_depth else None,
                           state=np.stack([np.append(tcp, grip) for _, _, tcp, grip in frames])[:, :state_dim],
                           command=anchor, task=sc.task)

    def plan(frames: list, elapsed: float, anchor: np.ndarray) -> np.ndarray:
        """The next Tp waypoints in the base frame, from the anchor."""
        if oracle is not None:
            now = path_at(elapsed, series_t, series_p[:, :3])[None]
            rel = relative_waypoints(np.array([elapsed]), now, series_t, series_p, cfg.horizon, cfg.rate_hz,
                                     sc.K, sc.T_base_camera)
            offsets = planner.norm.unnormalize(planner.norm.normalize(torch.from_numpy(rel)))[0, :, 2:].numpy()
            return anchor + np.asarray(offsets, float)
        obs = observation(frames, anchor)
        if client is not None:
            return np.asarray(client.plan(task=obs.task, rgb=obs.rgb, affordance=obs.affordance, depth=obs.depth,
                                          state=obs.state, command=obs.command)["waypoints"], float)
        return planner.plan(obs, gen, steps).waypoints

    streams = trial_streams(sc, cfg.image_size) if opts.trial_dir else None
    spec = spec_from_objects(sc.task, sc.object_names, sc.objects, sc.person)
    labelled, expert = None, None
    if opts.labelled:
        from ..sim.dagger import Expert, LabelledRollout, Operator

        ref_t, ref_p = sc.series("command")
        expert = Expert(ref_t, ref_p, cfg.horizon, cfg.rate_hz)
        plan = labelled = LabelledRollout(plan, expert, streams, execute,
                                          Operator(expert, opts.operator) if opts.operator else None)
    try:
        run = replay_closed_loop(spec, plan, time_limit * sc.duration_s, cfg.rate_hz, execute, cfg.n_obs,
                                 sc.rgb.shape[0], sc.camera_hz,
                                 anchor="measured" if (oracle or cfg.target) == "ee" else "command",
                                 ensemble=ensemble, latency_s=opts.latency_s, execution=opts.execution,
                                 streams=streams, expert=expert)
    finally:
        if client is not None:
            client.close()
    demo_t, demo_p = sc.series("command") if sc.command is not None else sc.series("ee")
    demo_len = path_length(sc.ee_pos)
    demo_at_rate = np.stack([np.interp(np.arange(0, sc.duration_s, 1 / cfg.rate_hz), sc.ee_t, sc.ee_pos[:, d])
                             for d in range(3)], 1)
    diag = {"failed": [k for k, ok in run.checks.items() if not ok], "peak_force_n": round(float(run.peak_force_n), 2),
            "end_error_cm": round(100 * float(np.linalg.norm(run.command_path[-1] - sc.ee_pos[-1])), 2),
            "path_ratio": round(path_length(run.tcp_path) / demo_len, 3),
            "still_s": round(longest_still(run.command_path, cfg.rate_hz), 2),
            "demo_still_s": round(longest_still(demo_at_rate, cfg.rate_hz), 2), "plans": run.plans}
    if opts.latency_s == 0.0:  # with latency the executed commands are no longer whole chunks of Ta per re-plan
        diag.update(plan_diagnostics(run.command_path, demo_p[0], execute, cfg.rate_hz, demo_t, demo_p))
    if labelled is not None:
        diag["operator_plans"] = labelled.operator_plans
    if streams is not None:
        from ..deploy.trial_bags import write_trial_bag

        write_trial_bag(streams, Path(opts.trial_dir), label, sc.name, opts.trial_index, run.success,
                        float(run.peak_force_n))
    return label, sc.name, sc.task, run.success, diag


def trial_streams(sc: object, size: int) -> object:
    """An empty recording of a closed-loop rollout in scene `sc`, filled by the executor."""
    from ..sim.episode import Streams, spec_from_objects

    st = Streams(sc.task, spec_from_objects(sc.task, sc.object_names, sc.objects, sc.person),  # type: ignore[attr-defined]
                 sc.rgb.shape[0], sc.rgb.shape[0], np.eye(3), np.eye(4))  # type: ignore[attr-defined]
    st.affordance = sc.affordance  # type: ignore[attr-defined]
    return st


def median_or_none(values: np.ndarray) -> float | None:
    return round(float(np.median(values)), 3) if len(values) else None


ENSEMBLED = "-ensemble"  # label suffix of a closed loop with temporal ensembling (replay --temporal-ensemble)
OFF_PATH_M = 0.02  # a re-plan whose anchor lies further than this from the demonstrated path is off it


def plan_ratios(commands: np.ndarray, start: np.ndarray, execute: int, rate_hz: float, demo_t: np.ndarray,
                demo_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per re-plan, (how far the executed part of the plan moves the command against how far the demonstration
    moves it over the same time from the same phase, how far the anchor is from the demonstrated path in metres):
    the path length of the `execute` waypoints (from the anchor) over the demonstration's path length over
    execute / rate_hz seconds from its point nearest the anchor (searched forward along the demonstration, so that
    a rollout that lags is compared with where it is, not where the clock is). 1: the plan moves as the
    demonstration does; below 1: it moves the arm too little. Re-plans where the demonstration itself stands still
    (under 1 mm over the span: a dwell, the end) are left out."""
    span = execute / rate_hz
    chunks = commands.reshape(-1, execute, 3)
    anchors = np.vstack([start[None], chunks[:-1, -1]])
    ratios, off, j = [], [], 0
    for anchor, chunk in zip(anchors, chunks, strict=True):
        ahead = j + int(np.searchsorted(demo_t[j:], demo_t[j] + max(2 * span, 1.0)))  # not a later pass of a stroke
        dist = np.linalg.norm(demo_p[j:ahead + 1] - anchor, axis=1)
        j += int(np.argmin(dist))
        ts = np.linspace(demo_t[j], demo_t[j] + span, execute + 1)
        demo = path_length(path_at(ts, demo_t, demo_p[:, :3]))
        if demo > 1e-3:
            ratios.append(path_length(np.vstack([anchor, chunk])) / demo)
            off.append(float(dist.min()))
    return np.array(ratios), np.array(off)


def plan_diagnostics(commands: np.ndarray, start: np.ndarray, execute: int, rate_hz: float, demo_t: np.ndarray,
                     demo_p: np.ndarray) -> dict:
    """A rollout's plans against the demonstration (plan_ratios): the median ratio over all its re-plans, over those
    on the demonstrated path (anchor within OFF_PATH_M of it) and those off it, and the farthest it got (cm)."""
    ratios, off = plan_ratios(commands, start, execute, rate_hz, demo_t, demo_p)
    on = off <= OFF_PATH_M
    return {"plan_ratio": median_or_none(ratios), "plan_ratio_on_path": median_or_none(ratios[on]),
            "plan_ratio_off_path": median_or_none(ratios[~on]), "replans_off_path": int((~on).sum()),
            "replans": len(ratios), "off_path_cm": round(100 * float(off.max()), 2) if len(off) else None}


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


def oracle_jobs(model_dir: Path, horizon: int, checkpoint: str, scenes: list, formats: list[str],
                execute: list[int], placement: Placement, time_limit: float = 1.0,
                ensemble: float | None = None, loops: list[tuple[str, LoopOptions]] | None = None) -> list[tuple]:
    """Closed-loop jobs whose plans are each scene's demonstration's own future waypoints, in `model_dir`'s target
    format (horizon, rate, statistics) with the anchor of each format: "command" relative to the last command,
    "ee" relative to the measured tcp (the executor's ceiling for policies trained on each)."""
    missing = [sc.name for sc in scenes if sc.command is None]
    if "command" in formats and missing:
        raise AdlError(f"--oracle command: episode {missing[0]} has no commanded end-effector position "
                       "(frames/action); use --oracle ee")
    jobs = []
    for fmt in formats:
        for ta in execute:
            if ta > horizon:
                raise AdlError(f"--closed-loop {ta}: {model_dir} predicts only {horizon} waypoints")
            for suffix, opts in loops or [("", LoopOptions())]:  # the oracle plans in-process, never as a trial
                jobs += [(f"oracle-{fmt}/Ta-{ta}{ENSEMBLED if ensemble is not None else ''}{suffix}", str(model_dir),
                          checkpoint, sc, 1, ta, 0, placement, fmt, time_limit, ensemble,
                          replace(opts, server=None, trial_dir=None)) for sc in scenes]
    return jobs


def closed_loop_scenes(data: Path, eps: list, rates: list[float]) -> list:
    """The recorded test episodes as closed-loop scenes: each with its camera rate and its command series (None
    where the recording has none: only an "ee" oracle and policies can run there)."""
    from .scenes import from_episode

    out = []
    with schema.open_dataset(data, [ep.name for ep in eps]) as f:
        for ep, rate in zip(eps, rates, strict=True):
            try:
                command = command_series(f[schema.EPISODES][ep.name], ep.source_path)
            except AdlError:
                command = None
            out.append(from_episode(ep, rate, command))
    return out


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
             "demonstration's (medians over the failed rollouts, with their 95 % bootstrap intervals); plan / demo: "
             "per re-plan, the executed plan's path over the demonstration's from the same phase over the same time "
             "(median per rollout, then over all the policy's rollouts; 1: it moves as the demonstration does), "
             f"on the demonstrated path (the anchor within {100 * OFF_PATH_M:.0f} cm of it) and off it, with the "
             "share of re-plans made off it.\n",
             "| policy | failed | " + " | ".join(parts) + " | end error cm | path | still s (demo) | plan / demo | "
             "on path | off path | re-plans off path |",
             "| --- | ---: |" + " ---: |" * (len(parts) + 7)]
    for label, diags in diagnostics.items():
        bad = [d for name, d in diags.items() if not per_episode[label].get(name, False)]
        counts = " | ".join(str(sum(p in d["failed"] for d in bad)) for p in parts)
        err = median_cell([d["end_error_cm"] for d in bad]) if bad else "-"
        path = median_cell([d["path_ratio"] for d in bad], 2) if bad else "-"
        still = (f"{median_cell([d['still_s'] for d in bad])} ({median_cell([d['demo_still_s'] for d in bad])})"
                 if bad else "-")
        ratio = [_median_of(diags, k) for k in ("plan_ratio", "plan_ratio_on_path", "plan_ratio_off_path")]
        off = sum(d.get("replans_off_path", 0) for d in diags.values())
        total = sum(d.get("replans", 0) for d in diags.values())
        share = f"{100 * off / total:.0f} %" if total else "-"
        lines.append(f"| {label} | {len(bad)} of {len(diags)} | {counts} | {err} | {path} | {still} | "
                     f"{' | '.join(ratio)} | {share} |")
    return "\n".join(lines) + "\n"


def _median_of(diags: dict[str, dict], key: str) -> str:
    values = [d[key] for d in diags.values() if d.get(key) is not None]
    return median_cell(values, 2) if values else "-"


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
