"""README's result tables, generated from the committed results of a measured run (one source of truth).

    python -m adlpipe.results --save-from metrics        # after `dvc repro`: keep the run's details in results/
    python -m adlpipe.results --save-seeds pipelines/seeds/metrics/seeds.json
    python -m adlpipe.results --save-study pipelines/study     # after `dvc repro` there
    python -m adlpipe.results --save-closed-loop pipelines/closed_loop     # likewise
    python -m adlpipe.results --save-dagger pipelines/closed_loop          # its DAgger rounds
    python -m adlpipe.results                            # rewrite README's tables from results/
    python -m adlpipe.results --check                    # exit 1 when README and results/ disagree (a test runs it)

README marks each generated table with `<!-- results:NAME -->` ... `<!-- /results:NAME -->`; everything between
the marks is written here from results/default/ (evaluate's, replay's and the closed loop's details) and
results/seeds/seeds.json, with the same cells the report prints (adlpipe.evaluation.tables and .outcomes), and so is
the paragraph on the default run's decision (`results:decision`). Other prose is written by hand; tests/test_docs.py
checks the figures it quotes from results/ against them.
"""

from __future__ import annotations

import re
import shutil
import sys
from pathlib import Path

from .evaluation.claims import claims
from .evaluation.dagger import ARMS as DAGGER_ARMS
from .evaluation.dagger import dagger_lines, fit_lines, merged
from .evaluation.decision import decision_lines
from .evaluation.latency import latency_lines, serve_lines
from .evaluation.outcomes import breakdown_lines
from .evaluation.person import motion_training_lines, moving_person_lines
from .evaluation.recoveries import OPEN_LOOP_OF, recording_line, recoveries_lines
from .evaluation.sections import grasp_tasks
from .evaluation.stats import rate_cell
from .evaluation.table2 import table2_lines
from .evaluation.tables import FIXED, blind_lines, error_cell, per_task_lines, rate_of, seeds_lines
from .plumbing.atomic import atomic_path, write_text_atomic
from .plumbing.cli import Parser
from .plumbing.errors import AdlError, read_json_object, run_cli

RUN_FILES = ("eval_details.json", "replay_details.json", "replay_closed_loop_details.json")  # the last optional

# (README row, model, evaluate's row key ("*": the model's lowest-px row), replay's label)
DEFAULT_ROWS = (
    ("demonstrations (the demonstrator's measured path, 32 waypoints)", None, None, "demo"),
    ("FM-CNN, x1 output, 1 Euler step", "fm_cnn", "euler/1", "fm_cnn/euler-1"),
    ("FM-CNN, x1 output, 16 Euler steps", "fm_cnn", "euler/16", "fm_cnn/euler-16"),
    ("DP-CNN, clean-sample output, 16 DDPM steps (leading)", "dp_cnn", "ddpm/16", "dp_cnn/ddpm-16"),
    ("DP-CNN, clean-sample output, 1 DDPM step (trailing)", "dp_cnn", "ddpm_trailing/1", None),
    ("BC-CNN (MSE, same U-Net)", "bc_cnn", "direct/1", "bc_cnn"),
    ("FM-CNN, velocity output (the paper's), 1 Euler step", "fm_cnn_velocity", "euler/1", "fm_cnn_velocity/euler-1"),
    ("FM-CNN, velocity output, 16 Euler steps", "fm_cnn_velocity", "euler/16", "fm_cnn_velocity/euler-16"),
    ("DP-CNN, epsilon output (the paper's), 16 DDPM steps", "dp_cnn_epsilon", "ddpm/16", "dp_cnn_epsilon/ddpm-16"),
    ("DP-CNN, epsilon output, its lowest-px row", "dp_cnn_epsilon", "*", None),
    ("FM-Transformer, x1 output, 1 Euler step", "fm_transformer", "euler/1", "fm_transformer/euler-1"),
    ("FM-Transformer, x1 output, 16 Euler steps", "fm_transformer", "euler/16", "fm_transformer/euler-16"),
    ("BC-Transformer (MSE, same transformer)", "bc_transformer", "direct/1", "bc_transformer"),
    ("blind baseline: the task's mean training trajectory", "blind", "task_mean/1", "blind"),
)
# What the study keeps (pipelines/study -> results/study): its own path -> the name kept
STUDY_FILES = {"metrics/seed0/eval_details.json": "eval_details.json",
               "metrics/seed0/replay_details.json": "replay_details.json", "metrics/seeds.json": "seeds.json",
               "metrics/replay_open_details.json": "replay_open_details.json",
               "metrics/replay_closed_loop_details.json": "replay_closed_loop_details.json",
               "reports/report.md": "report.md", "reports/seeds.md": "seeds.md",
               "reports/closed_loop/report.md": "closed_loop_report.md",
               **{f"metrics/seed{k}/{kind}_details.json": f"seed{k}/{kind}_details.json"
                  for k in (1, 2) for kind in ("eval", "replay")}}
