"""Evaluate trained policies on the test split: trajectory error and inference time vs number of steps.

    python -m adlpipe.evaluate --models models/fm_cnn models/dp_cnn ... [--steps 1 2 4 8 16]

Per model and step count: mean per-waypoint error in pixels (2D, at the stored image size) and centimetres (3D),
per task and overall; best-of-K error over K samples (how well the samples cover the demonstrated mode); inference
milliseconds per sample (batch 1, encoder included, median of repeated runs). Writes a metrics JSON, a CSV of
error/latency vs steps for `dvc plots`, and a markdown table shaped like the paper's Table 1.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
import time
from pathlib import Path

import h5py
import torch

from . import schema
from .atomic import atomic_path, write_json_atomic, write_text_atomic
from .data import Normalizer, TrajectoryDataset
from .errors import AdlError, run_cli
from .policy.checkpoint import load_policy
from .split import load_split

STEPS = [1, 2, 4, 8, 16]


def multimodal_tasks() -> set[str]:
    from .sim.tasks import TASKS

    return {name for name, t in TASKS.items() if t.multimodal}


def waypoint_errors(pred: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample mean per-waypoint error: (px, cm). pred/gt: (B, N, 5) unnormalised (u, v, x, y, z)."""
    px = (pred[..., :2] - gt[..., :2]).norm(dim=-1).mean(-1)
    cm = (pred[..., 2:] - gt[..., 2:]).norm(dim=-1).mean(-1) * 100.0
    return px, cm


def latency_ms(policy, obs: torch.Tensor, steps: int, method: str, repeats: int) -> float:  # noqa: ANN001
    gen = torch.Generator().manual_seed(0)
    for _ in range(2):  # warm-up
        policy.predict(obs, steps, method, gen)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        policy.predict(obs, steps, method, gen)
        times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times)


def evaluate_model(model_dir: Path, data: Path, test: list[str], steps_list: list[int],
                   methods_by_kind: dict[str, list[str]], k: int, repeats: int, seed: int) -> dict:
    """methods_by_kind: the samplers to evaluate for each objective ("fm", "ddpm"); others use their default."""
    policy, ck = load_policy(model_dir / "model.pt")
    cfg = policy.cfg
    ds = TrajectoryDataset(str(data), test, ck["stats"], cfg.image_size, cfg.use_depth)
    norm = Normalizer(ck["stats"])
    obs = torch.stack([ds[i][0] for i in range(len(ds))])
    gt = norm.unnormalize(torch.stack([ds[i][1] for i in range(len(ds))]))
    tasks = [ds.task(i) for i in range(len(ds))]
    methods = methods_by_kind.get(policy.kind) or [policy.default_method]
    if policy.kind == "mse":
        steps_list = [1]
    by_task = {t: [i for i, tt in enumerate(tasks) if tt == t] for t in sorted(set(tasks))}
    multimodal = multimodal_tasks()
    mm = [i for i, t in enumerate(tasks) if t in multimodal]
    rows = {}
    for method in methods:
        for steps in steps_list:
            gen = torch.Generator().manual_seed(seed)
            pred = norm.unnormalize(policy.predict(obs, steps, method, gen))
            px, cm = waypoint_errors(pred, gt)
            # best-of-K: the closest of K samples to the demonstration (for BC all K are the same prediction)
            best_px, best_cm = px.clone(), cm.clone()
            for _ in range(k - 1 if policy.kind != "mse" else 0):
                p2, c2 = waypoint_errors(norm.unnormalize(policy.predict(obs, steps, method, gen)), gt)
                best_px, best_cm = torch.minimum(best_px, p2), torch.minimum(best_cm, c2)
            per_task = {t: {"px": float(px[idx].mean()), "cm": float(cm[idx].mean()), "n": len(idx)}
                        for t, idx in by_task.items()}
            rows[f"{method}/{steps}"] = {
                "model": cfg.model, "method": method, "steps": steps,
                "evaluations": policy.objective.evaluations(steps, method),
                "px": float(px.mean()), "cm": float(cm.mean()),
                "px_multimodal": float(px[mm].mean()) if mm else None,
                "cm_multimodal": float(cm[mm].mean()) if mm else None,
                f"best_of_{k}_px": float(best_px.mean()), f"best_of_{k}_cm": float(best_cm.mean()),
                "ms": latency_ms(policy, obs[:1], steps, method, repeats), "per_task": per_task,
            }
    return rows


