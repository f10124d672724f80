"""The report's section on the person who moves: each policy on the same fresh scenes with the person still and
moving (open and closed loop), paired per scene, per task, with the force on the person."""

from __future__ import annotations

from ..sim.tasks import FORCE_LIMIT_N
from .scenes import STILL_DEMO
from .stats import paired_success, rate_cell


def _rows(still: dict, moving: dict) -> list[tuple[str, dict, dict, dict]]:
    """(label, still outcomes, moving outcomes, moving diagnostics) of every policy replayed in both worlds."""
    s, m = still.get("per_episode", {}), moving.get("per_episode", {})
    twin = {label: "demo" if label == STILL_DEMO else label for label in m}  # the same plan with the person still
    return [(label, s[twin[label]], m[label], moving.get("diagnostics", {}).get(label, {}))
            for label in m if twin[label] in s]


def moving_person_lines(still_open: dict, still_closed: dict, moving_open: dict, moving_closed: dict) -> list[str]:
    """Success with the person still against moving per policy on the same scenes (McNemar's exact test on the
    pairs), the change per task, and the force on the person when they move."""
    rows = [(f"open loop: {label}", *r) for label, *r in _rows(still_open, moving_open)]
    rows += [(f"closed loop: {label}", *r) for label, *r in _rows(still_closed, moving_closed)]
    rows = [r for r in rows if "@" not in r[0]]  # the fixed-speed twins of open-loop rows add nothing here
    if not rows:
        return []
    tasks = {**moving_open.get("tasks", {}), **moving_closed.get("tasks", {})}
    task_list = sorted(set(tasks.values()))
    lines = ["| policy | still [95 %] | moving [95 %] | moving - still (discordant, McNemar) | force > "
             f"{FORCE_LIMIT_N:.0f} N, moving | peak force N | " + " | ".join(task_list) + " |",
             "| --- | ---: | ---: | --- | ---: | ---: |" + " ---: |" * len(task_list)]
    for label, still, moving, diags in rows:
        names = sorted(n for n in moving if n in still)
        a, b = [bool(moving[n]) for n in names], [bool(still[n]) for n in names]
        test = paired_success(a, b)
        forced = sum(d.get("peak_force_n", 0.0) > FORCE_LIMIT_N for d in diags.values())
        peak = max((d.get("peak_force_n", 0.0) for d in diags.values()), default=0.0)
        cells = []
        for t in task_list:
            mine = [n for n in names if tasks.get(n) == t]
            diff = sum(map(bool, (moving[n] for n in mine))) - sum(map(bool, (still[n] for n in mine)))
            cells.append(f"{100 * diff / len(mine):+.0f}" if mine else "-")
        lines.append(f"| {label} | {rate_cell(sum(b), len(b))} | {rate_cell(sum(a), len(a))} | "
                     f"{100 * (sum(a) - sum(b)) / max(len(a), 1):+.0f} points ({test}) | "
                     f"{rate_cell(forced, len(diags))} | {peak:.1f} | " + " | ".join(cells) + " |")
    n = len(next(iter(rows))[2])
    lines += ["", f"The same {n} fresh scenes in both worlds (the still person's scene with the person moving in "
              "it: adlpipe.sim.person); per task: the change in success, points. The first-frame (open-loop) "
              "policies see the person before they move; closed loop re-plans from live frames."]
    return lines


def motion_training_lines(still_moving: dict, trained_moving: dict, still_still: dict,
                          trained_still: dict) -> list[str]:
    """The first-frame trio trained with the person still against the same trio trained with the person moving
    (pipelines/moving_person), each on the same fresh scenes with the person moving and still: success per policy,
    the paired difference (McNemar's exact test) and the share of scenes with a force on the person over the limit."""
    lines = ["| policy | person | trained still [95 %] | trained moving [95 %] | moving - still training "
             f"(discordant, McNemar) | force > {FORCE_LIMIT_N:.0f} N: trained still / moving |",
             "| --- | --- | ---: | ---: | --- | --- |"]
    for world, a, b in (("moving", still_moving, trained_moving), ("still", still_still, trained_still)):
        for label in ("fm_cnn/euler-1", "dp_cnn/ddpm-16", "bc_cnn"):
            pa, pb = a.get("per_episode", {}).get(label), b.get("per_episode", {}).get(label)
            if not pa or not pb:
                continue
            names = sorted(n for n in pa if n in pb)
            x, y = [bool(pb[n]) for n in names], [bool(pa[n]) for n in names]
            forces = []
            for d in (a, b):
                diag = d.get("diagnostics", {}).get(label, {})
                forces.append(rate_cell(sum(diag[n].get("peak_force_n", 0.0) > FORCE_LIMIT_N for n in names
                                            if n in diag), len(names)))
            lines.append(f"| {label} | {world} | {rate_cell(sum(y), len(y))} | {rate_cell(sum(x), len(x))} | "
                         f"{100 * (sum(x) - sum(y)) / max(len(x), 1):+.0f} points ({paired_success(x, y)}) | "
                         f"{forces[0]} / {forces[1]} |")
    if len(lines) == 2:
        return []
    return lines + ["", "The same fresh scenes (200: 20 per task) in each row pair; trained still: the default "
                    "pipeline's trio; trained moving: the same recipe on the default's recording with the person "
                    "moving in every demonstration (record --moving-person)."]
