"""README's result tables are generated from the committed results (results/), and disagree with them never."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from conftest import REPO, one_line_error, run_module

from adlpipe.errors import AdlError
from adlpipe.evaluation.table2 import table2_lines
from adlpipe.results import save_closed_loop


def test_readme_tables_agree_with_the_committed_results() -> None:
    proc = run_module("results", "--check")
    assert proc.returncode == 0, proc.stderr
    pages = "".join(p.read_text() for p in [REPO / "README.md", *(REPO / "docs").rglob("*.md")])
    for name in ("default", "blind", "per-task", "safety", "seeds", "closed-loop-fresh", "moving-person"):
        assert f"<!-- results:{name} -->" in pages, name
    assert "<!-- results:default -->" in (REPO / "README.md").read_text()  # the front page's headline table


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
