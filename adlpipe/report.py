"""Summarise evaluation and replay into one markdown report: the paper's claims, each supported or not on this data,
and the figures as PNG beside it (no CDN needed to see them).

An accuracy claim ("FM-1 within 10 % of DP-16", "FM better than BC") is decided on the test episodes both models
ran, paired: supported only when the 95 % bootstrap interval of the per-episode difference excludes zero the
claimed way, contradicted when it excludes it the other way, otherwise not resolved at that n (with about how many
episodes would resolve it at the observed effect); a model that did not converge makes it no finding at all.
Success rates are compared by McNemar's exact test on the same scenes. Every model is also measured against the
blind baseline (its task's mean training trajectory: what knowing the task alone buys), and its failures are
broken down by the part of the task's predicate that failed, the force on the person first
(adlpipe.evaluation.outcomes).

--summary writes one small JSON per policy (px, cm, ms, open-loop success, converged) into a folder: the rows
`dvc metrics show` prints, one line per policy.

    python -m adlpipe.report --eval metrics/eval_details.json --replay metrics/replay_details.json -o reports/report.md
"""

from __future__ import annotations

import io
import math
import os
import sys
from pathlib import Path

from .atomic import check_outputs, json_text, write_all_atomic
from .cli import Parser
from .dvc_outputs import refuse_pipeline_outputs
from .errors import AdlError, read_json_object, run_cli
from .evaluation.outcomes import breakdown_lines
from .evaluation.tables import (
    FIXED,
    blind_lines,
    default_row,
    error_cell,
    per_task_lines,
    rate_of,
    replay_label,
    share_cell,
)
from .evaluation.training_log import read_training_log
from .policy.blind import BLIND
from .stats import paired_difference, paired_success, rate_cell

FAST_RATIO = 8.0  # "much faster": DP-16 takes at least this many times FM-1's milliseconds
AS_ACCURATE = 0.10  # "about as accurate": FM-1 px at most 10 % above DP-16 px


def _load(path: Path) -> dict:
    return read_json_object(path, "metrics")


def _row(ev: dict, model: str, method: str, steps: int, checkpoint: str = "best") -> dict | None:
    return ev.get("models", {}).get(model, {}).get(checkpoint, {}).get(f"{method}/{steps}")


UNDERTRAINED_RATIO = 2.0  # a generative model this many times worse than MSE regression on the same network


def _converged(ev: dict, *models: str) -> list[str]:
    """'<model> not converged' (by training's rule) or '<model> undertrained' (see _undertrained) for the models
    among `models` a claim cannot rest on."""
    out = []
    for m in models:
        if not ev.get("training", {}).get(m, {}).get("converged"):
            out.append(f"{m} not converged")
        elif _undertrained(ev, m):
            out.append(f"{m} undertrained: over {UNDERTRAINED_RATIO:.0f}x BC-CNN's error with the same network")
    return out


def _undertrained(ev: dict, model: str) -> bool:
    """A plateau of val px within one run can come from the learning-rate schedule running out, not from the model
    having learnt the data (DP at the default budget: flat at ~22 px as the cosine schedule ends, 2.3 px after
    7,000 steps). A generative U-Net model far worse than BC-CNN, the MSE regressor on the same U-Net and encoder,
    has not learnt what regression learns from the same data: it is undertrained, whatever its curve says."""
    if not model.endswith("_cnn") or model == "bc_cnn":
        return False
    method = "ddpm" if model.startswith("dp_") else "euler"
    row, bc = _row(ev, model, method, 16), _row(ev, "bc_cnn", "direct", 1)
    return bool(row and bc and row["px"] > UNDERTRAINED_RATIO * bc["px"])


def _verdict(holds: bool, not_converged: list[str]) -> str:
    if not_converged:
        measured = "holds" if holds else "fails"
        return f"**not a finding** ({', '.join(not_converged)}; measured: {measured})"
    return "**supported**" if holds else "**not supported**"


