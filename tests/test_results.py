"""README's result tables are generated from the committed results (results/), and disagree with them never."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from conftest import REPO, one_line_error, run_module

from adlpipe.evaluation.table2 import table2_lines
from adlpipe.plumbing.errors import AdlError
from adlpipe.results import save_closed_loop


def test_readme_tables_agree_with_the_committed_results() -> None:
    proc = run_module("results", "--check")
    assert proc.returncode == 0, proc.stderr
    pages = "".join(p.read_text() for p in [REPO / "README.md", *(REPO / "docs").rglob("*.md")])
    for name in ("default", "decision", "blind", "per-task", "safety", "seeds", "closed-loop-fresh", "moving-person"):
        assert f"<!-- results:{name} -->" in pages, name
    assert "<!-- results:default -->" in (REPO / "README.md").read_text()  # the front page's headline table


def test_the_decision_paragraph_says_what_the_rule_says_on_the_scenes_it_had() -> None:
    import json

    from adlpipe.evaluation.decision import decide_replay, decision_lines

    ev, rp = (json.loads((REPO / "results" / "default" / f"{n}_details.json").read_text()) for n in ("eval", "replay"))
    got = decide_replay(ev, rp)
    text = " ".join(decision_lines(ev, rp))
    assert got is not None and got["recommended"] == rp["sequential"]["looks"][-1]["recommended"]
    assert f"after {got['n']} scenes" in text and "deploy " in text, text
    # the same run cut to its first look (50 scenes, one per task and batch): what the rule said then
    first = set(sorted(rp["tasks"], key=lambda s: int(s.rsplit("/", 1)[1]))[:50])
    cut = {**rp, "per_episode": {p: {s: v for s, v in o.items() if s in first} for p, o in rp["per_episode"].items()},
           "sequential": {**rp["sequential"], "looks": rp["sequential"]["looks"][:1]}}
    early = decide_replay(ev, cut)
    assert early is not None and early["status"] == rp["sequential"]["looks"][0]["status"]
    if early["recommended"] is None:
        assert " ".join(decision_lines(ev, cut)).startswith("**The default run is undecided** after 50 fresh scenes")


def test_a_changed_figure_is_caught_and_rewritten(tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    text = (REPO / "README.md").read_text()
    start = text.index("<!-- results:default -->")
    row = text.index("| FM-CNN, x1 output, 1 Euler step |", start)
    cell = text.index("|", row + 3) + 2  # the px cell of FM-1
    readme.write_text(text[:cell] + "9" + text[cell + 1:])
    proc = run_module("results", "--check", "--readme", readme, "--results", REPO / "results")
    assert "README.md: 'default'" in one_line_error(proc)
    run_module("results", "--readme", readme, "--results", REPO / "results", check=True)
    assert readme.read_text() == text


def test_save_from_a_run_missing_a_file_copies_nothing(tmp_path: Path) -> None:
    run = tmp_path / "metrics"
    run.mkdir()
    shutil.copy(REPO / "results" / "default" / "eval_details.json", run)
    results = tmp_path / "results"
    proc = run_module("results", "--save-from", run, "--results", results, "--readme", tmp_path / "none.md")
    assert proc.returncode != 0 and "replay_details.json" in one_line_error(proc)
    assert not results.exists()


def test_save_closed_loop_before_its_replay_copies_nothing(tmp_path: Path) -> None:
    pipeline = tmp_path / "closed_loop"
    (pipeline / "metrics").mkdir(parents=True)
    results = tmp_path / "results"
    proc = run_module("results", "--save-closed-loop", pipeline, "--results", results, "--readme",
                      tmp_path / "none.md")
    assert proc.returncode != 0 and "replay_closed_loop_details.json missing" in one_line_error(proc)
    assert not results.exists()


def test_save_closed_loop_keeps_one_levers_replay_alone(tmp_path: Path) -> None:
    """A session that re-runs only one lever's stages keeps that replay; nothing else is written or required."""
    pipeline = tmp_path / "closed_loop"
    (pipeline / "metrics").mkdir(parents=True)
    details = REPO / "results" / "closed_loop" / "replay_closed_loop_details.json"
    shutil.copy(details, pipeline / "metrics" / "replay_recoveries_details.json")
    results = tmp_path / "results"
    save_closed_loop(pipeline, results)  # what --save-closed-loop does before it rewrites the tables
    kept = sorted(p.name for p in (results / "closed_loop").iterdir())
    assert kept == ["replay_recoveries_details.json"]
    assert (results / "closed_loop" / kept[0]).read_bytes() == details.read_bytes()


