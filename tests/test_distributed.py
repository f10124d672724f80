"""Training on several processes (torchrun, DDP over gloo on the CPU) against one process with the same global
batch, DataLoader workers against none, and resuming across the two."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from adlpipe.policy.checkpoint import load_checkpoint
from adlpipe.policy.models import ModelConfig, preset
from adlpipe.training.loop import train

TINY = dict(image_size=32, encoder_width=8, obs_dim=16, down_dims=(16, 32, 64), d_model=32, n_layers=1, n_heads=2)
# Measured: 2 processes and 1 agree to 1e-7 relative (the gradient average differs from the global mean only in
# the order of the sums); the tolerance leaves room for other CPUs' kernels.
REL_TOL = 1e-4


@pytest.fixture(scope="module")
def four(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Four episodes of two tasks, all in the train split (an even count: no sample is repeated to fill a share)."""
    from conftest import SMALL, run_module

    root = tmp_path_factory.mktemp("ddp")
    run_module("record", "--episodes", "2", "--tasks", "wipe the nose", "pass the water", "--out", root / "bags",
               *SMALL, check=True)
    run_module("ingest", *sorted((root / "bags").glob("*.mcap")), "-o", root / "adl.h5", "--size", "64",
               check=True)
    run_module("split", root / "adl.h5", "-o", root / "all.json", check=True)
    s = json.loads((root / "all.json").read_text())
    names = sorted(s["train"] + s["test"])
    assert len(names) == 4
    (root / "split.json").write_text(json.dumps({"train": names, "test": []}))
    return root / "adl.h5", root / "split.json"


def torchrun(*args: object) -> None:
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "adlpipe.train", *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]


def losses(log: Path) -> list[float]:
    with open(log) as f:
        return [float(r["train_loss"]) for r in csv.DictReader(f)]


COMMON = ["--model", "fm_cnn", "--epochs", "4", "--batch-size", "2", "--val-fraction", "0", "--warmup-steps", "2",
          "--threads", "1", "--device", "cpu", "--seed", "3"]


def test_two_gloo_processes_train_as_one_with_the_same_global_batch(four: tuple[Path, Path], tmp_path: Path) -> None:
    from conftest import run_module

    data, split = four
    run_module("train", *COMMON, "--data", data, "--split", split, "--out", tmp_path / "one", check=True)
    torchrun(*COMMON, "--data", data, "--split", split, "--out", tmp_path / "two")
    one, two = losses(tmp_path / "one" / "log.csv"), losses(tmp_path / "two" / "log.csv")
    assert len(one) == len(two) == 4
    assert two == pytest.approx(one, rel=REL_TOL)
    assert one[-1] < one[0]  # it trained: a history of equal constants would match too
    m = json.loads((tmp_path / "two" / "metrics.json").read_text())
    assert m["processes"] == 2 and m["optimizer_steps"] == 8  # 4 samples in global batches of 2, 4 epochs
    a = load_checkpoint(tmp_path / "one" / "model.pt")["ema"]
    b = load_checkpoint(tmp_path / "two" / "model.pt")["ema"]
    diff = sum(float((a[k] - b[k]).float().norm() ** 2) for k in a) ** 0.5
    norm = sum(float(a[k].float().norm() ** 2) for k in a) ** 0.5
    print(f"weights: |two - one| / |one| = {diff / norm:.2e}")
    assert diff < 1e-3 * norm  # the gradients were synchronised (measured 1.8e-5: Adam's division by small second
    #                             moments lifts the float rounding of the sums)


def test_a_run_resumes_on_another_number_of_processes_where_it_stopped(four: tuple[Path, Path],
                                                                       tmp_path: Path) -> None:
    data, split = four
    cfg = preset("small", "dp_cnn", horizon=32)  # what the command line below configures
    kw = dict(epochs=4, batch_size=2, lr=1e-3, warmup_steps=2, seed=3, val_fraction=0.0)
    full = train(data, split, tmp_path / "a", cfg, **kw)
    assert train(data, split, tmp_path / "b", cfg, stop_after_epoch=2, **kw) == {"interrupted_at": 2}
    assert load_checkpoint(tmp_path / "b" / "last.pt")["epoch"] == 2
    torchrun("--model", "dp_cnn", "--data", data, "--split", split, "--out", tmp_path / "b", "--epochs", "4",
             "--batch-size", "2", "--lr", "1e-3", "--warmup-steps", "2", "--seed", "3", "--val-fraction", "0",
             "--threads", "1", "--device", "cpu")  # the last two epochs on two processes
    resumed = load_checkpoint(tmp_path / "b" / "model.pt")
    assert [r["train_loss"] for r in resumed["history"]] == pytest.approx(
        [r["train_loss"] for r in load_checkpoint(tmp_path / "a" / "model.pt")["history"]], rel=REL_TOL)
    assert resumed["history"][-1]["train_loss"] == pytest.approx(full["train_loss"], rel=REL_TOL)


