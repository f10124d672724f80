"""Closed-loop evaluation on the seed's Table 2 benchmarks, Push-T and Franka Kitchen: trained policies act in the
environment from seeded initial conditions.

    python -m adlpipe.benchmark --models models/fm_cnn models/dp_cnn --steps 2 16 --episodes 50
    python -m adlpipe.benchmark --env kitchen --models models/fm_cnn models/dp_cnn --steps 2 16 --episodes 50

Each model (trained with `train --closed-loop --target action` on the environment's bags; Franka Kitchen's with
--no-image, on the state alone; on Push-T either: a --no-image policy sees the keypoint state, the T's 8 keypoints
and the agent, as in pipelines/pusht's state variant) runs from initial conditions seed0, seed0+1, ... (none of them
a training demonstration's: record uses 0..N-1, the default seed0 is 100,000), predicting Tp actions from To
observations, executing Ta, re-planning, until the environment's step limit (Push-T 300, Franka Kitchen 280). Per
model, checkpoint (--checkpoints: best validation, last) and step count: the mean score with its bootstrap interval,
the success rate with Wilson's, and milliseconds per plan; beside them, from the same initial conditions, the
references (the scripted demonstrator; on Push-T also the agent holding still, the coverage an episode starts with).
  Push-T: score = each episode's highest coverage of the goal (the seed's), success = coverage above 0.95.
  Franka Kitchen: score = the share of the four tasks (microwave, kettle, light switch, slide cabinet) done,
  success = all four; the table also gives each task's success rate.
--curve also runs every checkpoint train --save-every kept along training: the learning curves (a PNG) and the
seed's Table 2 columns, the best checkpoint's score and the mean over the last three.
Diffusion Policy samples with --dp-sampler (default DDPM on leading timesteps, as Diffusion Policy does; a
non-default sampler is named in the model's row).
Writes --metrics (headline), --details (per episode) and --table (the Table 2 replica).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

from .atomic import atomic_path, check_outputs, json_text, write_all_atomic
from .cli import SEED, Parser, int_range
from .dataset.loader import Normalizer, normalize_state, observation_from_arrays
from .errors import AdlError, run_cli
from .policy.checkpoint import CHECKPOINTS, load_policy
from .policy.models import MODELS
from .policy.objectives import DDPM
from .runtime import Placement
from .sim.kitchen import TASKS as KITCHEN_TASKS
from .stats import interval_cell, mean_interval, paired_difference, paired_success, success_interval

FIRST_SEED = 100_000


@dataclass(frozen=True)
class Benchmark:
    module: str  # adlpipe.sim.<module>: make_env, run_policy, reference, REFERENCES
    title: str
    action_dim: int
    images: bool  # image policies run here (Push-T); state-only policies run on every benchmark
    protocol: str  # what the table's score and success mean
    max_steps: int  # the environment's episode limit
    tasks: tuple[str, ...] = ()  # subtasks whose success rates the table gives (Franka Kitchen's four)

    def sim(self) -> ModuleType:
        return importlib.import_module(f"adlpipe.sim.{self.module}")


BENCHMARKS = {
    "pusht": Benchmark("pusht", "Push-T", 2, True,
                       "Score: the mean over episodes of the highest goal coverage reached; success: coverage above "
                       "0.95.", 300),
    "kitchen": Benchmark("kitchen", "Franka Kitchen", 9, False,
                         "Score: the mean share of the four tasks done (microwave, kettle, light switch, slide "
                         "cabinet); success: all four.", 280, KITCHEN_TASKS),
}


@lru_cache(maxsize=8)
def _policy(path: str) -> tuple:
    """A worker process's policy, loaded once for all the episodes it runs."""
    return load_policy(Path(path), Placement())


def _episode(job: tuple) -> tuple[str, str | int, int, dict]:
    from .policy.inference import predict

    env, name, checkpoint, path, steps, method, seed, execute, max_steps = job
    torch.set_num_threads(1)
    placement = Placement()
    policy, ck = _policy(path)
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

    outcome = BENCHMARKS[env].sim().run_policy(plan, seed, execute, cfg.n_obs, max_steps=max_steps,
                                               state_only=not cfg.use_image)
    label = name + (f" ({method})" if method not in (None, "ddpm") else "")
    return label, checkpoint, steps, {"seed": seed, **outcome, "ms": 1000.0 * float(np.median(seconds))}


def _reference(job: tuple) -> tuple[str, dict]:
    env, kind, seed = job
    return kind, {"seed": seed, **BENCHMARKS[env].sim().reference(kind, seed)}


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


def _tasks_cell(r: dict) -> str:
    return " / ".join(f"{v:.0%}" for v in r["tasks"].values())


def _score_cell(r: dict) -> str:
    return interval_cell(r["score"], r["score_ci"])