def test_table2_puts_the_final_checkpoint_beside_the_best_ones() -> None:
    lines = table2_lines(REPO / "pipelines")
    fm = next(r for r in lines if r.startswith("| Push-T | FM-CNN |"))
    # pusht_levers_long: the final checkpoint on 500 initial conditions, the best along training on 50
    assert "**0.896 [0.879, 0.911]** (0.845), 500 initial conditions" in fm
    assert "0.908 (13,302) / 0.900 (50 initial conditions each)" in fm and fm.endswith("| yes |")
    kitchen = [r for r in lines if r.startswith("| Franka Kitchen | FM-CNN |")]
    assert "| 58,140 |" in kitchen[0] and "0.823 [0.775, 0.868]" in kitchen[0] and kitchen[0].endswith("| no |")


def test_table2_waits_for_a_run_not_committed_and_names_a_broken_one(tmp_path: Path) -> None:
    assert table2_lines(tmp_path) == []  # no benchmark pipeline's results: no table, no error
    folder = tmp_path / "kitchen_levers" / "results"
    shutil.copytree(REPO / "pipelines" / "kitchen_levers" / "results", folder,
                    ignore=shutil.ignore_patterns("kitchen_e60*"))
    assert [r.split(" | ")[1] for r in table2_lines(tmp_path)[2:]] == ["FM-CNN", "DP-CNN (sample)"]
    (folder / "kitchen_long_details.json").write_text("{")
    with pytest.raises(AdlError, match="kitchen_long_details.json: not a benchmark details file"):
        table2_lines(tmp_path)


def test_the_dagger_table_pairs_each_arm_with_the_one_before_and_with_open_loop() -> None:
    from adlpipe.evaluation.dagger import dagger_lines

    scenes = [f"fresh/t/{i}" for i in range(20)]
    fm, ol = "fm_cnn/euler-1/Ta-8", "fm_cnn/euler-1"

    def arm(solved: int, off: int) -> dict:
        diag = {s: {"replans": 4, "replans_off_path": off, "plan_ratio_off_path": 0.5, "peak_force_n": 5.0 + i}
                for i, s in enumerate(scenes)}
        return {"per_episode": {fm: {s: i < solved for i, s in enumerate(scenes)}}, "diagnostics": {fm: diag},
                "training": {"fm_cnn": {"converged": True}}}

    open_loop = {"per_episode": {ol: {s: i < 10 for i, s in enumerate(scenes)}}}
    rollouts = {"dagger_rollout_r1_fm_cnn": {"plans": 880}}
    lines = dagger_lines({"r0": arm(4, 2), "r1": arm(12, 1)}, open_loop, rollouts)
    r0, r1 = (ln for ln in lines if ln.startswith("| FM-1 |"))
    assert "| round 0: the demonstrations | 0 | 20 [8, 42] | - | -30.0 (p = 0.03) | 50 % |" in r0  # 0 : 6
    # round 1 solves the 4 scenes round 0 did and 8 more: +40 points, McNemar 8 : 0, p = 2 / 2^8
    assert "| DAgger round 1 | 880 re-plans (expert) | 60 [39, 78] | +40.0 (p = 0.01) | +10.0 (p = 0.50) | 25 % |" in r1
    assert r1.endswith("| 0.50 | 4 (max 24 N) | yes |")  # peaks 5-24 N: 4 over 20 N


