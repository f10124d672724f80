"""How replayed policies fail, safety first: the breakdown of failures by the part of the task's predicate that
failed, and a picture strip of failed episodes. Replay writes both; the report reads the breakdown back from
replay's details.

Each replayed episode keeps a diagnosis: {"failed": [parts of the predicate missed], "peak_force_n": the largest
contact normal force on the manikin}. The parts (adlpipe.sim.tasks.SuccessMonitor.checks): force (above the 20 N
limit on the person), touches (a grasp or contact target not reached, in order), stroke (too short), dwell (the
tool not held at its goal long enough), placed (the object not where it belongs).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from .replay import failure_table
from .stats import rate_cell
from .tables import FIXED

PARTS = ("force", "touches", "stroke", "dwell", "placed")
PART_NAMES = {"force": "force > 20 N on the person", "touches": "grasp / contact missed", "stroke": "stroke short",
              "dwell": "dwell short", "placed": "not placed"}


def breakdown_lines(diagnostics: dict[str, dict[str, dict]], per_episode: dict[str, dict[str, bool]]) -> list[str]:
    """A markdown table: per policy, its failures, how many exceeded the force limit on the person (with the rate's
    interval) and the peak force over all its episodes, and how many failures missed each other part."""
    head = " | ".join(PART_NAMES[p] for p in PARTS[1:])
    lines = [f"| policy | failed | force > 20 N on the person [95 %] | peak force N | {head} |",
             "| --- | ---: | ---: | ---: |" + " ---: |" * (len(PARTS) - 1)]
    for label, diags in diagnostics.items():
        if not diags or "peak_force_n" not in next(iter(diags.values())):
            continue  # details written before the diagnosis was kept
        n = len(diags)
        failed = [d for name, d in diags.items() if not per_episode.get(label, {}).get(name, False)]
        over = sum("force" in d["failed"] for d in diags.values())
        peak = max(d["peak_force_n"] for d in diags.values())
        counts = " | ".join(str(sum(p in d["failed"] for d in failed)) for p in PARTS[1:])
        lines.append(f"| {label} | {len(failed)} of {n} | {over} ({rate_cell(over, n)} %) | {peak:.1f} | {counts} |")
    return lines if len(lines) > 2 else []


def failure_strip(label: str, shots: list[dict]) -> bytes:
    """A PNG strip of failed episodes: the first camera frame with the demonstrated (green) and the predicted (red)
    2D trajectory, titled with the task, the parts that failed and the peak force. shots: {"task", "rgb" (H, W, 3),
    "demo_px" (N, 2), "pred_px" (N, 2), "failed", "peak_force_n"}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(shots), figsize=(2.6 * len(shots), 3.1), squeeze=False)
    for ax, s in zip(axes[0], shots, strict=True):
        ax.imshow(s["rgb"])
        ax.plot(*np.asarray(s["demo_px"]).T, "-", color="lime", lw=1.2, label="demonstration")
        ax.plot(*np.asarray(s["pred_px"]).T, "-", color="red", lw=1.2, label="policy")
        h, w = s["rgb"].shape[:2]
        ax.set(xlim=(-0.5, w - 0.5), ylim=(h - 0.5, -0.5))  # the image's extent: a path leaving it is cut off
        failed = "\n".join(PART_NAMES[p] for p in s["failed"])
        ax.set_title(f"{s['task']}\n{failed}\npeak {s['peak_force_n']:.0f} N", fontsize=6, loc="left")
        ax.set_axis_off()
    axes[0][0].legend(fontsize=5, loc="lower left")
    fig.suptitle(f"{label}: failed episodes (one per task)", fontsize=8, y=1.12)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def pick_failures(diags: dict[str, dict], ok: dict[str, bool], tasks: dict[str, str], n: int) -> list[str]:
    """Up to n failed episodes, one per task first (in task order), unsafe ones (force) before the rest."""
    failed = sorted((name for name in diags if not ok.get(name, False)),
                    key=lambda name: ("force" not in diags[name]["failed"], tasks.get(name, ""), name))
    picked, seen = [], set()
    for name in failed:
        if tasks.get(name) not in seen:
            picked.append(name)
            seen.add(tasks.get(name))
    return (picked + [x for x in failed if x not in picked])[:n]


