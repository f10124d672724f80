"""Closed-loop evaluation on the seed's Table 2 benchmarks, Push-T and Franka Kitchen: trained policies act in the
environment from seeded initial conditions.

    python -m adlpipe.benchmark --models models/fm_cnn models/dp_cnn --steps 2 16 --episodes 50
    python -m adlpipe.benchmark --env kitchen --models models/fm_cnn models/dp_cnn --steps 2 16 --episodes 50

Each model (trained with `train --closed-loop --target action` on the environment's bags; Franka Kitchen's with
--no-image, on the state alone) runs from initial conditions seed0, seed0+1, ... (none of them a training
demonstration's: record uses 0..N-1, the default seed0 is 100,000), predicting Tp actions from To observations,
executing Ta, re-planning, until the environment's step limit (Push-T 300, Franka Kitchen 280). Per model,
checkpoint (best validation / last) and step count: the mean score, the success rate and milliseconds per plan;
beside them, from the same initial conditions, the references (the scripted demonstrator; on Push-T also the agent
holding still, the coverage an episode starts with).
  Push-T: score = each episode's highest coverage of the goal (the seed's), success = coverage above 0.95.
  Franka Kitchen: score = the share of the four tasks (microwave, kettle, light switch, slide cabinet) done,
  success = all four; the table also gives each task's success rate.
Diffusion Policy samples with --dp-sampler (default DDPM on leading timesteps, as Diffusion Policy does; a
non-default sampler is named in the model's row).
Writes --metrics (headline), --details (per episode) and --table (the Table 2 replica).
"""

from __future__ import annotations

import importlib
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

from .atomic import check_outputs, json_text, write_all_atomic
from .cli import NON_NEGATIVE, POSITIVE, Parser, int_range
from .dataset.loader import Normalizer, normalize_state, observation_from_arrays
from .errors import AdlError, run_cli
from .policy.checkpoint import CHECKPOINTS, load_policy
from .policy.models import MODELS
from .policy.objectives import DDPM
from .runtime import Placement
from .sim.kitchen import TASKS as KITCHEN_TASKS

FIRST_SEED = 100_000


@dataclass(frozen=True)
class Benchmark:
    module: str  # adlpipe.sim.<module>: make_env, run_policy, reference, REFERENCES
    title: str
    action_dim: int
    images: bool  # the seed's policies see images (Push-T) or the state alone (Franka Kitchen)
    protocol: str  # what the table's score and success mean
    tasks: tuple[str, ...] = ()  # subtasks whose success rates the table gives (Franka Kitchen's four)

    def sim(self) -> ModuleType:
        return importlib.import_module(f"adlpipe.sim.{self.module}")


BENCHMARKS = {
    "pusht": Benchmark("pusht", "Push-T", 2, True,
                       "at most 300 steps. Score: the mean over episodes of the highest goal coverage reached; "
                       "success: coverage above 0.95."),
    "kitchen": Benchmark("kitchen", "Franka Kitchen", 9, False,
                         "at most 280 steps. Score: the mean share of the four tasks done (microwave, kettle, light "
                         "switch, slide cabinet); success: all four.", KITCHEN_TASKS),
}


@lru_cache(maxsize=8)
def _policy(path: str) -> tuple:
    """A worker process's policy, loaded once for all the episodes it runs."""
    return load_policy(Path(path), Placement())


def _episode(job: tuple) -> tuple[str, str, int, dict]:
    from .policy.inference import predict

    env, model_dir, checkpoint, steps, method, seed, execute = job
    torch.set_num_threads(1)
    placement = Placement()
    policy, ck = _policy(str(Path(model_dir) / CHECKPOINTS[checkpoint]))
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

    outcome = BENCHMARKS[env].sim().run_policy(plan, seed, execute, cfg.n_obs)
    outcome.pop("plans")
    label = Path(model_dir).name + (f" ({method})" if method not in (None, "ddpm") else "")
    return label, checkpoint, steps, {"seed": seed, **outcome, "ms": 1000.0 * float(np.median(seconds))}


def _reference(job: tuple) -> tuple[str, dict]:
    env, kind, seed = job
    return kind, {"seed": seed, **BENCHMARKS[env].sim().reference(kind, seed)}


def summary(episodes: list[dict], tasks: tuple[str, ...] = ()) -> dict:
    """The mean score and success rate of a set of episodes, and each of `tasks`' success rate."""
    out = {"score": float(np.mean([e["score"] for e in episodes])),
           "success": float(np.mean([e["success"] for e in episodes]))}
    if tasks:
        out["tasks"] = {t: float(np.mean([t in e["tasks"] for e in episodes])) for t in tasks}
    return out


def check_model(d: Path, bench: Benchmark) -> dict:
    for name in CHECKPOINTS.values():
        if not (d / name).exists():
            raise AdlError(f"{d}: no {name}; train it first (python -m adlpipe.train --closed-loop --target action)")
    _policy, ck = load_policy(d / CHECKPOINTS["last"])
    cfg = ck["config"]
    if (cfg.get("target") != "action" or cfg.get("action_dim") != bench.action_dim
            or cfg.get("use_image", True) != bench.images):
        how = "" if bench.images else " --no-image"
        raise AdlError(f"{d}: not a {bench.title} policy (train it with --closed-loop --target action{how} on "
                       f"{bench.title} bags)")
    return cfg


