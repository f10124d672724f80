"""The numbered examples (examples/0*.py) run as a user runs them, on tiny data: inspect a dataset, train on bags,
evaluate and decide, decide from trials (03 and 06, planning in-process and through a server, are in
test_deploy.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, SMALL, run_module

TASKS = ["wipe the nose", "pass the water"]


def example(name: str, *args: object, cwd: Path = REPO) -> str:
    proc = subprocess.run([sys.executable, str(REPO / "examples" / name), *map(str, args)], capture_output=True,
                          text=True, timeout=600, cwd=cwd, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Bags of two tasks, three each, through examples/02: the dataset, its split and two tiny models."""
    root = tmp_path_factory.mktemp("examples")
    run_module("record", "--episodes", "3", "--tasks", *TASKS, "--out", root / "bags", *SMALL, check=True)
    out = example("02_train_on_your_bags.py", *sorted((root / "bags").glob("*.mcap")), "--work", root / "work",
                  "--size", "64", "--model", "fm_cnn", "bc_cnn", "--epochs", "2")
    assert "fm_cnn: 2 epochs" in out and "bc_cnn: 2 epochs" in out, out
    return root / "work"


def test_inspecting_the_dataset_the_training_example_wrote(trained: Path) -> None:
    out = example("01_inspect_a_dataset.py", trained / "robot.h5")
    assert out.startswith(f"{trained / 'robot.h5'}: 6 episodes, 2 tasks")
    assert "  pass the water: 3\n  wipe the nose: 3\n" in out
    assert "32 waypoints" in out and "with depth" in out


def test_evaluating_and_deciding_replays_fresh_scenes_until_the_cap_or_a_decision(trained: Path,
                                                                                tmp_path: Path) -> None:
    out = example("04_evaluate_and_decide.py", trained / "robot.h5", trained / "fm_cnn", trained / "bc_cnn",
                  "--scenes", "2", "--batch", "1", "--out", tmp_path / "decision")
    assert "demo: success" in out and "fm_cnn/euler-1: success" in out and "bc_cnn: success" in out, out
    last = out.strip().splitlines()[-1]
    assert last.startswith(("decided after", "the cap (2 per task) reached")) and "recommended" in last, last
    assert (tmp_path / "decision" / "table2.md").is_file() and (tmp_path / "decision" / "table1.md").is_file()


def test_deciding_from_the_sample_trials() -> None:
    out = example("05_decide_from_trials.py", REPO / "examples" / "trials.csv")
    assert out.strip().splitlines()[-1] == "status undecided, recommended None, next fm_cnn, after 40 trials"
