"""A training never deletes what it did not write: its --resume-dir holds only its own checkpoints, is refused in
one line when it holds anything else (a user's file, the dataset, the output), and a finished run removes what it
wrote there file by file. A stale checkpoint of another model in it is refused, as in --out."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import copy_dataset, one_line_error, run_module

TINY = ["--model", "fm_cnn", "--epochs", "1", "--batch-size", "3", "--val-fraction", "0"]


@pytest.fixture()
def data(ingested: Path, tmp_path: Path) -> tuple[Path, Path]:
    (tmp_path / "ds").mkdir()
    d = copy_dataset(ingested, tmp_path / "ds" / "adl.h5")
    split = tmp_path / "ds" / "split.json"
    run_module("split", d, "-o", split, check=True)  # 3 episodes, one per task: all train
    return d, split


def train(data: tuple[Path, Path], *extra: object) -> object:
    return run_module("train", *TINY, "--data", data[0], "--split", data[1], *extra)


def test_a_finished_run_removes_its_own_files_and_keeps_a_users(data: tuple[Path, Path], tmp_path: Path) -> None:
    resume = tmp_path / "resume"
    proc = train(data, "--out", tmp_path / "m", "--resume-dir", resume)
    assert proc.returncode == 0, proc.stderr
    assert {p.name for p in (tmp_path / "m").iterdir()} >= {"model.pt", "best.pt"}
    assert not resume.exists()  # it held only what training wrote: gone with it
    resume.mkdir()
    (resume / "notes.txt").write_text("mine")
    err = one_line_error(train(data, "--out", tmp_path / "m2", "--resume-dir", resume))
    assert "holds notes.txt, which training did not write" in err
    assert (resume / "notes.txt").read_text() == "mine" and not (tmp_path / "m2" / "model.pt").exists()


@pytest.mark.parametrize("where", ["dataset", "output"])
def test_a_resume_folder_holding_the_dataset_or_the_output_is_refused(data: tuple[Path, Path], tmp_path: Path,
                                                                       where: str) -> None:
    if where == "dataset":
        out, resume, holds = tmp_path / "m", data[0].parent, "holds an input"
    else:
        out, resume, holds = tmp_path / "runs" / "o", tmp_path / "runs", "holds the output"
        out.mkdir(parents=True)
    before = sorted(p.name for p in resume.rglob("*"))
    assert holds in one_line_error(train(data, "--out", out, "--resume-dir", resume))
    assert sorted(p.name for p in resume.rglob("*")) == before


def test_another_models_checkpoint_in_a_resume_folder_is_refused(data: tuple[Path, Path], tmp_path: Path) -> None:
    from adlpipe.policy.models import ModelConfig
    from adlpipe.training.loop import train as train_loop

    resume = tmp_path / "resume"  # a bc_cnn run killed after its first epoch left its checkpoint here
    cfg = ModelConfig(model="bc_cnn", image_size=32, encoder_width=8, down_dims=(16, 32, 64), obs_dim=16)
    assert train_loop(data[0], data[1], tmp_path / "bc", cfg, epochs=2, batch_size=3, val_fraction=0,
                      stop_after_epoch=1, resume_dir=resume) == {"interrupted_at": 1}
    assert (resume / "last.pt").exists()
    err = one_line_error(train(data, "--out", tmp_path / "fm", "--resume-dir", resume))
    assert "a checkpoint of another model (bc_cnn, not fm_cnn)" in err
    assert (resume / "last.pt").exists()
    assert train(data, "--out", tmp_path / "fm", "--resume-dir", resume, "--restart").returncode == 0
    assert json.loads((tmp_path / "fm" / "metrics.json").read_text())["epochs"] == 1


@pytest.mark.parametrize("content", [[1, 2, 3], "a tensor"])
def test_a_last_checkpoint_that_is_not_one_is_one_line(data: tuple[Path, Path], tmp_path: Path,
                                                       content: object) -> None:
    import torch

    (tmp_path / "m").mkdir()
    torch.save(torch.zeros(3) if content == "a tensor" else content, tmp_path / "m" / "last.pt")
    err = one_line_error(train(data, "--out", tmp_path / "m"))
    assert "last.pt: not a training checkpoint adlpipe wrote" in err
