"""Closed-loop episodes of trained policies in a benchmark environment: which episodes to run (every model, step count
and checkpoint, and the checkpoints along training), running them in worker processes, and their summaries (the mean
score with its bootstrap interval, success with Wilson's; the seed's best and last-three figures along training)."""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from ..dataset.loader import Normalizer, normalize_state, observation_from_arrays
from ..envs.registry import BENCHMARKS, Benchmark
from ..plumbing.atomic import json_text, write_all_atomic
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Placement
from ..policy.checkpoint import CHECKPOINTS, load_policy
from ..policy.models import MODELS
from .benchmark_tables import plot_curves, table
from .stats import mean_interval, success_interval

FIRST_SEED = 100_000


@dataclass(frozen=True)
class BenchmarkConfig:
    """What `adlpipe benchmark` was asked (its options, one field each: `adlpipe benchmark --help` says what each
    does); the output paths as the stage defaults them from the environment's name."""

    env: str
    models: list[Path]
    metrics: Path
    details: Path
    table: Path
    curve_plot: Path | None = None  # with curve
    steps: list[int] = field(default_factory=lambda: [2, 16])  # sampling steps of the generative models
    dp_sampler: str = "ddpm"
    clip_sample: str = "own"  # own (DDPM's clips, FM's does not), on, off: every generative model alike
    noise_scale: float = 1.0  # the samplers' starting (and DDPM's ancestral) noise scale, every model alike
    max_steps: int | None = None  # None: the environment's limit
    checkpoints: list[str] = field(default_factory=lambda: ["best", "last"])
    episodes: int = 50
    seed: int = FIRST_SEED
    execute: int = 8
    workers: int = 2
    curve: bool = False
    curve_steps: int = 16
    curve_episodes: int | None = None
    reference_episodes: int | None = None


CLIP_CHOICES = ("own", "on", "off")


@lru_cache(maxsize=8)
def _policy(path: str) -> tuple:
    """A worker process's policy, loaded once for all the episodes it runs."""
    return load_policy(Path(path), Placement())