def table1(results: dict[str, dict], k: int) -> str:
    lines = [f"| method | sampler | steps | px | cm | ms | best-of-{k} px | px (multimodal tasks) |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for model, rows in results.items():
        for r in rows.values():
            mm = f"{r['px_multimodal']:.2f}" if r["px_multimodal"] is not None else "-"
            lines.append(f"| {model} | {r['method']} | {r['steps']} | {r['px']:.2f} | {r['cm']:.2f} | {r['ms']:.1f} | "
                         f"{r[f'best_of_{k}_px']:.2f} | {mm} |")
    return "\n".join(lines) + "\n"


def write_steps_csv(path: Path, results: dict[str, dict], steps_list: list[int]) -> None:
    """Wide CSV for `dvc plots`: one row per step count, columns <model>_<sampler>_{px,cm,ms}. A regressor does
    not depend on steps: its single figure is repeated as a flat reference line."""
    series: dict[str, dict[int, dict]] = {}
    for model, rows in results.items():
        for r in rows.values():
            series.setdefault(f"{model}_{r['method']}", {})[r["steps"]] = r
    cols = [f"{name}_{m}" for name in series for m in ("px", "cm", "ms")]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["steps", *cols])
        for k in steps_list:
            row = [k]
            for by_steps in series.values():
                r = by_steps.get(k) or by_steps[min(by_steps)]
                row += [f"{r['px']:.4f}", f"{r['cm']:.4f}", f"{r['ms']:.3f}"]
            w.writerow(row)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m adlpipe.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", type=Path, required=True, help="model folders (holding model.pt)")
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--steps", nargs="+", type=int, default=STEPS)
    p.add_argument("--fm-methods", nargs="+", default=["euler"], help="euler, midpoint, rk4")
    p.add_argument("--dp-methods", nargs="+", default=["ddim", "ddpm"], help="ddim, ddpm")
    p.add_argument("--best-of", type=int, default=8, help="K samples for the best-of-K error")
    p.add_argument("--repeats", type=int, default=20, help="timed runs per latency figure (median)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--metrics", type=Path, default=Path("metrics/eval.json"))
    p.add_argument("--plots", type=Path, default=Path("metrics/steps.csv"))
    p.add_argument("--table", type=Path, default=Path("reports/table1.md"))
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    split = load_split(args.split or args.data.with_name("split.json"))
    if not split["test"]:
        raise AdlError("the test split is empty: record more episodes per task")
    with h5py.File(args.data, "r") as f:
        schema.check_file(f, str(args.data))
        missing = set(split["test"]) - set(schema.episode_names(f))
    if missing:
        raise AdlError(f"{args.data}: {len(missing)} test episode(s) of the split are not in the dataset")
    results = {}
    for d in args.models:
        if not (d / "model.pt").exists():
            raise AdlError(f"{d}: no model.pt; train it first (python -m adlpipe.train)")
        results[d.name] = evaluate_model(d, args.data, split["test"], args.steps,
                                         {"fm": args.fm_methods, "ddpm": args.dp_methods}, args.best_of,
                                         args.repeats, args.seed)
        best = min(results[d.name].values(), key=lambda r: r["px"])
        print(f"{d.name}: best {best['px']:.2f} px / {best['cm']:.2f} cm ({best['method']}, {best['steps']} steps)")
    write_json_atomic(args.metrics, {"n_test": len(split["test"]), "best_of": args.best_of, "models": results})
    write_steps_csv(args.plots, results, args.steps)
    title = "# Trajectory error and inference time on the test split\n\n"
    write_text_atomic(args.table, title + table1(results, args.best_of))
    print(f"wrote {args.metrics}, {args.plots}, {args.table}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.evaluate", main))
