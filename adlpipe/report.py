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

import os
import sys
from pathlib import Path

from .evaluation.claims import UNDERTRAINED_RATIO, claims, convergence_lines
from .evaluation.decision import Rule, decide_replay
from .evaluation.figures import figures
from .evaluation.outcomes import breakdown_lines
from .evaluation.person import moving_person_lines
from .evaluation.sections import closed_loop_lines, grasp_tasks, headline_lines, mode_lines, summary_files
from .evaluation.tables import blind_lines, default_row, per_task_lines
from .evaluation.training_log import read_training_log
from .plumbing.atomic import check_outputs, write_all_atomic
from .plumbing.cli import Parser, float_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, read_json_object, run_cli


def _load(path: Path) -> dict:
    return read_json_object(path, "metrics")


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


def decision_section(decision: dict | None, rp: dict) -> list[str]:
    """Which policy to deploy, by the stated rule (adlpipe.evaluation.decision), and what it is about."""
    if decision is None:
        return []
    stopped = rp.get("sequential")
    how = (f" Replay ran until decided: it stopped after {stopped['scenes']} scenes ({stopped['reason']})."
           if stopped else "")
    return ["## The decision: which policy to put on the robot", "", *decision["lines"], "",
            "This is about these trained checkpoints on these scenes (what a lab deploys); whether a method is better "
            "needs the training seeds of pipelines/study." + how, ""]


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.report", __doc__)
    p.add_argument("--eval", type=Path, default=Path("metrics/eval_details.json"))
    p.add_argument("--replay", type=Path, default=Path("metrics/replay_details.json"))
    p.add_argument("--closed-loop", type=Path, help="replay details of closed-loop policies (optional)")
    p.add_argument("--moving-replay", type=Path, help="open-loop replay details of the same fresh scenes with the "
                   "person moving (replay --moving-person; optional)")
    p.add_argument("--moving-closed-loop", type=Path, help="closed-loop replay details of the same fresh scenes with "
                   "the person moving (optional)")
    p.add_argument("--train-logs", type=Path, default=Path("metrics/train"), help="folder of <model>.csv logs")
    p.add_argument("--table1", type=Path, default=Path("reports/table1.md"))
    p.add_argument("--table2", type=Path, default=Path("reports/table2.md"))
    p.add_argument("--table2-closed-loop", type=Path, default=Path("reports/table2_closed_loop.md"))
    p.add_argument("--failures", type=Path, help="replay's folder of failure strips (PNG), linked from the report")
    p.add_argument("--summary", type=Path, help="folder for one JSON per policy, the rows of `dvc metrics show`")
    p.add_argument("--margin", type=float_range(0.0, 0.5), default=0.05,
                   help="the decision's non-inferiority margin on success, as a fraction (default 0.05: 5 points)")
    p.add_argument("--alpha", type=float_range(0.001, 0.5), default=0.05,
                   help="the decision's family-wise error rate per step (default 0.05)")
    p.add_argument("-o", "--output", type=Path, default=Path("reports/report.md"))
    p.add_force()
    p.io(inputs=["eval", "replay", "closed_loop", "moving_replay", "moving_closed_loop", "train_logs", "table1",
                 "table2", "table2_closed_loop", "failures"], outputs=["output", "summary"])
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
    decision = decide_replay(ev, rp, Rule(args.margin, args.alpha))
    parts = ["# adlpipe report", "",
             f"Test episodes: {ev['n_test']} (error); replay: {replay_scenes(rp)}, {rp.get('checkpoint', 'best')} "
             "checkpoints. Figures of the best validation checkpoints with each model's default sampler.", "",
             "## Headline: each model's default sampler, best checkpoint", "", *headline_lines(ev, rp), "",
             "Replay success: open loop over the demonstration's own duration (which no deployed policy knows); at a "
             "fixed speed: the same trajectory over its own path length at the task's median demonstrated speed.",
             "", *decision_section(decision, rp),
             "## The paper's claims on this data", "", *compared, "",
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
    moving = moving_person_lines(rp, cl, *(_load(m) if m is not None and m.exists() else {}
                                           for m in (args.moving_replay, args.moving_closed_loop)))
    if moving:
        parts += ["## The person who moves (success %, the same fresh scenes)", "", *moving, ""]
    if args.table1.exists():
        parts += ["## Table 1 in detail: every checkpoint, sampler and step count", "", read_table(args.table1), ""]
    for t in (args.table2, args.table2_closed_loop):
        if t.exists():
            parts += [read_table(t).replace("# ", "## ", 1), ""]
    summary = ({args.summary / f"{k}.json": v for k, v in summary_files(ev, rp, cl, decision).items()}
               if args.summary else {})
    write_all_atomic({args.output: "\n".join(parts), **summary, **figs})
    print("\n".join(compared))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.report", main))