def test_the_dagger_fit_table_reads_each_set_on_and_off_the_path() -> None:
    from adlpipe.evaluation.dagger import fit_lines

    def fit(demo: float, on: float, off: float) -> dict:
        return {"demo_test": {"error_cm": demo},
                "rollouts_r1": {"error_on_path_cm": on, "error_off_path_cm": off},
                "rollouts_r2": {"error_on_path_cm": on + 1, "error_off_path_cm": off + 1,
                                "plan_over_label_length": {"on": 1.0, "off": 0.645}}}

    fits = {"dp_cnn": {"per_episode": 12, "sets": {"demo_test": 40, "rollouts_r1": 160},
                       "round 0": fit(2.55, 5.04, 11.04), "DAgger round 1": fit(3.67, 3.93, 5.06)}}
    lines = fit_lines(fits)
    rows = [ln for ln in lines if ln.startswith("| DP-16 |")]
    assert rows[0] == "| DP-16 | round 0 | demonstrations | 2.5 | 5.0 / 11.0 | 6.0 / 12.0 | 0.65 |"
    assert rows[1].startswith("| DP-16 | DAgger round 1 | + round 1's rollouts | 3.7 | 3.9 / 5.1 |")
    assert "12 evenly spaced frames of every episode (40 test demonstrations" in lines[-1]
    assert fit_lines({"dp_cnn": {"per_episode": 12, "sets": {}}}) == []


def _default_figures() -> dict[str, str]:
    """The figures the prose around the default run's tables quotes, from results/default as committed."""
    import csv
    import json

    run = REPO / "results" / "default"
    rp = json.loads((run / "replay_details.json").read_text())
    n = len(rp["tasks"])
    rate = {p: f"{100 * sum(v.values()) / len(v):.1f}" for p, v in rp["per_episode"].items()}
    force = {p: [d.get("peak_force_n", 0.0) for d in v.values()] for p, v in rp["diagnostics"].items()}
    unsafe = {p: sum(f > 20 for f in v) for p, v in force.items()}
    peak = {p: f"{max(v):.1f}" for p, v in force.items()}
    best = {}
    for model in ("fm_cnn", "dp_cnn", "bc_cnn"):
        with open(run / "train" / f"{model}.csv") as f:
            rows = [r for r in csv.DictReader(f) if r["val_px"]]
        best[model] = min(rows, key=lambda r: float(r["val_px"]))["epoch"]
    demo = json.loads((REPO / "results" / "bench" / "demo_side_by_side.json").read_text())["runs"][0]["make_demo"]
    fm, dp, bc = "fm_cnn/euler-1", "dp_cnn/ddpm-16", "bc_cnn"
    return {
        "decided": f"this run was decided at **{n} scenes**",
        "epochs": f"best epochs FM {best['fm_cnn']}, DP {best['dp_cnn']}, BC {best['bc_cnn']} of 800",
        "success": f"FM-1 {rate[fm]} %, DP-16 {rate[dp]} %, BC {rate[bc]} % against blind's {rate['blind']} % on the "
                   f"same {n} scenes",
        "forces": f"FM-1 in {unsafe[fm]} of {n} scenes (peak {peak[fm]} N), BC {unsafe[bc]} ({peak[bc]} N), DP-16 "
                  f"{unsafe[dp]} ({peak[dp]} N), blind {unsafe['blind']}",
        "demo": f"`make demo` **{demo // 60} min {demo % 60} s**",
    }


def test_the_prose_around_the_default_tables_quotes_the_committed_run() -> None:
    """Hand-written sentences that quote results/default (the tables and the decision are generated): each figure
    as the committed run has it, so a re-run that changes one fails here until the prose is rewritten."""
    page = " ".join((REPO / "docs" / "science" / "default-results.md").read_text().split())
    for name, quote in _default_figures().items():
        assert quote in page, (name, quote)
