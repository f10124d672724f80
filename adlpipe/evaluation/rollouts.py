"""Labelled rollouts (DAgger, HG-DAgger): a closed-loop policy rolled out on the training split's scenes, each
rollout a bag with the expert's plans and the scene's demonstrated path (and, with an operator, the intervention
flag), for ingest -> train --target recovery like any lab's bags (adlpipe.sim.dagger; docs/science/dagger.md).
Never the test split's scenes: the rollouts join the training data."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..dataset import schema
from ..dataset.splits import load_split
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Placement
from ..plumbing.workers import stoppable_pool
from .replay import LoopOptions, camera_rate, closed_loop_one, closed_loop_scenes


@dataclass(frozen=True)
class RolloutConfig:
    """What `adlpipe rollout` runs: one model on the training split's scenes."""

    model: Path  # a closed-loop model folder
    data: Path
    split: Path
    out: Path  # the bags' folder
    checkpoint: str = "best.pt"
    execute: int = 8  # Ta
    rate_hz: float = 10.0  # the model's waypoint rate (Ta / rate: the seconds a re-plan covers)
    steps: int = 1  # sampler steps (FM-1, DP-16: the decision's)
    seed: int = 0  # the samplers' noise (a round's own)
    operator: object | None = None  # adlpipe.sim.dagger.OperatorRule: HG-DAgger; None: DAgger (the expert labels)
    time_limit: float = 1.0  # times the demonstration's duration
    workers: int = 2
    limit: int | None = None  # at most this many scenes, spread over the tasks


def run_rollouts(cfg: RolloutConfig) -> dict:
    """Roll the model out on every training scene and write each rollout's bag; returns the summary."""
    split = load_split(cfg.split)
    names = list(split["train"])
    if not names:
        raise AdlError(f"{cfg.split}: no train episodes to roll out on")
    with schema.open_dataset(cfg.data, names) as f:
        names = spread(names, {n: str(f[schema.EPISODES][n].attrs["task"]) for n in names}, cfg.limit)
        eps = [schema.read_episode(f, n) for n in names]
        rates = [camera_rate(f, n) for n in names]
    scenes = closed_loop_scenes(cfg.data, eps, rates)
    missing = [s.name for s in scenes if s.command is None]
    if missing:
        raise AdlError(f"{cfg.data}: episode {missing[0]} has no command stream (frames/action): the expert labels "
                       "from the demonstrated command path; ingest with the topic map's action topic")
    label = cfg.model.name
    jobs = [(label, str(cfg.model), cfg.checkpoint, sc, cfg.steps, cfg.execute, cfg.seed, Placement(), None,
             cfg.time_limit, None, LoopOptions(trial_dir=str(cfg.out), trial_index=i, labelled=True,
                                               operator=cfg.operator))
            for i, sc in enumerate(scenes)]
    cfg.out.mkdir(parents=True, exist_ok=True)
    rows = []
    with stoppable_pool(cfg.workers) as pool:
        for _label, name, task, ok, diag in tqdm(pool.imap(closed_loop_one, jobs), total=len(jobs),
                                                 desc=f"rollout {label}", unit="rollout", file=sys.stderr,
                                                 disable=None):
            rows.append({"scene": name, "task": task, "success": bool(ok), "plans": diag["plans"],
                         "operator_plans": diag.get("operator_plans", 0),
                         "replans_off_path": diag.get("replans_off_path")})
    return summary(cfg, rows)


def spread(names: list[str], tasks: dict[str, str], limit: int | None) -> list[str]:
    """At most `limit` of the names, every task's in turn (its first, then its second, ...), in the split's order."""
    if limit is None or limit >= len(names):
        return names
    by_task: dict[str, list[str]] = {}
    for n in names:
        by_task.setdefault(tasks[n], []).append(n)
    turns = sorted((i, t) for t, ns in by_task.items() for i in range(len(ns)))
    keep = {by_task[t][i] for i, t in turns[:limit]}
    return [n for n in names if n in keep]


def summary(cfg: RolloutConfig, rows: list[dict]) -> dict:
    """Per rollout and in all: success, re-plans, the operator's share of them and its seconds at the wheel."""
    plans = sum(r["plans"] for r in rows)
    taken = sum(r["operator_plans"] for r in rows)
    return {"model": str(cfg.model), "checkpoint": cfg.checkpoint, "execute": cfg.execute, "steps": cfg.steps,
            "seed": cfg.seed, "operator": None if cfg.operator is None else vars(cfg.operator),
            "rollouts": len(rows), "success": float(np.mean([r["success"] for r in rows])),
            "plans": plans, "operator_plans": taken,
            "operator_s": round(taken * cfg.execute / cfg.rate_hz, 1),
            "labelled_plans": taken if cfg.operator is not None else plans, "per_rollout": rows}


def write_summary(path: Path, s: dict) -> None:
    from ..plumbing.atomic import write_text_atomic

    write_text_atomic(path, json.dumps(s, indent=1) + "\n")
