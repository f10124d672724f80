"""Closed-loop evaluation on the seed's Table 2 benchmark Push-T: trained policies act in gym-pusht from seeded
initial conditions.

    python -m adlpipe.benchmark --models models/fm_cnn models/dp_cnn --steps 2 16 --episodes 50

Each model (trained with `train --closed-loop --target action` on Push-T bags) runs from initial conditions
seed0, seed0+1, ... (none of them a training demonstration's: record uses 0..N-1, the default seed0 is 100,000),
predicting Tp actions from To frames and agent positions, executing Ta, re-planning, for at most 300 steps. Per
model, checkpoint (best validation / last) and step count: the mean of each episode's highest coverage of the goal
(the seed's score), the success rate (coverage above 0.95), milliseconds per plan; beside them, from the same
initial conditions, the scripted demonstrator and the agent holding still (the coverage an episode starts with).
Writes --metrics (headline), --details (per episode) and --table (the Table 2 replica).
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from .atomic import check_outputs, json_text, write_all_atomic
from .cli import NON_NEGATIVE, POSITIVE, Parser, int_range
from .dataset.loader import Normalizer, normalize_state, observation_from_arrays
from .errors import AdlError, run_cli
from .policy.checkpoint import CHECKPOINTS, load_policy
from .policy.inference import predict
from .runtime import Placement

FIRST_SEED = 100_000
REFERENCES = ("demonstrator", "no action")


@lru_cache(maxsize=8)
def _policy(path: str) -> tuple:
    """A worker process's policy, loaded once for all the episodes it runs."""
    return load_policy(Path(path), Placement())


