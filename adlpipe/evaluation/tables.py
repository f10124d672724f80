"""Markdown tables from evaluate's and replay's details that the report and README's generated results share
(adlpipe.results), so the two never word or round a figure differently."""

from __future__ import annotations

from ..policy.blind import BLIND
from .stats import interval_cell, paired_difference, paired_success, rate_cell

FIXED = "@fixed-speed"  # replay's label suffix for a trajectory run at the task's demonstrated speed


def error_cell(r: dict, key: str, digits: int = 2) -> str:
    """'2.23 [2.05, 2.41]': an error (or a latency) and its 95 % interval; a row evaluated before the figure had an
    interval prints the figure alone."""
    ci = r.get(f"{key}_ci")
    return interval_cell(r[key], ci, digits) if ci else f"{r[key]:.{digits}f}"


def share_cell(r: dict, key: str) -> str:
    """'64 % [55, 72]': a share with its 95 % interval; '-' where it was not measured."""
    if r.get(key) is None:
        return "-"
    ci = r.get(f"{key}_ci")
    return f"{r[key]:.0%} [{100 * ci[0]:.0f}, {100 * ci[1]:.0f}]" if ci else f"{r[key]:.0%}"


def rate_of(r: dict | None) -> str:
    return "-" if r is None else f"{rate_cell(round(r['overall'] * r['n']), r['n'])} n={r['n']}"


def replay_label(model: str, row: dict) -> str:
    """Replay's label of an evaluated model row: <model>/<sampler>-<steps>, or the model alone for a regressor and
    the blind baseline."""
    return model if row["method"] in ("direct", "task_mean") else f"{model}/{row['method']}-{row['steps']}"


def default_row(ev: dict, model: str) -> dict | None:
    rows = list(ev.get("models", {}).get(model, {}).get("best", {}).values())
    return next((x for x in rows if x.get("default")), None) or (min(rows, key=lambda x: x["steps"]) if rows else None)


def blind_lines(ev: dict, rp: dict) -> list[str]:
    """How far each model is above the blind baseline, paired: the px difference on the test episodes (model -
    blind, negative: the model is better) with its bootstrap interval, and the success on replay's scenes by
    McNemar's exact test, with its verdict (and the scenes that would resolve it)."""
    blind = default_row(ev, BLIND)
    if blind is None or not blind.get("px_per_episode"):
        return []
    per = rp.get("per_episode", {})
    lines = ["| model | px - blind px [95 %] | verdict: better than blind | success vs blind | verdict in success |",
             "| --- | ---: | --- | --- | --- |"]
    for model in ev.get("models", {}):
        r = default_row(ev, model)
        if model == BLIND or r is None or not r.get("px_per_episode"):
            continue
        d = paired_difference(r["px_per_episode"], blind["px_per_episode"])
        a, b = per.get(replay_label(model, r), {}), per.get(BLIND, {})
        both = sorted(set(a) & set(b))
        vs, verdict = "-", "-"
        if both:
            test = paired_success([a[n] for n in both], [b[n] for n in both])
            sa, sb = sum(a[n] for n in both), sum(b[n] for n in both)
            vs = f"{100 * sa / len(both):.0f} vs {100 * sb / len(both):.0f} % ({test})"
            verdict = {"better": "beats blind", "worse": "below blind"}.get(test.verdict(), test.verdict())
        lines.append(f"| {model} | {d.mean:+.2f} [{d.low:+.2f}, {d.high:+.2f}] | {d.verdict()} | {vs} | {verdict} |")
    scenes = rp.get("scenes", {})
    where = (f"{rp['episodes']} fresh scenes ({scenes.get('per_task')} per task)" if scenes.get("kind") == "fresh"
             else f"{rp['episodes']} test episodes")
    return lines + ["", f"Blind: {blind['px']:.2f} px, {blind['cm']:.2f} cm over {blind['n']} test episodes; replay "
                    f"{rate_of(rp.get('success', {}).get(BLIND))} on {where}. A model that is not better than blind "
                    "has learnt nothing from the image that the task name does not give."]


def per_task_lines(ev: dict, rp: dict, grasp: set[str]) -> list[str]:
    """Scenes solved per task (k of n) by each model's default sampler and by the blind baseline, on replay's
    scenes (the demonstration's duration); a task that needs a grasp or a placement is marked *."""
    success = rp.get("success", {})
    labels = [BLIND] + [replay_label(m, r) for m in ev.get("models", {}) if m != BLIND
                        for r in [default_row(ev, m)] if r is not None]
    labels = [x for x in labels if x in success]
    if not labels:
        return []
    tasks = sorted({t for x in labels for t in success[x]["per_task"]})
    lines = ["| policy | " + " | ".join(f"{t}{' *' if t in grasp else ''}" for t in tasks) + " |",
             "| --- |" + " ---: |" * len(tasks)]
    for x in labels:
        r = success[x]
        cells = [f"{round(r['per_task'][t] * r['per_task_n'][t])} of {r['per_task_n'][t]}" if t in r["per_task"]
                 else "-" for t in tasks]
        lines.append(f"| {x} | " + " | ".join(cells) + " |")
    return lines + ["", "*: the task needs a grasp or a placement (an object gripped and put, or a spoon's scoop "
                    "carried to the mouth)."]


def _spread(entry: dict, key: str, scale: float = 1.0, digits: int = 2) -> str:
    if entry.get(key) is None:
        return "-"
    each = " / ".join(f"{scale * v:.{digits}f}" for v in entry[key])
    return f"{scale * entry[f'{key}_mean']:.{digits}f} ± {scale * entry[f'{key}_sd']:.{digits}f} ({each})"


def seeds_lines(s: dict) -> list[str]:
    """The seeds summary (adlpipe.seeds): per model the mean ± sd over seeds with each seed's figure, then each
    claim per seed and over seeds."""
    lines = ["Mean ± standard deviation over the seeds (each seed's figure in brackets, seed order); the default "
             "sampler of each model, best validation checkpoint; success: open-loop replay.", "",
             "| model | row | px | cm | success % | converged |", "| --- | --- | ---: | ---: | ---: | ---: |"]
    for m, e in s["models"].items():
        conv = ("- (not trained)" if all(c is None for c in e["converged"])
                else f"{sum(bool(c) for c in e['converged'])} of {len(e['converged'])}")
        lines.append(f"| {m} | {e['row']} | {_spread(e, 'px')} | {_spread(e, 'cm')} | {_spread(e, 'success', 100, 0)} "
                     f"| {conv} |")
    lines += ["", "Claims: per seed, the paired bootstrap verdict on that seed's models (first - scale x second, px); "
              "over seeds, the same on each test episode's error averaged over the seeds.", "",
              "| claim | per seed | over seeds: difference [95 %] | verdict over seeds |", "| --- | --- | ---: | --- |"]
    for c in s["claims"]:
        lo, hi = c["difference"][1:]
        lines.append(f"| {c['claim']} | {' / '.join(c['per_seed'])} | {c['difference'][0]:+.2f} [{lo:+.2f}, {hi:+.2f}] "
                     f"| {c['over_seeds']} |")
    return lines