def _speed_verdict(fm1: dict, dp16: dict) -> str:
    """The speed-up DP-16 / FM-1 against FAST_RATIO, with the interval its medians' bootstrap intervals bound (the
    slowest DP over the fastest FM to the fastest DP over the slowest FM: conservative): supported when even its
    low end reaches the ratio, contradicted when even its high end stays below, else not resolved."""
    ratio = dp16["ms"] / fm1["ms"]
    text = f"{fm1['ms']:.1f} vs {dp16['ms']:.1f} ms per sample, batch 1, encoder included ({ratio:.1f}x"
    if not (fm1.get("ms_ci") and dp16.get("ms_ci")):  # measured before latencies had intervals
        return f"{'**supported**' if ratio >= FAST_RATIO else '**not supported**'}. {text})."
    lo, hi = dp16["ms_ci"][0] / fm1["ms_ci"][1], dp16["ms_ci"][1] / fm1["ms_ci"][0]
    verdict = ("**supported**" if lo >= FAST_RATIO else "**contradicted**" if hi < FAST_RATIO
               else "**not resolved** (the latencies' spread on this machine)")
    return f"{verdict}. {text} [{lo:.1f}, {hi:.1f}] from the medians' 95 % intervals)."


def _paired_verdict(a: dict, b: dict, not_converged: list[str], scale: float = 1.0) -> str:
    """The claim "a's px is below scale x b's" on the episodes both were evaluated on: supported or contradicted
    only when the paired 95 % bootstrap interval of the per-episode difference excludes zero, else not resolved
    (adlpipe.stats.PairedDifference); never a finding when a model it rests on is not converged."""
    if a.get("px_per_episode") and b.get("px_per_episode"):
        d = paired_difference(a["px_per_episode"], b["px_per_episode"], scale)
        of = f", of first - {scale:g} x second" if scale != 1 else ""  # the tolerance is part of the claim
        verdict, detail = d.verdict(), f" ({d} px{of})"
    else:  # details written before per-episode errors were kept
        verdict = "supported" if a["px"] <= scale * b["px"] else "contradicted"
        detail = " (unpaired: no per-episode errors)"
    if not_converged:
        return f"**not a finding** ({', '.join(not_converged)}; measured: {verdict}){detail}"
    return f"**{verdict}**{detail}"


def _instability(ev: dict, model: str) -> float | None:
    """How much val px goes back up over the second half of training: the mean rise of log val px between
    successive validations (falls count as zero: a curve still improving is not unstable)."""
    hist = [r for r in ev.get("training", {}).get(model, {}).get("val_history", []) if r[1]]
    half = [v for e, v in hist if e > hist[-1][0] / 2] if hist else []
    if len(half) < 3:
        return None
    return sum(max(0.0, math.log(b / a)) for a, b in zip(half[:-1], half[1:], strict=True)) / (len(half) - 1)


# The FM / DP pairs, each on the same U-Net: both predicting the clean trajectory (the default pair), and both
# predicting what the paper's methods predict (a velocity, the noise).
PAIRS = (("fm_cnn", "dp_cnn", "clean-trajectory output for both"),
         ("fm_cnn_velocity", "dp_cnn_epsilon", "the paper's pair: velocity vs noise output"))


