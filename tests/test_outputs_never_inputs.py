"""No output ever overwrites an input: every stage's output options, pointed at one of its inputs (or at a dataset's
index, its episode files or the split beside it), are refused in one line before any work, and the input is intact."""

from __future__ import annotations

import hashlib
import importlib
from pathlib import Path

import pytest
from conftest import copy_dataset, one_line_error, run_module

from adlpipe.plumbing.errors import run_cli


class Proc:
    def __init__(self, rc: int, stderr: str) -> None:
        self.returncode, self.stderr = rc, stderr


def run_stage(capsys: pytest.CaptureFixture, stage: str, argv: list[str]) -> Proc:
    """The stage through its real entry point (run_cli + main), in this process: the refusal comes before any work."""
    module = importlib.import_module(f"adlpipe.{stage}")
    capsys.readouterr()
    try:
        rc = run_cli(f"adlpipe.{stage}", module.main, argv)
    except SystemExit as exc:
        rc = int(exc.code or 0)
    return Proc(rc, capsys.readouterr().err)


@pytest.fixture(scope="module")
def world(ingested: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("victims")
    data = copy_dataset(ingested, root / "adl.h5")
    run_module("split", data, check=True)
    shards = sorted((root / "adl.shards").rglob("*.h5"))
    (root / "details.json").write_text('{"models": {}, "success": {}}')
    (root / "trials.csv").write_text("policy,success\na,1\nb,0\n")
    (root / "log.csv").write_text("epoch,step\n")
    return {"data": data, "split": root / "split.json", "shard": shards[0], "details": root / "details.json",
            "trials": root / "trials.csv", "log": root / "log.csv", "models": root / "no_model"}


# (stage, its arguments with {names} of the world's files): each names an input, or a dataset, as an output
CASES = [
    ("doctor", "{data} --json {data}"),
    ("doctor", "{data} --png {data}"),
    ("doctor", "{data} --json {split}"),
    ("doctor", "{data} --json {shard}"),
    ("split", "{data} -o {data}"),
    ("evaluate", "--models {models} --data {data} --metrics {data}"),
    ("evaluate", "--models {models} --data {data} --details {split}"),
    ("evaluate", "--models {models} --data {data} --table {shard}"),
    ("inspect", "--dataset --data {data} -o {data}"),
    ("train", "--model fm_cnn --data {data} --log {data}"),
    ("train", "--model fm_cnn --data {data} --log {split}"),
    ("replay", "--models {models} --data {data} --details {split}"),
    ("replay", "--models {models} --data {data} --scenes 1 --until-decided --eval {details} --details {details}"),
    ("rollout", "{models} --data {data} --out {models} --summary {split}"),
    ("rollout", "{models} --data {data} --out {models} --summary {data}"),
    ("report", "--eval {details} --replay {details} -o {details}"),
    ("report", "--eval {details} --replay {details} -o {data}"),
    ("assess", "--models {models} --data {data} --table {split}"),
    ("seeds", "--eval {details} --replay {details} --metrics {details}"),
    ("benchmark", "--compare {details} --table {details}"),
    ("export", "{data} {data}"),
    ("edit", "{data} -o {data} --drop x"),
    ("ingest", "{shard} -o {shard}"),
    ("trials", "{trials} -o {trials}"),
    ("trials", "{trials} -o {data}"),
]


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize(("stage", "argv"), CASES, ids=[f"{s}:{a.split(' -')[-1]}" for s, a in CASES])
def test_an_output_that_names_an_input_is_refused_and_the_input_kept(capsys: pytest.CaptureFixture,
                                                                       world: dict[str, Path], stage: str,
                                                                       argv: str) -> None:
    files = {k: v for k, v in world.items() if v.exists()}
    before = {k: digest(v) for k, v in files.items() if v.is_file()}
    line = one_line_error(run_stage(capsys, stage, argv.format(**world).split()))
    assert ("is an input of this command" in line or "HDF5 file" in line or "episode files" in line), line
    assert {k: digest(v) for k, v in files.items() if v.is_file()} == before
