"""The core install (no extras: no torch, mujoco, rerun or dvc) ingests, splits, examines and exports real bags; a
stage that needs an extra says which one in one line. The missing packages are made unimportable for the command's
process, so this checks what a core-only environment imports, not what this test's environment happens to lack."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from conftest import REPO, one_line_error

BLOCKED = {"torch": "train", "mujoco": "sim", "rerun": "viz", "dvc": "pipeline"}  # import name: its extra

RUN_WITHOUT_EXTRAS = f"""
import importlib.abc, sys
class NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {sorted(BLOCKED)!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, NotInstalled())
from adlpipe.console import main
code = main(sys.argv[1:])
leaked = sorted(m for m in sys.modules if m.split(".")[0] in {sorted(BLOCKED)!r})
assert not leaked, leaked
sys.exit(code)
"""


def core(*args: object) -> subprocess.CompletedProcess:
    """`adlpipe <args>` in a process where the extras' packages are not installed."""
    return subprocess.run([sys.executable, "-c", RUN_WITHOUT_EXTRAS, *map(str, args)], capture_output=True, text=True,
                          timeout=600, cwd=REPO)


def test_the_extras_hold_what_the_core_does_without() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    names = {d.split(">")[0].split("=")[0].split("<")[0].split("[")[0].strip() for d in project["dependencies"]}
    dist = {"torch": "torch", "mujoco": "mujoco", "rerun": "rerun-sdk", "dvc": "dvc"}
    assert not names & set(dist.values()), names  # the core installs none of them
    extras = project["optional-dependencies"]
    for module, extra in BLOCKED.items():
        assert any(d.startswith(dist[module]) for d in extras[extra]), (extra, extras[extra])
    assert extras["all"] == ["adlpipe[" + ",".join(sorted(set(BLOCKED.values()))) + "]"]


def test_the_core_ingests_splits_examines_and_exports(mcap_bags: list[Path], tmp_path: Path) -> None:
    data = tmp_path / "adl.h5"
    for args in (("ingest", *mcap_bags, "-o", data, "--size", "64"),
                 ("split", data, "-o", tmp_path / "split.json", "--test-fraction", "0.34"),
                 ("doctor", data, "--json", tmp_path / "doctor.json"),
                 ("doctor", data, "--verify", *mcap_bags),
                 ("export", "--format", "lerobot", data, tmp_path / "lerobot")):
        proc = core(*args)
        assert proc.returncode == 0, f"{args[0]}: {proc.stderr}"
    assert len(json.loads((tmp_path / "doctor.json").read_text())["episodes"]) == 3
    info = json.loads((tmp_path / "lerobot" / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 3


@pytest.mark.parametrize(("stage", "extra"), [("train", "train"), ("record", "sim"), ("inspect", "viz")])
def test_a_stage_that_needs_an_extra_names_it(stage: str, extra: str, tmp_path: Path, ingested: Path) -> None:
    args = {"train": ("--model", "fm_cnn", "--data", ingested, "--out", tmp_path / "m", "--epochs", "1"),
            "record": ("--out", tmp_path / "bags", "--episodes", "1"),
            "inspect": (ingested, "--out", tmp_path / "x.rrd")}[stage]
    line = one_line_error(core(stage, *args))
    assert f"pip install 'adlpipe[{extra}]'" in line, line
    assert not (tmp_path / "m").exists() and not (tmp_path / "bags").exists()