def claims(ev: dict, rp: dict) -> list[str]:
    """The paper's four claims, as measured here (best validation checkpoints, default samplers), for each FM/DP
    pair that was trained."""
    out = []
    success = rp.get("success", {})

    def sr(label: str) -> str:
        r = success.get(label)
        return f"{100 * r['overall']:.0f}%" if r else "-"

    def paired(a: str, b: str) -> str:
        """The paired test of two replayed policies on the scenes both ran."""
        pa, pb = rp.get("per_episode", {}).get(a, {}), rp.get("per_episode", {}).get(b, {})
        both = sorted(set(pa) & set(pb))
        return f" ({paired_success([pa[n] for n in both], [pb[n] for n in both])})" if both else ""

    for fm, dp, pair in PAIRS:
        fm1, fm16 = _row(ev, fm, "euler", 1), _row(ev, fm, "euler", 16)
        dp16 = _row(ev, dp, "ddpm", 16)
        if fm1 and dp16:
            verdict = _paired_verdict(fm1, dp16, _converged(ev, fm, dp), 1 + AS_ACCURATE)
            out.append(f"- FM-1 about as accurate as DP-16 (within {100 * AS_ACCURATE:.0f}% or better; {pair}): "
                       f"{verdict}. {fm} 1 step {fm1['px']:.2f} px "
                       f"({fm1['px224']:.2f} px at 224) vs {dp} 16 DDPM steps {dp16['px']:.2f} px "
                       f"({dp16['px224']:.2f}); replay {sr(f'{fm}/euler-1')} vs {sr(f'{dp}/ddpm-16')}"
                       f"{paired(f'{fm}/euler-1', f'{dp}/ddpm-16')}.")
            out.append(f"- FM-1 much faster than DP-16 (at least {FAST_RATIO:.0f}x; {pair}): "
                       f"{_speed_verdict(fm1, dp16)}")
        if fm16 and dp16:
            out.append(f"- At equal steps (16), {fm} more accurate than {dp}: "
                       f"{_paired_verdict(fm16, dp16, _converged(ev, fm, dp))}. {fm16['px']:.2f} vs "
                       f"{dp16['px']:.2f} px.")
        s_fm, s_dp = _instability(ev, fm), _instability(ev, dp)
        if s_fm is not None and s_dp is not None:
            out.append(f"- FM more stable in training than DP ({pair}): "
                       f"{_verdict(s_fm <= s_dp, _converged(ev, fm, dp))}. Mean rise of log val px between "
                       f"validations over the second half of training: {fm} {s_fm:.4f}, {dp} {s_dp:.4f} (0: never "
                       "went back up); see val_px_vs_epoch.png.")
    for fm, bc, net in (("fm_cnn", "bc_cnn", "U-Net"), ("fm_transformer", "bc_transformer", "transformer")):
        f, b = _row(ev, fm, "euler", 1), _row(ev, bc, "direct", 1)
        if f and b:
            mm = (f"; multimodal tasks {f['px_multimodal']:.2f} vs {b['px_multimodal']:.2f} px"
                  if f.get("px_multimodal") is not None and b.get("px_multimodal") is not None else "")
            out.append(f"- FM better than BC ({net} for both, only the objective differs): "
                       f"{_paired_verdict(f, b, _converged(ev, fm, bc))}. 1 step {f['px']:.2f} vs {b['px']:.2f} "
                       f"px{mm}; "
                       f"replay {sr(f'{fm}/euler-1')} (16 steps: {sr(f'{fm}/euler-16')}) vs {sr(bc)}"
                       f"{paired(f'{fm}/euler-1', bc)}.")
    return out


def closed_loop_lines(open_rp: dict, cl: dict) -> list[str]:
    """Closed-loop and open-loop success per task on the same test episodes (those the closed loop replayed)."""
    names = sorted({n for per in cl.get("per_episode", {}).values() for n in per})
    tasks = {**open_rp.get("tasks", {}), **cl.get("tasks", {})}
    if not names:
        return []
    task_list = sorted({tasks.get(n, "?") for n in names})
    open_labels = ("fm_cnn/euler-1", "fm_cnn/euler-16", "dp_cnn/ddpm-16", "bc_cnn", "demo")
    rows = [(f"open loop: {label} (first frame -> whole trajectory)", open_rp.get("per_episode", {}).get(label, {}))
            for label in open_labels]
    rows += [(f"closed loop: {label}" if not label.startswith("oracle") else
              f"closed loop: {label} (the demonstration's own plans in the policy's format: the ceiling)", per)
             for label, per in cl["per_episode"].items()]
    lines = ["| policy | overall [95 %] | " + " | ".join(f"{t} % (n)" for t in task_list) + " |",
             "| --- | ---: |" + " ---: |" * len(task_list)]
    for label, per in rows:
        got = [per[n] for n in names if n in per]
        if len(got) < len(names):
            continue  # not replayed on these episodes
        cells = []
        for t in task_list:
            v = [per[n] for n in names if tasks.get(n) == t]
            cells.append(f"{100 * sum(v) / len(v):.0f} ({len(v)})")
        lines.append(f"| {label} | {rate_cell(sum(got), len(got))} n={len(got)} | " + " | ".join(cells) + " |")
    training = cl.get("training", {})
    late = [m for m, t in training.items() if not t.get("converged")]
    lines += ["", f"The same {len(names)} test episodes for every row. Closed-loop models: To frames in, Tp waypoints "
              "out at a fixed rate, Ta executed before re-planning (Ta = Tp: one plan per Tp waypoints). "
              + (f"Not converged: {', '.join(late)}." if late else "All closed-loop models converged."), ""]
    open_per = open_rp.get("per_episode", {})
    for model, label in (("fm_cnn", "fm_cnn/euler-1"), ("dp_cnn", "dp_cnn/ddpm-16"), ("bc_cnn", "bc_cnn")):
        ol = [open_per.get(label, {}).get(n) for n in names]
        cls = {k: per for k, per in cl["per_episode"].items() if k.split("/")[0] == model}
        if None in ol or not cls:
            continue
        best_label, best = max(cls.items(), key=lambda kv: sum(kv[1].get(n, False) for n in names))
        closed = [bool(best.get(n, False)) for n in names]
        c, o = sum(closed), sum(ol)
        test = paired_success(closed, ol)
        verdict = ("**reaches**" if c >= o else "**stays below**" if test.p_value < 0.05
                   else f"is below (**not resolved** at n = {len(names)})")
        lines.append(f"- {model}: closed loop {verdict} open loop. Best closed loop {best_label} "
                     f"{rate_cell(c, len(names))} % vs open loop {label} {rate_cell(o, len(names))} % on the same "
                     f"{len(names)} scenes ({test}).")
    return lines