def _episode(job: tuple) -> tuple[str, str | int, int, dict]:
    from ..policy.inference import predict

    env, name, checkpoint, path, steps, method, seed, execute, max_steps, clip, noise_scale = job
    torch.set_num_threads(1)
    placement = Placement()
    policy, ck = _policy(path)
    if clip != "own" and hasattr(policy.objective, "clip"):
        policy.objective.clip = clip == "on"
    if hasattr(policy.objective, "noise_scale"):
        policy.objective.noise_scale = noise_scale
    cfg, norm, gen = policy.cfg, Normalizer(ck["stats"]), placement.generator(seed)
    blank = np.zeros((cfg.image_size, cfg.image_size), np.float32)
    seconds: list[float] = []

    def plan(pixels: list[np.ndarray] | None, state: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        if cfg.use_image:
            image = torch.from_numpy(np.concatenate([observation_from_arrays(p, blank, None, cfg.image_size, False)
                                                     for p in pixels]))[None]
        else:
            image = torch.zeros(1, 0)
        obs = (image, normalize_state(state, ck["stats"])[None])
        out = norm.unnormalize(predict(policy, obs, steps, method, gen, placement))[0].numpy()
        seconds.append(time.perf_counter() - t0)
        return out

    outcome = BENCHMARKS[env].env().run_policy(plan, seed, execute, cfg.n_obs, max_steps=max_steps,
                                               state_only=not cfg.use_image)
    label = name + (f" ({method})" if method not in (None, "ddpm") else "")
    label += {"on": " (clipped)", "off": " (unclipped)"}.get(clip, "") if hasattr(policy.objective, "clip") else ""
    label += f" (noise {noise_scale:g})" if noise_scale != 1.0 and hasattr(policy.objective, "noise_scale") else ""
    return label, checkpoint, steps, {"seed": seed, **outcome, "ms": 1000.0 * float(np.median(seconds))}


def _reference(job: tuple) -> tuple[str, dict]:
    env, kind, seed = job
    return kind, {"seed": seed, **BENCHMARKS[env].env().reference(kind, seed)}


def summary(episodes: list[dict], tasks: tuple[str, ...] = ()) -> dict:
    """The mean score (with its bootstrap interval) and success rate (with Wilson's) of a set of episodes, their
    number, and each of `tasks`' success rate."""
    scores, wins = [e["score"] for e in episodes], sum(bool(e["success"]) for e in episodes)
    out = {"score": float(np.mean(scores)), "score_ci": list(mean_interval(scores)),
           "success": wins / len(episodes), "success_ci": list(success_interval(wins, len(episodes))),
           "n": len(episodes)}
    if tasks:
        out["tasks"] = {t: float(np.mean([t in e["tasks"] for e in episodes])) for t in tasks}
    return out


def curve_summary(points: list[tuple[int, list[dict]]], last: int = 3) -> dict:
    """The seed's two figures from the checkpoints along training ((step, episodes on the same initial conditions)
    in order): the best checkpoint's, and the mean over the last `last` (per initial condition, then over them)."""
    rows = [{"step": step, **summary(eps)} for step, eps in points]
    top = max(rows, key=lambda r: r["score"])
    tail = [eps for _, eps in points[-last:]]
    per_ic = [{"score": float(np.mean([eps[i]["score"] for eps in tail])),
               "success": float(np.mean([eps[i]["success"] for eps in tail]))} for i in range(len(tail[0]))]
    scores = [e["score"] for e in per_ic]
    wins = sum(bool(eps[i]["success"]) for eps in tail for i in range(len(eps)))
    n = sum(len(eps) for eps in tail)
    tail_row = {"score": float(np.mean(scores)), "score_ci": list(mean_interval(scores)), "success": wins / n,
                "success_ci": list(success_interval(wins, n)), "n": len(per_ic), "checkpoints": len(tail)}
    return {"points": rows, "max": top, "last": tail_row}


def model_labels(dirs: list[Path]) -> list[str]:
    """Each model's row label: its folder's name, or with its parent folder where two folders share a name (the
    same model trained with two encoders: models/fm_cnn, models/refenc/fm_cnn)."""
    names = [d.name for d in dirs]
    return [n if names.count(n) == 1 else "/".join(d.resolve().parts[-2:]) for n, d in zip(names, dirs, strict=True)]


def check_model(d: Path, bench: Benchmark) -> dict:
    for name in CHECKPOINTS.values():
        if not (d / name).exists():
            raise AdlError(f"{d}: no {name}; train it first (python -m adlpipe.train --closed-loop --target action)")
    _policy, ck = load_policy(d / CHECKPOINTS["last"])
    cfg = ck["config"]
    if len(cfg.get("cameras", ())) > 1:
        raise AdlError(f"{d}: sees cameras {', '.join(cfg['cameras'])}; {bench.title} renders one camera")
    if (cfg.get("target") != "action" or cfg.get("action_dim") != bench.action_dim
            or (cfg.get("use_image", True) and not bench.images)):
        how = "" if bench.images else " --no-image"
        raise AdlError(f"{d}: not a {bench.title} policy (train it with --closed-loop --target action{how} on "
                       f"{bench.title} bags)")
    return cfg


def curve_checkpoints(d: Path) -> list[tuple[int, Path]]:
    """(optimiser step, path) of the checkpoints train --save-every kept along training, in order."""
    found = sorted((int(p.stem[len("step_"):]), p) for p in (d / "checkpoints").glob("step_*.pt")
                   if p.stem[len("step_"):].isdigit())
    if not found:
        raise AdlError(f"{d}: no checkpoints along training in {d / 'checkpoints'}; train it with --save-every N "
                       "for --curve")
    return found


def episode_jobs(c: BenchmarkConfig, bench: Benchmark) -> tuple[list[tuple], list[tuple]]:
    """(every model's episodes at each step count and checkpoint, those of its checkpoints along training)."""
    jobs, curve_jobs = [], []
    for d, name in zip(c.models, model_labels(c.models), strict=True):
        cfg = check_model(d, bench)
        method = c.dp_sampler if MODELS[cfg["model"]][0].startswith("ddpm") else None
        bc = cfg["model"].startswith("bc_")
        for steps in ([1] if bc else c.steps):
            jobs += [(c.env, name, ck, str(d / CHECKPOINTS[ck]), steps, method, c.seed + i, c.execute,
                      c.max_steps, c.clip_sample, c.noise_scale) for ck in c.checkpoints for i in range(c.episodes)]
        if c.curve:
            steps = 1 if bc else c.curve_steps
            curve_jobs += [(c.env, name, n, str(path), steps, method, c.seed + i, c.execute,
                            c.max_steps, c.clip_sample, c.noise_scale)
                           for n, path in curve_checkpoints(d)
                           for i in range(c.curve_episodes or c.episodes)]  # checkpoint: its step
    return jobs, curve_jobs


def run_episodes(c: BenchmarkConfig, bench: Benchmark, jobs: list[tuple],
                 curve_jobs: list[tuple]) -> tuple[dict, dict, dict]:
    """(per (model, steps, checkpoint): episodes, per (model, steps): step -> episodes, per reference: episodes)."""
    per: dict = {}
    along: dict = {}
    ref_eps: dict = {}
    with ProcessPoolExecutor(max_workers=c.workers) as pool:
        for label, ck, steps, episode in pool.map(_episode, jobs):
            per.setdefault((label, steps, ck), []).append(episode)
        for label, step, steps, episode in pool.map(_episode, curve_jobs):
            along.setdefault((label, steps), {}).setdefault(step, []).append(episode)
        ref_jobs = [(c.env, kind, c.seed + i) for kind in bench.env().REFERENCES
                    for i in range(min(c.reference_episodes or c.episodes, c.episodes))]
        for kind, episode in pool.map(_reference, ref_jobs):
            ref_eps.setdefault(kind, []).append(episode)
    return per, along, ref_eps


def run_benchmark(c: BenchmarkConfig) -> tuple[dict, dict]:
    """Run every model of `c` (and the environment's references) and write the metrics, details, table and
    curve plot: the rows (model, steps, checkpoint) -> summary and the curves (model, steps) -> summary."""
    bench = BENCHMARKS[c.env]
    max_steps = c.max_steps or bench.max_steps  # the environment's limit unless --max-steps
    c = replace(c, max_steps=max_steps)
    bench.env().make_env().close()  # the optional extra's absence: one line
    per, along, ref_eps = run_episodes(c, bench, *episode_jobs(c, bench))
    refs = {k: summary(eps, bench.tasks) for k, eps in ref_eps.items()}
    rows = {key: {**summary(eps, bench.tasks), "ms": float(np.median([e["ms"] for e in eps]))}
            for key, eps in per.items()}
    curves = {key: curve_summary(sorted(by_step.items())) for key, by_step in along.items()}
    headline = {f"{m}/{s}/{ck}": {"score": round(r["score"], 3), "success": round(r["success"], 3)}
                for (m, s, ck), r in rows.items()}
    headline.update({f"{m}/{s}/curve": {"score_max": round(cv["max"]["score"], 3),
                                        "score_last3": round(cv["last"]["score"], 3)}
                     for (m, s), cv in curves.items()})
    write_all_atomic({
        c.metrics: json_text(headline),
        c.details: json_text({"env": c.env, "episodes": c.episodes, "first_seed": c.seed,
                              "execute": c.execute, "max_steps": max_steps,
                              "results": [{"model": m, "steps": s, "checkpoint": ck, **r,
                                           "per_episode": per[(m, s, ck)]} for (m, s, ck), r in rows.items()],
                              "curves": [{"model": m, "steps": s, "episodes": c.curve_episodes or c.episodes, **cv}
                                         for (m, s), cv in curves.items()],
                              "references": {k: {**refs[k], "per_episode": ref_eps[k]} for k in refs}}),
        c.table: table(bench, rows, refs, c.episodes, c.execute, c.seed, max_steps, curves)})
    if c.curve_plot:
        plot_curves(curves, refs, c.curve_plot, bench.title)
    return rows, curves