# What the closed-loop pipeline keeps (pipelines/closed_loop -> results/closed_loop): its own path -> the name kept
CLOSED_LOOP_FILES = {"metrics/replay_closed_loop_details.json": "replay_closed_loop_details.json",
                     "metrics/replay_moving_closed_loop_details.json": "replay_moving_closed_loop_details.json",
                     "metrics/replay_moving_open_details.json": "replay_moving_open_details.json",
                     "metrics/replay_ensemble_details.json": "replay_ensemble_details.json",
                     "metrics/replay_moving_ensemble_details.json": "replay_moving_ensemble_details.json",
                     # the trio trained on demonstrations with recoveries, replayed on the same scenes
                     "metrics/replay_recoveries_details.json": "replay_recoveries_details.json",
                     "metrics/replay_moving_recoveries_details.json": "replay_moving_recoveries_details.json",
                     "metrics/recoveries_recording.json": "recoveries_recording.json",
                     "reports/report.md": "report.md", "reports/history.md": "history.md",
                     # what a plan's latency costs (replay --latency --execution), the person still and moving
                     "metrics/replay_latency_still_details.json": "replay_latency_still_details.json",
                     "metrics/replay_latency_moving_details.json": "replay_latency_moving_details.json",
                     # the open-loop reference: the default pipeline's replay of the same scenes in that run
                     "../../metrics/replay_details.json": "replay_open_details.json"}
# DAgger and HG-DAgger (pipelines/closed_loop -> results/closed_loop/dagger): each arm's replays (the pair's and
# BC's), each round's rollouts, and the expert's timing on round 1's rollouts
DAGGER_FILES = {**{f"metrics/dagger/{kind}{arm}_details.json": f"{kind}{arm}_details.json"
                   for arm, _, _ in DAGGER_ARMS
                   for kind in ("replay_dagger_", "replay_moving_dagger_", "replay_dagger_bc_",
                                "replay_moving_dagger_bc_")},
                **{f"metrics/dagger/{r}_{m}.json": f"{r}_{m}.json"
                   for r in ("dagger_rollout_r1", "dagger_rollout_r2", "hg_rollout_r1", "expert_timing_r1", "fit")
                   for m in ("fm_cnn", "dp_cnn", "bc_cnn")}}
# What pipelines/moving_person keeps (-> results/moving_person): the trio trained with the person moving, replayed
MOVING_PERSON_FILES = {"metrics/replay_moving_details.json": "replay_moving_details.json",
                       "metrics/replay_still_details.json": "replay_still_details.json",
                       "reports/replay_moving.md": "replay_moving.md", "reports/replay_still.md": "replay_still.md"}


def _load(path: Path) -> dict:
    return read_json_object(path, "the committed results")