# Two-mode tasks whose average of the modes fails physically: the broom's average path hits the trash, the lid's
# hits the bottle, and the forearm's average of the two stroke directions strokes nowhere.
AVERAGING_FAILS = ("sweep the trash", "cover the food", "wipe the forearm")


def mode_lines(ev: dict, rp: dict) -> list[str]:
    """Mode commitment beside error, time and replay success on the averaging-fails tasks, per model at its
    default step count and at 16 steps."""
    tasks = rp.get("tasks", {})
    head = " | ".join(AVERAGING_FAILS)
    lines = ["| policy | steps | px [95 %] | ms [95 %] | mode commitment [95 %] | to the demonstrated mode [95 %] | "
             f"{head} |",
             "| --- | ---: | ---: | ---: | ---: | ---: |" + " ---: |" * len(AVERAGING_FAILS)]
    for model, by_ck in ev.get("models", {}).items():
        best = by_ck.get("best", {})
        default = next((r for r in best.values() if r.get("default")), None)
        if default is None or default.get("commitment") is None:
            continue
        at16 = best.get(f"{default['method']}/16")
        for r in [default] + ([at16] if at16 is not None and at16["steps"] != default["steps"] else []):
            label = model if r["method"] == "direct" else f"{model}/{r['method']}-{r['steps']}"
            per = rp.get("per_episode", {}).get(label, {})
            cells = []
            for t in AVERAGING_FAILS:
                got = [ok for n, ok in per.items() if tasks.get(n) == t]
                cells.append(f"{rate_cell(sum(got), len(got))} ({len(got)})" if got else "-")
            lines.append(f"| {model} | {r['steps']} | {error_cell(r, 'px')} | {error_cell(r, 'ms', 1)} | "
                         f"{share_cell(r, 'commitment')} | {share_cell(r, 'to_demonstrated')} | "
                         + " | ".join(cells) + " |")
    if len(lines) == 2:
        return []
    return lines + ["", f"Over {ev.get('mode_scenes', '?')} test scenes of two-mode tasks, {ev.get('best_of', '?')} "
                    "samples each: a sample is committed when it lies nearer one of the scene's two demonstrated modes "
                    "(both rebuilt in the simulator) than their average. With modes invisible in the image, committed "
                    "samples should go to the demonstrated mode about half the time. Replay: success % (scenes)."]


def convergence_lines(ev: dict) -> list[str]:
    lines = ["| model | optimiser steps | val px best [95 %] (epoch) | val px last [95 %] | converged |",
             "| --- | ---: | ---: | ---: | --- |"]
    for model, t in ev.get("training", {}).items():
        if t.get("val_px_best") is None:
            continue
        state = "yes" if t.get("converged") else "**no**"
        if t.get("converged") and _undertrained(ev, model):
            state = f"flat, but **undertrained** (16-step px over {UNDERTRAINED_RATIO:.0f}x BC-CNN's)"
        lines.append(f"| {model} | {t.get('optimizer_steps', '?')} | {error_cell(t, 'val_px_best')} "
                     f"({t.get('best_epoch')}) | {error_cell(t, 'val_px_last')} | {state} |")
    return lines