def _success_cell(r: dict) -> str:
    lo, hi = r["success_ci"]
    return f"{r['success']:.0%} [{100 * lo:.0f}, {100 * hi:.0f}]"


def table(bench: Benchmark, rows: dict, refs: dict, episodes: int, execute: int, first_seed: int, max_steps: int,
          curves: dict | None = None) -> str:
    """The Table 2 replica: references, then one row per model, sampling steps and checkpoint; with curves, the
    seed's two columns over the checkpoints along training."""
    per_task = bool(bench.tasks)
    limit = f"at most {max_steps} steps" + (
        f" (the environment's limit is {bench.max_steps}: policies given more time)." if max_steps != bench.max_steps
        else ".")
    head = "| model | steps | checkpoint | score [95 %] | success [95 %] | ms per plan |"
    if per_task:
        head += f" {' / '.join(bench.tasks)} |"
    lines = [f"# {bench.title}, closed loop (the seed's Table 2 setting)", "",
             f"{episodes} seeded initial conditions (seeds {first_seed}..), Ta = {execute}, {limit} {bench.protocol} "
             "Intervals: 95 %, a percentile bootstrap over the initial conditions for the score, Wilson's for the "
             "success rate. Checkpoint best: the lowest validation error; last: the final one.", "",
             head, "| --- | ---: | --- | ---: | ---: | ---: |" + (" ---: |" if per_task else "")]
    for name, r in refs.items():
        if r["n"] < episodes:  # --reference-episodes
            name += f", first {r['n']} initial conditions"
        lines.append(f"| {name} (reference) | | | {_score_cell(r)} | {_success_cell(r)} | |"
                     + (f" {_tasks_cell(r)} |" if per_task else ""))
    for (model, steps, ck), r in rows.items():
        lines.append(f"| {model} | {steps} | {ck} | {_score_cell(r)} | {_success_cell(r)} | {r['ms']:.1f} |"
                     + (f" {_tasks_cell(r)} |" if per_task else ""))
    if curves:
        lines += ["", "## Along training (the seed's protocol)", "",
                  "Every checkpoint kept along training (train --save-every), each on the same initial conditions. "
                  "max: the best checkpoint's score (the seed's 'max'; picking the best of several noisy figures "
                  "favours it: its interval is that checkpoint's alone); last 3: the mean over the last three "
                  "checkpoints (the seed's average of the last checkpoints), its interval a bootstrap of each "
                  "initial condition's mean over them.", "",
                  "| model | steps | checkpoints | episodes each | max score (at step) | max success | "
                  "last 3 score | last 3 success |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for (model, steps), c in curves.items():
            top, tail = c["max"], c["last"]
            lines.append(f"| {model} | {steps} | {len(c['points'])} | {top['n']} | {_score_cell(top)} "
                         f"({top['step']}) | {_success_cell(top)} | {_score_cell(tail)} | {_success_cell(tail)} |")
    return "\n".join(lines) + "\n"


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


def plot_curves(curves: dict, refs: dict, path: Path, title: str) -> None:
    """Score and success against optimiser steps, one line per model and step count, the references flat."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for (model, steps), c in curves.items():
        x = [p["step"] for p in c["points"]]
        for ax, key in zip(axes, ("score", "success"), strict=True):
            lo = [p[f"{key}_ci"][0] for p in c["points"]]
            hi = [p[f"{key}_ci"][1] for p in c["points"]]
            line, = ax.plot(x, [p[key] for p in c["points"]], marker="o", label=f"{model} ({steps} steps)")
            ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.15)
    for ax, key in zip(axes, ("score", "success"), strict=True):
        for (name, r), style in zip(refs.items(), (":", "--", "-."), strict=False):
            ax.axhline(r[key], color="grey", linestyle=style, label=f"{name} (reference)")
        ax.set_xlabel("optimiser steps")
        ax.set_ylabel({"score": "mean max coverage" if "Push" in title else "score", "success": "success rate"}[key])
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{title}: closed loop along training (95 % intervals shaded)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def detail_rows(details: dict, prefix: str = "") -> dict[str, dict[int, dict]]:
    """Row name -> {initial condition: its episode} of a details file's results."""
    return {prefix + f"{r['model']}-{r['steps']}" + (f" ({r['checkpoint']})" if r.get("checkpoint", "last") != "last"
                                                     else ""): {e["seed"]: e for e in r["per_episode"]}
            for r in details.get("results", [])}


def paired_lines(rows: dict[str, dict[int, dict]]) -> list[str]:
    """Every two rows (detail_rows: of one details file, or of several merged) compared on the initial conditions
    both ran: the paired bootstrap of the per-episode score difference and McNemar's exact test on success."""
    out = []
    names = list(rows)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            both = sorted(set(rows[a]) & set(rows[b]))
            if not both:
                continue
            # higher scores are better: the difference of negated scores is "a lower" = "a better"
            d = paired_difference([-rows[a][s]["score"] for s in both], [-rows[b][s]["score"] for s in both])
            ok = paired_success([rows[a][s]["success"] for s in both], [rows[b][s]["success"] for s in both])
            mean, low, high = (0.0 - v for v in (d.mean, d.high, d.low))  # 0.0 - 0.0 prints +0.000, not -0.000
            out.append(f"- {a} vs {b}: score {mean:+.3f} [{low:+.3f}, {high:+.3f}], {a} better: "
                       f"{d.verdict()}; success {ok}")
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = Parser("python -m adlpipe.benchmark", __doc__)
    p.add_argument("--env", choices=sorted(BENCHMARKS), default="pusht")
    p.add_argument("--models", nargs="+", type=Path)
    p.add_argument("--compare", type=Path, nargs="+", metavar="DETAILS",
                   help="run nothing: compare every two rows of a details file written before (or of several, "
                   "their rows named by file), paired on the initial conditions both ran (bootstrap of the score "
                   "difference, McNemar on success)")
    p.add_argument("--steps", nargs="+", type=int_range(1, 100), default=[2, 16],
                   help="sampling steps of the generative models (BC: its one prediction)")
    p.add_argument("--dp-sampler", choices=DDPM.methods, default="ddpm",
                   help="Diffusion Policy's sampler (default ddpm, leading timesteps as Diffusion Policy; "
                   "ddim_trailing: deterministic, starting from the last timestep, the fair few-step choice)")
    p.add_argument("--max-steps", type=int_range(1, 100_000),
                   help="end each policy episode after this many steps instead of the environment's limit (Push-T "
                   "300, Franka Kitchen 280): does more time let a policy finish? (the references keep the limit)")
    p.add_argument("--checkpoints", nargs="+", choices=sorted(CHECKPOINTS), default=["best", "last"],
                   help="which of each model's checkpoints to run (default: both)")
    p.add_argument("--episodes", type=int_range(1, 100_000), default=50, help="initial conditions (the seed: 500)")
    p.add_argument("--seed", type=SEED, default=FIRST_SEED, help="the first initial condition")
    p.add_argument("--execute", type=int_range(1, 256), default=8, help="Ta: actions executed per plan")
    p.add_argument("--workers", type=int_range(1, 256), default=2)
    p.add_argument("--curve", action="store_true",
                   help="also run every checkpoint kept along training (train --save-every) at --curve-steps on "
                   "--curve-episodes initial conditions: the learning curves, and the seed's max and last-3 columns")
    p.add_argument("--curve-steps", type=int_range(1, 100), default=16,
                   help="sampling steps along the curve (default 16; BC: its one prediction)")
    p.add_argument("--curve-episodes", type=int_range(1, 100_000),
                   help="initial conditions per checkpoint (default: --episodes)")
    p.add_argument("--reference-episodes", type=int_range(1, 100_000),
                   help="run the references on the first this many initial conditions only (default: --episodes; "
                   "Push-T's demonstrator plans each push for seconds)")
    p.add_argument("--metrics", type=Path, help="default: metrics/<env>.json")
    p.add_argument("--details", type=Path, help="default: metrics/<env>_details.json")
    p.add_argument("--table", type=Path, help="default: reports/<env>.md")
    p.add_argument("--curve-plot", type=Path, help="with --curve; default: reports/<env>_curves.png")
    args = p.parse_args(argv)
    if args.compare:
        return args
    if not args.models:
        p.error("--models is required (or --compare DETAILS)")
    if args.seed + max(args.episodes, args.curve_episodes or 0) - 1 > 2**32 - 1:
        p.error(f"--seed {args.seed} with {max(args.episodes, args.curve_episodes or 0)} initial conditions runs "
                "past the largest seed 2**32 - 1")
    if len(set(map(Path.resolve, args.models))) < len(args.models):
        raise AdlError("--models: a model is named twice")
    return args


def compare(paths: list[Path]) -> None:
    """Print the paired comparisons of the rows of details files written before."""
    rows = {}
    stems = [p.stem.removesuffix("_details") for p in paths]
    for path, stem in zip(paths, stems, strict=True):  # several files: each row named by its file
        prefix = "" if len(stems) == 1 else f"{stem}:" if stems.count(stem) == 1 else f"{path}:"
        try:
            rows.update(detail_rows(json.loads(path.read_text()), prefix))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise AdlError(f"{path}: not a benchmark details file ({type(exc).__name__}: {exc})") from exc
    print("\n".join(paired_lines(rows)))


def episode_jobs(args: argparse.Namespace, bench: Benchmark) -> tuple[list[tuple], list[tuple]]:
    """(every model's episodes at each step count and checkpoint, those of its checkpoints along training)."""
    jobs, curve_jobs = [], []
    for d, name in zip(args.models, model_labels(args.models), strict=True):
        cfg = check_model(d, bench)
        method = args.dp_sampler if MODELS[cfg["model"]][0].startswith("ddpm") else None
        bc = cfg["model"].startswith("bc_")
        for steps in ([1] if bc else args.steps):
            jobs += [(args.env, name, ck, str(d / CHECKPOINTS[ck]), steps, method, args.seed + i, args.execute,
                      args.max_steps) for ck in args.checkpoints for i in range(args.episodes)]
        if args.curve:
            steps = 1 if bc else args.curve_steps
            curve_jobs += [(args.env, name, n, str(path), steps, method, args.seed + i, args.execute,
                            args.max_steps)
                           for n, path in curve_checkpoints(d)
                           for i in range(args.curve_episodes or args.episodes)]  # checkpoint: its step
    return jobs, curve_jobs


def run_episodes(args: argparse.Namespace, bench: Benchmark, jobs: list[tuple],
                 curve_jobs: list[tuple]) -> tuple[dict, dict, dict]:
    """(per (model, steps, checkpoint): episodes, per (model, steps): step -> episodes, per reference: episodes)."""
    per: dict = {}
    along: dict = {}
    ref_eps: dict = {}
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for label, ck, steps, episode in pool.map(_episode, jobs):
            per.setdefault((label, steps, ck), []).append(episode)
        for label, step, steps, episode in pool.map(_episode, curve_jobs):
            along.setdefault((label, steps), {}).setdefault(step, []).append(episode)
        ref_jobs = [(args.env, kind, args.seed + i) for kind in bench.sim().REFERENCES
                    for i in range(min(args.reference_episodes or args.episodes, args.episodes))]
        for kind, episode in pool.map(_reference, ref_jobs):
            ref_eps.setdefault(kind, []).append(episode)
    return per, along, ref_eps


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.compare:
        compare(args.compare)
        return 0
    bench = BENCHMARKS[args.env]
    args.max_steps = args.max_steps or bench.max_steps  # the environment's limit unless --max-steps
    metrics = args.metrics or Path(f"metrics/{args.env}.json")
    details = args.details or Path(f"metrics/{args.env}_details.json")
    table_path = args.table or Path(f"reports/{args.env}.md")
    plot_path = (args.curve_plot or Path(f"reports/{args.env}_curves.png")) if args.curve else None
    check_outputs(metrics, details, table_path, *([plot_path] if plot_path else []))
    bench.sim().make_env().close()  # the optional extra's absence: one line
    per, along, ref_eps = run_episodes(args, bench, *episode_jobs(args, bench))
    refs = {k: summary(eps, bench.tasks) for k, eps in ref_eps.items()}
    rows = {key: {**summary(eps, bench.tasks), "ms": float(np.median([e["ms"] for e in eps]))}
            for key, eps in per.items()}
    curves = {key: curve_summary(sorted(by_step.items())) for key, by_step in along.items()}
    headline = {f"{m}/{s}/{ck}": {"score": round(r["score"], 3), "success": round(r["success"], 3)}
                for (m, s, ck), r in rows.items()}
    headline.update({f"{m}/{s}/curve": {"score_max": round(c["max"]["score"], 3),
                                        "score_last3": round(c["last"]["score"], 3)} for (m, s), c in curves.items()})
    write_all_atomic({
        metrics: json_text(headline),
        details: json_text({"env": args.env, "episodes": args.episodes, "first_seed": args.seed,
                            "execute": args.execute, "max_steps": args.max_steps,
                            "results": [{"model": m, "steps": s, "checkpoint": ck, **r, "per_episode": per[(m, s, ck)]}
                                        for (m, s, ck), r in rows.items()],
                            "curves": [{"model": m, "steps": s, "episodes": args.curve_episodes or args.episodes, **c}
                                       for (m, s), c in curves.items()],
                            "references": {k: {**refs[k], "per_episode": ref_eps[k]} for k in refs}}),
        table_path: table(bench, rows, refs, args.episodes, args.execute, args.seed, args.max_steps, curves)})
    if plot_path:
        plot_curves(curves, refs, plot_path, bench.title)
    for (m, s, ck), r in rows.items():
        print(f"{m} {s} steps ({ck}): score {_score_cell(r)}, success {_success_cell(r)}")
    for (m, s), c in curves.items():
        print(f"{m} {s} steps along training: max {c['max']['score']:.3f} at step {c['max']['step']}, "
              f"last 3 {c['last']['score']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.benchmark", main))
