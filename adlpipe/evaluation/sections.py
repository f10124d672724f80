"""The report's other sections as markdown lines: the headline table, mode commitment, closed loop beside open loop,
the grasp tasks, and the per-policy rows `dvc metrics show` prints."""

from __future__ import annotations

from ..plumbing.atomic import json_text
from ..policy.blind import BLIND
from .stats import paired_success, rate_cell
from .tables import FIXED, default_row, error_cell, rate_of, replay_label, share_cell


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
    lines += ["", f"The same {len(names)} scenes for every row. Closed-loop models: To frames in, Tp waypoints "
              "out at a fixed rate, Ta executed before re-planning (Ta = Tp: one plan per Tp waypoints); below, each "
              "model's best Ta on these very scenes (a pick that favours closed loop). "
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


def grasp_tasks() -> set[str]:
    """The ADL tasks that grip an object and put it somewhere, or carry a scoop to the mouth (no tool held
    throughout that only strokes): those a blind mean trajectory rarely solves."""
    from ..sim.tasks import TASKS

    return {t.name for t in TASKS.values() if t.tool is None or t.touches}


def decision_verdicts(decision: dict) -> dict[str, str]:
    """policy -> one word for `dvc metrics show`: deploy, candidate (not out, not chosen), out-safety, out-success,
    or undecided (a candidate while nothing is decided)."""
    out = {p: "out-safety" for p in decision.get("out_safety", {})}
    out.update({p: "out-success" for p in decision.get("out_success", {})})
    for p in decision.get("candidates", []):
        chosen = decision["recommended"]
        out[p] = "deploy" if p == chosen else ("candidate" if chosen else "undecided")
    return out


def summary_files(ev: dict, rp: dict, cl: dict, decision: dict | None = None) -> dict[str, str]:
    """policy -> the JSON `dvc metrics show` prints as one row: px, cm, ms, success (open loop; closed loop: the best
    Ta's), converged; and where the decision (adlpipe.evaluation.decision) leaves it, when there is one."""
    out: dict[str, dict] = {}
    verdicts = decision_verdicts(decision) if decision is not None else {}
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
                      "converged": ev.get("training", {}).get(model, {}).get("converged"),
                      **({"decision": verdicts[replay_label(model, r)]} if replay_label(model, r) in verdicts else {})}
    for label, r in cl.get("success", {}).items():
        model = label.split("/")[0]
        name = f"closed_loop_{model}"
        if model.startswith("oracle") or (name in out and out[name]["success"] >= round(r["overall"], 4)):
            continue  # keep the best Ta's
        out[name] = {"success": round(r["overall"], 4),
                     "converged": cl.get("training", {}).get(model, {}).get("converged")}
    return {name: json_text(row) for name, row in out.items()}