def headline_lines(ev: dict, rp: dict) -> list[str]:
    """One row per model, before the detail: its default sampler's error with intervals on the best checkpoint,
    its latency, whether it converged and its open-loop success (replay) when there is one."""
    lines = ["| model | sampler | steps | px [95 %] | cm [95 %] | ms [95 %] | converged | success (replay) [95 %] | "
             "success at a fixed speed |", "| --- | --- | ---: | ---: | ---: | ---: | --- | ---: | ---: |"]
    success = rp.get("success", {})
    for model in ev.get("models", {}):
        r = default_row(ev, model)
        if r is None:
            continue
        conv = {True: "yes", False: "**no**", None: "?"}[ev.get("training", {}).get(model, {}).get("converged")]
        label = replay_label(model, r)
        ok, fixed = success.get(label), success.get(label + FIXED)
        lines.append(f"| {model} | {r['method']} | {r['steps']} | {error_cell(r, 'px')} | {error_cell(r, 'cm')} | "
                     f"{error_cell(r, 'ms', 1)} | "
                     f"{'- (not trained)' if model == BLIND else conv} | {rate_of(ok)} | {rate_of(fixed)} |")
    return lines


def summary_files(ev: dict, rp: dict, cl: dict) -> dict[str, str]:
    """policy -> the JSON `dvc metrics show` prints as one row: px, cm, ms, success (open loop; closed loop: the best
    Ta's), converged."""
    out: dict[str, dict] = {}
    success = rp.get("success", {})
    if "demo" in success:
        out["demo"] = {"success": round(success["demo"]["overall"], 4)}
    for model in ev.get("models", {}):
        r = default_row(ev, model)
        if r is None:
            continue
        ok = success.get(replay_label(model, r))
        out[model] = {"px": round(r["px"], 3), "cm": round(r["cm"], 3), "ms": round(r["ms"], 2),
                      "success": None if ok is None else round(ok["overall"], 4),
                      "converged": ev.get("training", {}).get(model, {}).get("converged")}
    for label, r in cl.get("success", {}).items():
        model = label.split("/")[0]
        name = f"closed_loop_{model}"
        if model.startswith("oracle") or (name in out and out[name]["success"] >= round(r["overall"], 4)):
            continue  # keep the best Ta's
        out[name] = {"success": round(r["overall"], 4),
                     "converged": cl.get("training", {}).get(model, {}).get("converged")}
    return {name: json_text(row) for name, row in out.items()}


def model_styles(models: list[str]) -> dict[str, dict]:
    """A colour per model (none shared) and a line style per objective family, so no two series look alike."""
    import matplotlib

    colours = matplotlib.colormaps["tab10"].colors
    dash = {"fm": "-", "dp": "--", "bc": ":", "mf": "-."}
    return {m: {"color": colours[i % len(colours)], "linestyle": dash.get(m.split("_")[0], "-")}
            for i, m in enumerate(models)}


def label_steps(ax: object, steps: list[int]) -> None:
    """A log step axis labelled with the step counts themselves (not only 10^0 and 10^1)."""
    from matplotlib.ticker import FixedLocator, NullLocator, ScalarFormatter

    ax.set_xscale("log")
    ax.xaxis.set_major_locator(FixedLocator(sorted(set(steps))))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_locator(NullLocator())