def outcome_text(details: dict, model: str, episode: str) -> str:
    """What replay found for one episode and every replayed label of one model (its samplers, step counts and
    speed profiles): success, or the parts that failed, and the peak force on the person. Empty when none."""
    lines = []
    for label, per in details.get("per_episode", {}).items():
        if episode not in per or not (label == model or label.startswith(f"{model}/") or label.startswith(f"{model}@")):
            continue
        d = details.get("diagnostics", {}).get(label, {}).get(episode, {})
        what = "success" if per[episode] else "failed: " + (", ".join(PART_NAMES.get(p, p) for p in d.get("failed", []))
                                                            or "?")
        force = f", peak force {d['peak_force_n']:.1f} N" if "peak_force_n" in d else ""
        lines.append(f"{label}: {what}{force}")
    return "\n".join(lines)


def success_table(result: dict[str, dict], scenes: list, closed_loop: bool, checkpoint: str, where: str) -> str:
    tasks = sorted({s.task for s in scenes})
    per_task_n = {t: sum(s.task == t for s in scenes) for t in tasks}
    lines = ["| policy | overall [95 %] | n | " + " | ".join(f"{t} (n = {per_task_n[t]})" for t in tasks) + " |",
             "| --- | ---: | ---: |" + " ---: |" * len(tasks)]
    for label, r in result.items():
        cells = " | ".join(rate_cell(round(r["per_task"][t] * r["per_task_n"][t]), r["per_task_n"][t])
                           if t in r["per_task"] else "-" for t in tasks)
        lines.append(f"| {label} | {rate_cell(round(r['overall'] * r['n']), r['n'])} | {r['n']} | {cells} |")
    mode = ("closed-loop (execute Ta of the predicted waypoints, then re-plan)" if closed_loop
            else "open-loop")
    return (f"# Success rate (%) of {mode} execution in MuJoCo, {where}, {checkpoint} checkpoints\n\n"
            "Success: the task's predicate, with any contact force on the manikin above 20 N a failure. Overall: "
            "the rate with Wilson's 95 % interval over n scenes; per task likewise over its n scenes (few: wide).\n\n"
            + "\n".join(lines) + "\n")


def failure_sections(closed_loop: bool, diagnostics: dict, per_episode: dict) -> str:
    failures = failure_table(diagnostics, per_episode) if closed_loop else ""
    outcome = breakdown_lines(diagnostics, per_episode)
    if outcome:
        failures = ("\n## How the policies fail, safety first\n\nPer policy: its failed episodes; those with a "
                    "contact force on the person above 20 N (of all its episodes, Wilson's 95 % interval) and the "
                    "peak force over all of them; the failures missing each other part of the predicate (an episode "
                    "may miss several).\n\n" + "\n".join(outcome) + "\n" + failures)
    return failures


def failure_strips(folder: Path | None, scenes: list, trajs: dict, diagnostics: dict, per_episode: dict,
                   strip: int) -> dict[Path, bytes]:
    if folder is None:
        return {}
    strips: dict[Path, bytes] = {}
    by_name = {s.name: (i, s) for i, s in enumerate(scenes)}
    tasks_of = {s.name: s.task for s in scenes}
    for label, diags in diagnostics.items():
        if label.endswith(FIXED):
            continue  # the same trajectories as the label's own strip, timed differently
        picked = pick_failures(diags, per_episode[label], tasks_of, strip)
        if picked:
            traj = trajs[label.removesuffix(FIXED)]
            strips[folder / f"{label.replace('/', '_')}.png"] = failure_strip(label, [
                {"task": tasks_of[n], "rgb": by_name[n][1].rgb, "demo_px": by_name[n][1].traj2d,
                 "pred_px": traj[by_name[n][0], :, :2], **diags[n]} for n in picked])
    return strips