def test_validation_px_carries_its_interval_over_validation_episodes(four: tuple[Path, Path],
                                                                     tmp_path: Path) -> None:
    """The val px that selects checkpoints is a mean over a handful of episodes: training keeps its bootstrap
    interval at the best and the last validation, and the training log keeps its plain columns."""
    data, split = four
    m = train(data, split, tmp_path / "m", ModelConfig(model="fm_cnn", **TINY), epochs=2, batch_size=2,
              val_fraction=0.5, val_every=1, log_csv=tmp_path / "log.csv")
    assert m["val_episodes"] == 2
    for key in ("val_px_best", "val_px_last"):
        lo, hi = m[f"{key}_ci"]
        assert lo <= m[key] <= hi and lo < hi, key  # two episodes never score the same to the last digit
    assert (tmp_path / "log.csv").read_text().splitlines()[0] == "epoch,step,train_loss,test_loss,val_px,lr,seconds"


def test_loader_workers_change_nothing_but_speed(four: tuple[Path, Path], tmp_path: Path) -> None:
    """One persistent DataLoader with 2 worker processes yields the same batches (windows, augmentation, noise)
    as loading in the training process: the epoch travels with each index."""
    data, split = four
    cfg = ModelConfig(model="fm_cnn", n_obs=2, horizon=16, rate_hz=10.0, state_dim=8, target="command", **TINY)
    kw = dict(epochs=3, batch_size=2, lr=1e-3, warmup_steps=2, seed=1, val_fraction=0.0)
    a = train(data, split, tmp_path / "a", cfg, workers=0, **kw)
    b = train(data, split, tmp_path / "b", cfg, workers=2, **kw)
    ha = [r["train_loss"] for r in load_checkpoint(tmp_path / "a" / "model.pt")["history"]]
    hb = [r["train_loss"] for r in load_checkpoint(tmp_path / "b" / "model.pt")["history"]]
    assert ha == pytest.approx(hb, rel=1e-6) and len(set(ha)) == 3
    assert a["train_loss"] == pytest.approx(b["train_loss"], rel=1e-6)


def test_first_frames_are_cached_only_while_they_fit(four: tuple[Path, Path]) -> None:
    """A paper-size set (224 px) of 400 episodes would be 321 MB per worker: read every time instead."""
    from adlpipe.dataset.loader import MAX_CACHED_BYTES, TrajectoryDataset

    data, split = four
    name = json.loads(split.read_text())["train"][0]
    stats = {"min": [0.0] * 5, "max": [1.0] * 5}
    assert 400 * 4 * 224 * 224 * 4 > MAX_CACHED_BYTES
    assert not TrajectoryDataset(str(data), [name] * 400, stats, 224).cache
    small = TrajectoryDataset(str(data), [name] * 10, stats, 224)
    assert small.cache
    small[0]
    assert 0 in small._items  # kept after the first read


def test_a_run_stopped_when_converged_is_the_capped_run_cut_at_the_rule(four: tuple[Path, Path],
                                                                       tmp_path: Path) -> None:
    """--stop-when-converged: the run stops at the first validation from the floor on at which the 2 % rule holds
    on its history so far, until then epoch for epoch the capped run (the schedule stays the cap's); two processes
    stop together (rank 0 validates, every process leaves the loop)."""
    from adlpipe.evaluation.training_log import converged

    data, split = four
    cfg = preset("small", "fm_cnn", horizon=32)  # what the command line below configures
    kw = dict(epochs=12, batch_size=2, lr=1e-7, warmup_steps=2, seed=3, val_fraction=0.5, val_every=2)
    train(data, split, tmp_path / "a", cfg, **kw)
    full = load_checkpoint(tmp_path / "a" / "model.pt")["history"]
    expected = next((r["epoch"] for r in full if r["epoch"] >= 4 and r["val_px"] is not None
                     and converged(full[:r["epoch"]])), 12)
    assert expected < 12  # at this learning rate val px stays flat, so the rule holds early
    m = train(data, split, tmp_path / "b", cfg, stop_floor=4, **kw)
    stopped = load_checkpoint(tmp_path / "b" / "model.pt")["history"]
    assert m["epochs"] == m["stopped_converged_at"] == expected == len(stopped) and m["converged"]
    assert [r["train_loss"] for r in stopped] == [r["train_loss"] for r in full[:expected]]
    torchrun("--model", "fm_cnn", "--data", data, "--split", split, "--out", tmp_path / "c", "--epochs", "12",
             "--batch-size", "2", "--lr", "1e-7", "--warmup-steps", "2", "--seed", "3", "--val-fraction", "0.5",
             "--val-every", "2", "--stop-when-converged", "4", "--threads", "1", "--device", "cpu")
    assert len(load_checkpoint(tmp_path / "c" / "model.pt")["history"]) == expected