def figures(ev: dict, read: dict[str, dict[str, list[float]]], out_dir: Path) -> dict[Path, bytes]:
    """The seed's Fig. 2 (train/test loss FM vs DP, one panel each: their losses are of different objectives),
    val px vs epoch, px and ms vs steps (all models on a log axis, and beside it the models within 3x of the best on
    a linear one, so one far-off model does not hide the others' differences), as PNG files. read: each model's
    training log columns (read_training_log)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made: dict[Path, bytes] = {}
    styles = model_styles(list(ev.get("models", {})) or list(read))

    def save(fig, name: str) -> None:  # noqa: ANN001
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
        plt.close(fig)
        made[out_dir / name] = buf.getvalue()  # written with the report, all or none

    if read:
        pair = [m for m in ("fm_cnn", "dp_cnn") if m in read]
        fig, axes = plt.subplots(1, max(len(pair), 1), figsize=(5.5 * max(len(pair), 1), 4), squeeze=False)
        for ax, m in zip(axes[0], pair, strict=False):
            ax.plot(read[m]["epoch"], read[m]["train_loss"], color=styles.get(m, {}).get("color"), label="train")
            pts = [(e, v) for e, v in zip(read[m]["epoch"], read[m]["test_loss"], strict=False)
                   if not math.isnan(v)]  # measured with each validation
            if pts:
                ax.plot(*zip(*pts, strict=True), "--", color="black", label="test")
            ax.set(xlabel="epoch", ylabel=f"{m} loss (its own objective)", yscale="log", title=m)
            ax.legend()
        fig.suptitle("Train and test loss, FM vs DP (separate axes: different objectives)")
        save(fig, "loss_fm_vs_dp.png")
        fig, ax = plt.subplots(figsize=(6, 4))
        for m, cols in read.items():
            pts = [(e, v) for e, v in zip(cols["epoch"], cols.get("val_px", []), strict=False) if not math.isnan(v)]
            if pts:
                ax.plot(*zip(*pts, strict=True), marker=".", label=m, **styles.get(m, {}))
        ax.set(xlabel="epoch", ylabel="val px (default sampler)", yscale="log", title="Validation error vs epoch")
        ax.legend(fontsize=7)
        save(fig, "val_px_vs_epoch.png")
    for key, ylabel, name in (("px", "px (test, best checkpoint)", "px_vs_steps.png"),
                              ("ms", "ms per sample, batch 1", "ms_vs_steps.png")):
        series: list[tuple[str, str, list]] = []
        for model, by_ck in ev.get("models", {}).items():
            per: dict[str, list] = {}
            for r in by_ck.get("best", {}).values():
                per.setdefault(r["method"], []).append((r["steps"], r[key]))
            series += [(model, method, sorted(pts)) for method, pts in per.items()]
        steps = sorted({s for _m, _k, pts in series for s, _v in pts})
        lowest = min((v for _m, _k, pts in series for _s, v in pts), default=1.0)
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, zoom in zip(axes, (False, True), strict=True):
            for model, method, pts in series:
                if zoom and min(v for _s, v in pts) > 3 * lowest:
                    continue
                style = dict(styles.get(model, {}))
                if len(pts) == 1:  # a regressor: one figure for every step count
                    style["linestyle"] = ":"
                    ax.axhline(pts[0][1], label=model, **style)
                else:
                    ax.plot(*zip(*pts, strict=True), marker="o", label=f"{model} {method}", **style)
            label_steps(ax, steps or [1])
            ax.set(xlabel="sampling steps", ylabel=ylabel, yscale="linear" if zoom else "log",
                   title=f"{key} vs steps" + (" (within 3x of the best, linear)" if zoom else " (all, log)"))
            ax.legend(fontsize=6)
        save(fig, name)
    return made


def read_table(path: Path) -> str:
    """A markdown table a stage wrote, or one line naming the file that is not one."""
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise AdlError(f"{path}: cannot read it as a markdown table ({exc.__class__.__name__}: {exc})") from None


def replay_scenes(rp: dict) -> str:
    sc = rp.get("scenes", {})
    if sc.get("kind") == "fresh":
        return (f"{rp['episodes']} fresh scenes ({sc['per_task']} per task, drawn by the recorder's generator with "
                f"seed {sc['seed']} at indices no recording uses)")
    return f"{rp['episodes']} recorded test episodes"


def grasp_tasks() -> set[str]:
    """The ADL tasks that grip an object and put it somewhere, or carry a scoop to the mouth (no tool held
    throughout that only strokes): those a blind mean trajectory rarely solves."""
    from .sim.tasks import TASKS

    return {t.name for t in TASKS.values() if t.tool is None or t.touches}


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.report", __doc__)
    p.add_argument("--eval", type=Path, default=Path("metrics/eval_details.json"))
    p.add_argument("--replay", type=Path, default=Path("metrics/replay_details.json"))
    p.add_argument("--closed-loop", type=Path, help="replay details of closed-loop policies (optional)")
    p.add_argument("--train-logs", type=Path, default=Path("metrics/train"), help="folder of <model>.csv logs")
    p.add_argument("--table1", type=Path, default=Path("reports/table1.md"))
    p.add_argument("--table2", type=Path, default=Path("reports/table2.md"))
    p.add_argument("--table2-closed-loop", type=Path, default=Path("reports/table2_closed_loop.md"))
    p.add_argument("--failures", type=Path, help="replay's folder of failure strips (PNG), linked from the report")
    p.add_argument("--summary", type=Path, help="folder for one JSON per policy, the rows of `dvc metrics show`")
    p.add_argument("-o", "--output", type=Path, default=Path("reports/report.md"))
    p.add_force()
    args = p.parse_args(argv)
    check_outputs(args.output)
    refuse_pipeline_outputs([args.output, args.output.parent / "figures", args.summary], args.force)
    ev, rp = _load(args.eval), _load(args.replay)
    if "models" not in ev or "success" not in rp:
        raise AdlError(f"{args.eval} / {args.replay}: not evaluate/replay detail files (no 'models' / 'success')")
    compared = claims(ev, rp)
    logs = {m: args.train_logs / f"{m}.csv" for m in ev["models"]}
    read = {m: read_training_log(p) for m, p in logs.items() if p.exists()}  # a log that cannot be read is named first
    usable = [m for m in ev["models"] if default_row(ev, m) is not None] if isinstance(ev["models"], dict) else []
    if not usable or not isinstance(rp["success"], dict) or not rp["success"]:
        what = args.eval if not usable else args.replay
        raise AdlError(f"{what}: holds no usable figures (no evaluated model rows / no replayed policy): nothing to "
                       "report; re-run evaluate and replay")
    figs = figures(ev, read, args.output.parent / "figures")
    parts = ["# adlpipe report", "",
             f"Test episodes: {ev['n_test']} (error); replay: {replay_scenes(rp)}, {rp.get('checkpoint', 'best')} "
             "checkpoints. Figures of the best validation checkpoints with each model's default sampler.", "",
             "## Headline: each model's default sampler, best checkpoint", "", *headline_lines(ev, rp), "",
             "Replay success: open loop over the demonstration's own duration (which no deployed policy knows); at a "
             "fixed speed: the same trajectory over its own path length at the task's median demonstrated speed.",
             "", "## The paper's claims on this data", "", *compared, "",
             "## Convergence (same optimiser steps for every model)", "", *convergence_lines(ev), "",
             "A model is converged when its best val px fell by at most 2 % over the last fifth of training; a claim "
             "involving a model that is not, or a generative U-Net model more than "
             f"{UNDERTRAINED_RATIO:.0f}x worse than BC-CNN (the same network trained by regression), is never stated "
             "as a finding.", "",
             "## Figures", "", *[f"![{f.stem}](figures/{f.name})" for f in figs], ""]
    blind = blind_lines(ev, rp)
    if blind:
        parts += ["## Above the blind baseline (paired, best checkpoints, default samplers)", "", *blind, "",
                  "### Scenes solved per task", "", *per_task_lines(ev, rp, grasp_tasks()), ""]
    outcome = breakdown_lines(rp.get("diagnostics", {}), rp.get("per_episode", {}))
    if outcome:
        strips = sorted(args.failures.glob("*.png")) if args.failures is not None and args.failures.is_dir() else []
        rel = [os.path.relpath(f, args.output.parent) for f in strips]
        parts += ["## How the policies fail, safety first (open loop)", "", *outcome, "",
                  "Force: episodes with a contact force on the person above 20 N, of all the policy's episodes; the "
                  "other columns count its failed episodes missing that part of the task's predicate (an episode "
                  "may miss several).", "", *[f"![{f.stem}]({r})" for f, r in zip(strips, rel, strict=True)], ""]
    modes = mode_lines(ev, rp)
    if modes:
        parts += ["## Mode commitment", "", *modes, ""]
    cl = _load(args.closed_loop) if args.closed_loop is not None and args.closed_loop.exists() else {}
    if cl:
        parts += ["## Closed loop vs open loop (success %)", "", *closed_loop_lines(rp, cl), ""]
    if args.table1.exists():
        parts += ["## Table 1 in detail: every checkpoint, sampler and step count", "", read_table(args.table1), ""]
    for t in (args.table2, args.table2_closed_loop):
        if t.exists():
            parts += [read_table(t).replace("# ", "## ", 1), ""]
    summary = {args.summary / f"{k}.json": v for k, v in summary_files(ev, rp, cl).items()} if args.summary else {}
    write_all_atomic({args.output: "\n".join(parts), **summary, **figs})
    print("\n".join(compared))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.report", main))
