"""What the benchmark writes and compares: the seed's Table 2 replica, the learning curves' plot, and paired
comparisons of rows on the initial conditions both ran (bootstrap of the score difference, McNemar on success)."""

from __future__ import annotations

import json
from pathlib import Path

from ..envs.registry import Benchmark
from ..plumbing.atomic import atomic_path
from ..plumbing.errors import AdlError
from .stats import interval_cell, paired_difference, paired_success


def tasks_cell(r: dict) -> str:
    return " / ".join(f"{v:.0%}" for v in r["tasks"].values())


def score_cell(r: dict) -> str:
    return interval_cell(r["score"], r["score_ci"])


def success_cell(r: dict) -> str:
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
        lines.append(f"| {name} (reference) | | | {score_cell(r)} | {success_cell(r)} | |"
                     + (f" {tasks_cell(r)} |" if per_task else ""))
    for (model, steps, ck), r in rows.items():
        lines.append(f"| {model} | {steps} | {ck} | {score_cell(r)} | {success_cell(r)} | {r['ms']:.1f} |"
                     + (f" {tasks_cell(r)} |" if per_task else ""))
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
            lines.append(f"| {model} | {steps} | {len(c['points'])} | {top['n']} | {score_cell(top)} "
                         f"({top['step']}) | {success_cell(top)} | {score_cell(tail)} | {success_cell(tail)} |")
    return "\n".join(lines) + "\n"


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