def _episode(job: tuple) -> tuple[str, str, int, int, float, bool, float]:
    from .sim.pusht import run_policy

    model_dir, checkpoint, steps, seed, execute = job
    torch.set_num_threads(1)
    placement = Placement()
    policy, ck = _policy(str(Path(model_dir) / CHECKPOINTS[checkpoint]))
    cfg, norm, gen = policy.cfg, Normalizer(ck["stats"]), placement.generator(seed)
    blank = np.zeros((cfg.image_size, cfg.image_size), np.float32)
    seconds: list[float] = []

    def plan(pixels: list[np.ndarray], agent: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        image = np.concatenate([observation_from_arrays(p, blank, None, cfg.image_size, False) for p in pixels])
        obs = (torch.from_numpy(image)[None], normalize_state(agent, ck["stats"])[None])
        out = norm.unnormalize(predict(policy, obs, steps, None, gen, placement))[0].numpy()
        seconds.append(time.perf_counter() - t0)
        return out

    coverage, ok, _plans = run_policy(plan, seed, execute, cfg.n_obs)
    return str(model_dir), checkpoint, steps, seed, coverage, ok, 1000.0 * float(np.median(seconds))


def _reference(job: tuple) -> tuple[str, int, float, bool]:
    """The demonstrator, and the agent holding still (the coverage an episode starts with), from one initial
    condition: the scale a policy's score sits on."""
    from .sim.pusht import demonstrate, make_env

    kind, seed = job
    env = make_env()
    try:
        if kind == "demonstrator":
            steps = list(demonstrate(env, seed))
            return kind, seed, max(s.info["coverage"] for s in steps), bool(steps[-1].info["is_success"])
        env.reset(seed=seed)
        u = env.unwrapped
        _obs, _r, done, _t, info = env.step(np.asarray(u.agent.position, np.float32))
        return kind, seed, float(info["coverage"]), bool(done)
    finally:
        env.close()


def summary(episodes: list[dict]) -> dict:
    """The score (mean highest coverage) and success rate of a set of episodes."""
    return {"score": float(np.mean([e["coverage"] for e in episodes])),
            "success": float(np.mean([e["success"] for e in episodes]))}


def check_model(d: Path) -> dict:
    for name in CHECKPOINTS.values():
        if not (d / name).exists():
            raise AdlError(f"{d}: no {name}; train it first (python -m adlpipe.train --closed-loop --target action)")
    _policy, ck = load_policy(d / CHECKPOINTS["last"])
    cfg = ck["config"]
    if cfg.get("target") != "action" or cfg.get("action_dim") != 2:
        raise AdlError(f"{d}: not a Push-T policy (train it with --closed-loop --target action on Push-T bags)")
    return cfg


def table(rows: dict, refs: dict, episodes: int, execute: int, first_seed: int) -> str:
    lines = ["# Push-T, closed loop (the seed's Table 2 setting)", "",
             f"{episodes} seeded initial conditions (seeds {first_seed}..), Ta = {execute}, at most 300 steps. "
             "Score: the mean over episodes of the highest goal coverage reached; success: coverage above 0.95. "
             "best: the checkpoint with the lowest validation error; last: the final one (the seed reports the max "
             "and the average of its last checkpoints).", "",
             "| model | steps | score best / last | success best / last | ms per plan |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for name, r in refs.items():
        lines.append(f"| {name} (reference) | | {r['score']:.3f} | {r['success']:.0%} | |")
    for (model, steps), r in rows.items():
        lines.append(f"| {model} | {steps} | {r['best']['score']:.3f} / {r['last']['score']:.3f} | "
                     f"{r['best']['success']:.0%} / {r['last']['success']:.0%} | {r['last']['ms']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.benchmark", __doc__)
    p.add_argument("--models", nargs="+", type=Path, required=True)
    p.add_argument("--steps", nargs="+", type=int_range(1, 100), default=[2, 16],
                   help="sampling steps of the generative models (BC: its one prediction)")
    p.add_argument("--episodes", type=POSITIVE, default=50, help="initial conditions (the seed: 500)")
    p.add_argument("--seed", type=NON_NEGATIVE, default=FIRST_SEED, help="the first initial condition")
    p.add_argument("--execute", type=int_range(1, 256), default=8, help="Ta: actions executed per plan")
    p.add_argument("--workers", type=int_range(1, 256), default=2)
    p.add_argument("--metrics", type=Path, default=Path("metrics/pusht.json"))
    p.add_argument("--details", type=Path, default=Path("metrics/pusht_details.json"))
    p.add_argument("--table", type=Path, default=Path("reports/pusht.md"))
    args = p.parse_args(argv)
    check_outputs(args.metrics, args.details, args.table)
    from .sim.pusht import make_env

    make_env().close()  # the optional extra's absence: one line
    jobs = []
    for d in args.models:
        cfg = check_model(d)
        for steps in ([1] if cfg["model"].startswith("bc_") else args.steps):
            jobs += [(str(d), ck, steps, args.seed + i, args.execute) for ck in CHECKPOINTS
                     for i in range(args.episodes)]
    per: dict = {}
    ref_eps: dict = {}
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for model_dir, ck, steps, seed, coverage, ok, ms in pool.map(_episode, jobs):
            per.setdefault((Path(model_dir).name, steps), {}).setdefault(ck, []).append(
                {"seed": seed, "coverage": coverage, "success": ok, "ms": ms})
        ref_jobs = [(kind, args.seed + i) for kind in REFERENCES for i in range(args.episodes)]
        for kind, seed, coverage, ok in pool.map(_reference, ref_jobs):
            ref_eps.setdefault(kind, []).append({"seed": seed, "coverage": coverage, "success": ok})
    refs = {k: summary(eps) for k, eps in ref_eps.items()}
    rows = {key: {ck: {**summary(eps), "ms": float(np.median([e["ms"] for e in eps]))} for ck, eps in by_ck.items()}
            for key, by_ck in per.items()}
    headline = {f"{m}/{s}": {"score_best": round(r["best"]["score"], 3), "score_last": round(r["last"]["score"], 3),
                             "success_last": round(r["last"]["success"], 3)} for (m, s), r in rows.items()}
    write_all_atomic({
        args.metrics: json_text(headline),
        args.details: json_text({"episodes": args.episodes, "first_seed": args.seed, "execute": args.execute,
                                 "results": [{"model": m, "steps": s, **r, "per_episode": per[(m, s)]}
                                             for (m, s), r in rows.items()],
                                 "references": {k: {**refs[k], "per_episode": ref_eps[k]} for k in refs}}),
        args.table: table(rows, refs, args.episodes, args.execute, args.seed)})
    for (m, s), r in rows.items():
        print(f"{m} {s} steps: score {r['best']['score']:.3f} / {r['last']['score']:.3f} (best / last)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.benchmark", main))