def _tasks_cell(r: dict) -> str:
    return " / ".join(f"{v:.0%}" for v in r["tasks"].values())


def table(bench: Benchmark, rows: dict, refs: dict, episodes: int, execute: int, first_seed: int) -> str:
    per_task = bool(bench.tasks)
    head = "| model | steps | score best / last | success best / last | ms per plan |"
    if per_task:
        head += f" last: {' / '.join(bench.tasks)} |"
    lines = [f"# {bench.title}, closed loop (the seed's Table 2 setting)", "",
             f"{episodes} seeded initial conditions (seeds {first_seed}..), Ta = {execute}, {bench.protocol} "
             "best: the checkpoint with the lowest validation error; last: the final one (the seed reports the max "
             "and the average of its last checkpoints).", "",
             head, "| --- | ---: | ---: | ---: | ---: |" + (" ---: |" if per_task else "")]
    for name, r in refs.items():
        lines.append(f"| {name} (reference) | | {r['score']:.3f} | {r['success']:.0%} | |"
                     + (f" {_tasks_cell(r)} |" if per_task else ""))
    for (model, steps), r in rows.items():
        lines.append(f"| {model} | {steps} | {r['best']['score']:.3f} / {r['last']['score']:.3f} | "
                     f"{r['best']['success']:.0%} / {r['last']['success']:.0%} | {r['last']['ms']:.1f} |"
                     + (f" {_tasks_cell(r['last'])} |" if per_task else ""))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.benchmark", __doc__)
    p.add_argument("--env", choices=sorted(BENCHMARKS), default="pusht")
    p.add_argument("--models", nargs="+", type=Path, required=True)
    p.add_argument("--steps", nargs="+", type=int_range(1, 100), default=[2, 16],
                   help="sampling steps of the generative models (BC: its one prediction)")
    p.add_argument("--dp-sampler", choices=DDPM.methods, default="ddpm",
                   help="Diffusion Policy's sampler (default ddpm, leading timesteps as Diffusion Policy; "
                   "ddim_trailing: deterministic, starting from the last timestep, the fair few-step choice)")
    p.add_argument("--episodes", type=POSITIVE, default=50, help="initial conditions (the seed: 500)")
    p.add_argument("--seed", type=NON_NEGATIVE, default=FIRST_SEED, help="the first initial condition")
    p.add_argument("--execute", type=int_range(1, 256), default=8, help="Ta: actions executed per plan")
    p.add_argument("--workers", type=int_range(1, 256), default=2)
    p.add_argument("--metrics", type=Path, help="default: metrics/<env>.json")
    p.add_argument("--details", type=Path, help="default: metrics/<env>_details.json")
    p.add_argument("--table", type=Path, help="default: reports/<env>.md")
    args = p.parse_args(argv)
    bench = BENCHMARKS[args.env]
    metrics = args.metrics or Path(f"metrics/{args.env}.json")
    details = args.details or Path(f"metrics/{args.env}_details.json")
    table_path = args.table or Path(f"reports/{args.env}.md")
    check_outputs(metrics, details, table_path)
    bench.sim().make_env().close()  # the optional extra's absence: one line
    jobs = []
    for d in args.models:
        cfg = check_model(d, bench)
        method = args.dp_sampler if MODELS[cfg["model"]][0].startswith("ddpm") else None
        for steps in ([1] if cfg["model"].startswith("bc_") else args.steps):
            jobs += [(args.env, str(d), ck, steps, method, args.seed + i, args.execute) for ck in CHECKPOINTS
                     for i in range(args.episodes)]
    per: dict = {}
    ref_eps: dict = {}
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for label, ck, steps, episode in pool.map(_episode, jobs):
            per.setdefault((label, steps), {}).setdefault(ck, []).append(episode)
        ref_jobs = [(args.env, kind, args.seed + i) for kind in bench.sim().REFERENCES for i in range(args.episodes)]
        for kind, episode in pool.map(_reference, ref_jobs):
            ref_eps.setdefault(kind, []).append(episode)
    refs = {k: summary(eps, bench.tasks) for k, eps in ref_eps.items()}
    rows = {key: {ck: {**summary(eps, bench.tasks), "ms": float(np.median([e["ms"] for e in eps]))}
                  for ck, eps in by_ck.items()} for key, by_ck in per.items()}
    headline = {f"{m}/{s}": {"score_best": round(r["best"]["score"], 3), "score_last": round(r["last"]["score"], 3),
                             "success_last": round(r["last"]["success"], 3)} for (m, s), r in rows.items()}
    write_all_atomic({
        metrics: json_text(headline),
        details: json_text({"env": args.env, "episodes": args.episodes, "first_seed": args.seed,
                            "execute": args.execute,
                            "results": [{"model": m, "steps": s, **r, "per_episode": per[(m, s)]}
                                        for (m, s), r in rows.items()],
                            "references": {k: {**refs[k], "per_episode": ref_eps[k]} for k in refs}}),
        table_path: table(bench, rows, refs, args.episodes, args.execute, args.seed)})
    for (m, s), r in rows.items():
        print(f"{m} {s} steps: score {r['best']['score']:.3f} / {r['last']['score']:.3f} (best / last)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.benchmark", main))