def default_table(ev: dict, rp: dict) -> list[str]:
    n = ev["n_test"]
    lines = ["| policy | px [95 %] | px224 | cm [95 %] | ms | replay success % [95 %] | at a fixed speed | "
             "val px best [95 %] | converged |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    success = rp["success"]
    for text, model, key, label in DEFAULT_ROWS:
        rows = ev["models"].get(model, {}).get("best", {}) if model else {}
        r = min(rows.values(), key=lambda x: x["px"]) if key == "*" and rows else rows.get(key)
        if model and r is None:
            continue
        if key == "*":
            text = f"{text}: {r['method']} {r['steps']} steps"
        t = ev.get("training", {}).get(model, {})
        conv = {True: "yes", False: "no", None: "-"}[t.get("converged")]
        val = error_cell(t, "val_px_best") if t.get("val_px_best") is not None else ""
        first = key in (None, "task_mean/1") or r.get("default")  # validation and convergence: once per model
        px = (f"{error_cell(r, 'px')} | {r['px224']:.2f} | {error_cell(r, 'cm')} | {error_cell(r, 'ms', 1)}" if r
              else " | | | ")
        lines.append(f"| {text} | {px} | {rate_of(success.get(label)) if label else ''} | "
                     f"{rate_of(success.get(label + FIXED)) if label else ''} | {val if first else ''} | "
                     f"{conv if first and model else ''} |")
    lines += ["", f"n = {n} test episodes (px, cm: 95 % bootstrap intervals); replay: Wilson's 95 % interval over "
              "n scenes."]
    return lines


def closed_loop_table(rp: dict, cl: dict) -> list[str]:
    """Per closed-loop policy (and the oracle): success at each Ta, open loop on the same scenes, val px and
    convergence of its closed-loop training."""
    by: dict[str, dict[int, dict]] = {}
    for label, r in cl["success"].items():
        head, ta = label.rsplit("/Ta-", 1)
        by.setdefault(head, {})[int(ta)] = r
    tas = sorted({ta for v in by.values() for ta in v})
    names = sorted({n for per in cl["per_episode"].values() for n in per})
    lines = [f"| policy | success % at Ta = {' / '.join(map(str, tas))} (n = {len(names)}) | open loop on these "
             "scenes | val px [95 %] | converged |", "| --- | ---: | ---: | ---: | --- |"]
    for head, per_ta in by.items():
        model = head.split("/")[0]
        cells = " / ".join(f"{100 * per_ta[ta]['overall']:.0f}" if ta in per_ta else "-" for ta in tas)
        ol = rp["per_episode"].get(OPEN_LOOP_OF.get(model, ""), {})
        got = [ol[n] for n in names if n in ol]
        open_cell = (f"{OPEN_LOOP_OF[model]}: {rate_cell(sum(got), len(got))}" if len(got) == len(names) and got
                     else "")
        t = cl.get("training", {}).get(model, {})
        val = error_cell(t, "val_px_best") if t.get("val_px_best") is not None else ""
        conv = {True: "yes", False: "no", None: ""}[t.get("converged")]
        text = (f"{head}: the demonstrations' own plans in the policy's format (the executor's ceiling)"
                if model.startswith("oracle") else f"closed-loop {head}")
        lines.append(f"| {text} | {cells} | {open_cell} | {val} | {conv} |")
    return lines


def tables(results: Path) -> dict[str, str]:
    """name -> the markdown README shows between its marks."""
    run = results / "default"
    ev, rp = _load(run / RUN_FILES[0]), _load(run / RUN_FILES[1])

    out = {"default": default_table(ev, rp), "decision": decision_lines(ev, rp), "blind": blind_lines(ev, rp),
           "per-task": per_task_lines(ev, rp, grasp_tasks()),
           "safety": breakdown_lines({k: v for k, v in rp.get("diagnostics", {}).items() if FIXED not in k},
                                     rp["per_episode"])}
    if (run / RUN_FILES[2]).exists():
        out["closed-loop"] = closed_loop_table(rp, _load(run / RUN_FILES[2]))
    seeds = results / "seeds" / "seeds.json"
    if seeds.exists():
        out["seeds"] = seeds_lines(_load(seeds))
    study = results / "study"
    if (study / "eval_details.json").exists():
        out.update(study_tables(study))
    closed = results / "closed_loop"
    if (closed / "replay_closed_loop_details.json").exists():
        cl = _load(closed / "replay_closed_loop_details.json")
        ol = _load(closed / "replay_open_details.json") if (closed / "replay_open_details.json").exists() else rp
        out["closed-loop-fresh"] = closed_loop_table(ol, cl)
        moving = [closed / f"replay_moving_{k}_details.json" for k in ("open", "closed_loop")]
        if all(m.exists() for m in moving):
            out["moving-person"] = moving_person_lines(ol, cl, *map(_load, moving))
        pairs = [("still", "replay_closed_loop", "replay_recoveries", ol),
                 ("moving", "replay_moving_closed_loop", "replay_moving_recoveries", None)]
        worlds = [(world, _load(closed / f"{path}_details.json"), _load(closed / f"{rec}_details.json"),
                   open_loop or _load(closed / "replay_moving_open_details.json"))
                  for world, path, rec, open_loop in pairs if (closed / f"{rec}_details.json").exists()]
        if worlds:
            recording = closed / "recoveries_recording.json"
            out["closed-loop-recoveries"] = ([recording_line(_load(recording)), ""] if recording.exists() else []) \
                + recoveries_lines(worlds)
        trained = results / "moving_person"
        if (trained / "replay_moving_details.json").exists() and (trained / "replay_still_details.json").exists():
            out["moving-trained"] = motion_training_lines(
                _load(moving[0]), _load(trained / "replay_moving_details.json"), ol,
                _load(trained / "replay_still_details.json"))
        out.update(dagger_tables(closed / "dagger", ol, _load(closed / "replay_moving_open_details.json")
                                 if (closed / "replay_moving_open_details.json").exists() else None))
        latency = [closed / f"replay_latency_{w}_details.json" for w in ("still", "moving")]
        if latency[0].exists():
            out["latency"] = latency_lines(_load(latency[0]), _load(latency[1]) if latency[1].exists() else None)
    serve, load = results / "deploy" / "serve_bench.json", results / "deploy" / "serve_load.json"
    if serve.exists():
        out["serve-bench"] = serve_lines(_load(serve), _load(load) if load.exists() else None)
    out["table2"] = table2_lines(results.parent / "pipelines")  # the benchmark pipelines' committed results
    return {k: "\n".join(v) for k, v in out.items() if v}


def dagger_tables(kept: Path, still_open: dict, moving_open: dict | None) -> dict[str, list[str]]:
    """The DAgger rounds' tables, the person still and moving, from what results/closed_loop/dagger keeps."""
    if not kept.is_dir():
        return {}
    rollouts = {p.stem: _load(p) for p in kept.glob("*_rollout_r*.json")}
    out = {}
    for name, prefix, open_loop, person in (("dagger", "replay_dagger_", still_open, "still"),
                                            ("dagger-moving", "replay_moving_dagger_", moving_open, "moving")):
        arms = {}
        for arm, _, _ in DAGGER_ARMS:
            parts = [kept / f"{prefix}{arm}_details.json", kept / f"{prefix}bc_{arm}_details.json"]
            found = [_load(p) for p in parts if p.exists()]
            if found:
                arms[arm] = merged(*found)
        if arms and open_loop is not None:
            out[name] = dagger_lines(arms, open_loop, rollouts, person)
    fits = {p.stem.removeprefix("fit_"): _load(p) for p in kept.glob("fit_*.json")}
    if fits and (lines := fit_lines(fits)):
        out["dagger-fit"] = lines
    return out


def study_tables(study: Path) -> dict[str, list[str]]:
    """The study's tables (pipelines/study, kept in results/study): every model, blind, per task, the paper's
    claims, the seeds and the closed loop."""

    ev, rp = _load(study / "eval_details.json"), _load(study / "replay_details.json")
    out = {"study": default_table(ev, rp), "study-blind": blind_lines(ev, rp),
           "study-per-task": per_task_lines(ev, rp, grasp_tasks()), "study-claims": claims(ev, rp)}
    if (study / "seeds.json").exists():
        out["study-seeds"] = seeds_lines(_load(study / "seeds.json"))
    if (study / "replay_closed_loop_details.json").exists() and (study / "replay_open_details.json").exists():
        out["study-closed-loop"] = closed_loop_table(_load(study / "replay_open_details.json"),
                                                     _load(study / "replay_closed_loop_details.json"))
    return out


def keep(pipeline: Path, files: dict[str, str], logs: str, into: Path) -> None:
    """Copy a pipeline's files present (its path -> the name kept) and its training logs (a glob under
    metrics/train, kept with their folders) into `into`, every JSON read before any file is copied."""
    present = [k for k in files if (pipeline / k).is_file()]
    for src in present:
        if src.endswith(".json"):
            _load(pipeline / src)
    for src in present:
        with atomic_path(into / files[src]) as tmp:
            shutil.copyfile(pipeline / src, tmp)
    train = pipeline / "metrics" / "train"
    for log in sorted(train.glob(logs)):
        with atomic_path(into / "train" / log.relative_to(train)) as tmp:
            shutil.copyfile(log, tmp)


def save_study(pipeline: Path, results: Path) -> None:
    """Keep the study's details, reports and training logs in RESULTS/study (all readable before any is copied)."""
    required = list(STUDY_FILES)[:2]  # seed 0's evaluation and replay; the seeds and the closed loop may follow
    missing = [k for k in required if not (pipeline / k).is_file()]
    if missing:
        raise AdlError(f"{pipeline}: the study has not finished ({missing[0]} missing); run dvc repro there first")
    keep(pipeline, STUDY_FILES, "*/*.csv", results / "study")


def save_closed_loop(pipeline: Path, results: Path) -> None:
    """Keep the closed-loop pipeline's details, reports and training logs in RESULTS/closed_loop (all readable
    before any is copied)."""
    # any one replay will do: a session may re-run only one lever's stages (the others' kept files stay)
    replays = [k for k in CLOSED_LOOP_FILES if k.startswith("metrics/replay_")]
    if not any((pipeline / k).is_file() for k in replays):
        raise AdlError(f"{pipeline}: the closed loop has not been replayed ({replays[0]} missing); run dvc repro "
                       "there")
    keep(pipeline, CLOSED_LOOP_FILES, "*.csv", results / "closed_loop")


def save_dagger(pipeline: Path, results: Path) -> None:
    """Keep the DAgger rounds' replays, rollout summaries and training logs (the rounds', and round 0's
    closed_loop_*.csv) in RESULTS/closed_loop/dagger."""
    if not any((pipeline / k).is_file() for k in DAGGER_FILES if "replay_dagger_" in k):
        raise AdlError(f"{pipeline}: no DAgger arm has been replayed (metrics/dagger/replay_dagger_*_details.json "
                       "missing); run its stages there")
    keep(pipeline, DAGGER_FILES, "*.csv", results / "closed_loop" / "dagger")


def save_moving_person(pipeline: Path, results: Path) -> None:
    """Keep pipelines/moving_person's replays and training logs in RESULTS/moving_person."""
    first = next(iter(MOVING_PERSON_FILES))
    if not (pipeline / first).is_file():
        raise AdlError(f"{pipeline}: the moving-person trio has not been replayed ({first} missing); run dvc repro "
                       "there")
    keep(pipeline, MOVING_PERSON_FILES, "*.csv", results / "moving_person")


def _block(name: str) -> re.Pattern:
    return re.compile(rf"(<!-- results:{re.escape(name)} -->\n)(.*?)(<!-- /results:{re.escape(name)} -->)", re.S)


def apply(readme: str, generated: dict[str, str]) -> tuple[str, list[str]]:
    """README with every marked table replaced; and the names whose content changed."""
    changed = []
    for name, text in generated.items():
        pat = _block(name)
        m = pat.search(readme)
        if m is None:
            continue  # README does not show this table
        if m.group(2).rstrip("\n") != text:
            changed.append(name)
        readme = readme[:m.start(2)] + text + "\n" + readme[m.end(2):]
    return readme, changed


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.results", __doc__)
    p.add_argument("--results", type=Path, default=Path("results"), help="the committed results (default results/)")
    p.add_argument("--readme", type=Path, default=Path("README.md"))
    p.add_argument("--docs", type=Path, default=Path("docs"), help="the documentation's pages (every .md under it); "
                   "their marked tables are generated too")
    p.add_argument("--check", action="store_true", help="change nothing; exit 1 naming each table that disagrees")
    p.add_argument("--save-from", type=Path, metavar="METRICS",
                   help="first copy a run's details (" + ", ".join(RUN_FILES) + ") into RESULTS/default")
    p.add_argument("--save-seeds", type=Path, metavar="SEEDS_JSON", help="first copy the seeds summary into "
                   "RESULTS/seeds/seeds.json")
    p.add_argument("--save-study", type=Path, metavar="PIPELINE", help="first keep the study's details, reports and "
                   "training logs (pipelines/study) in RESULTS/study")
    p.add_argument("--save-moving-person", type=Path, metavar="PIPELINE", help="first keep the moving-person "
                   "trio's replays and training logs (pipelines/moving_person) in RESULTS/moving_person")
    p.add_argument("--save-closed-loop", type=Path, metavar="PIPELINE", help="first keep the closed-loop pipeline's "
                   "details, reports and training logs (pipelines/closed_loop) in RESULTS/closed_loop")
    p.add_argument("--save-dagger", type=Path, metavar="PIPELINE", help="first keep the DAgger rounds' replays, "
                   "rollouts and training logs (pipelines/closed_loop) in RESULTS/closed_loop/dagger")
    args = p.parse_args(argv)
    if args.save_moving_person is not None:
        save_moving_person(args.save_moving_person, args.results)
    if args.save_study is not None:
        save_study(args.save_study, args.results)
    if args.save_closed_loop is not None:
        save_closed_loop(args.save_closed_loop, args.results)
    if args.save_dagger is not None:
        save_dagger(args.save_dagger, args.results)
    if args.save_from is not None:
        present = [n for n in RUN_FILES if n in RUN_FILES[:2] or (args.save_from / n).exists()]
        for name in present:
            _load(args.save_from / name)  # all readable before any is copied
        stale = args.results / "default" / RUN_FILES[2]
        if RUN_FILES[2] not in present and stale.exists():
            stale.unlink()  # a closed loop of another run must not sit beside this one's figures
        for name in present:
            with atomic_path(args.results / "default" / name) as tmp:
                shutil.copyfile(args.save_from / name, tmp)
    if args.save_seeds is not None:
        _load(args.save_seeds)
        with atomic_path(args.results / "seeds" / "seeds.json") as tmp:
            shutil.copyfile(args.save_seeds, tmp)
    generated = tables(args.results)
    pages = [args.readme] + (sorted(args.docs.rglob("*.md")) if args.docs.is_dir() else [])
    texts = {}
    for page in pages:
        try:
            texts[page] = page.read_text()
        except OSError as exc:
            raise AdlError(f"{page}: cannot read ({exc.strerror})") from None
    missing = [n for n in generated if not any(_block(n).search(t) for t in texts.values())]
    updates = {page: apply(text, generated) for page, text in texts.items()}
    differing = [f"{page}: '{n}'" for page, (_, changed) in updates.items() for n in changed]
    if args.check:
        if differing:
            raise AdlError(f"table(s) {', '.join(differing)} differ from {args.results} (python -m adlpipe.results "
                           "rewrites them)")
        print(f"{', '.join(map(str, texts))}: every table agrees with {args.results}")
        return 0
    for page, (new, changed) in updates.items():
        if changed:
            write_text_atomic(page, new)
            print(f"{page}: {len(changed)} table(s) rewritten ({', '.join(changed)})")
    print(f"{len(differing)} table(s) rewritten" + (f"; shown on no page: {', '.join(missing)}" if missing else ""))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.results", main))
