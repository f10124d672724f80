"""Shared fixtures: real bags recorded once per test session with the MuJoCo recorder (small and fast)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
REPO = Path(__file__).resolve().parents[1]
# Real bags of other projects, used as outside input and never copied here: ADLPIPE_PUBLIC_BAGS names their folder,
# else ../shared/fixtures/public-bags beside the clone; tests that need them skip (with the reason) when absent.
PUBLIC_BAGS = Path(os.environ.get("ADLPIPE_PUBLIC_BAGS") or REPO.parent / "shared" / "fixtures" / "public-bags")


def public_bag(name: str) -> Path:
    """A public fixture bag, or a skip naming where it was looked for."""
    path = PUBLIC_BAGS / name
    if not path.exists():
        pytest.skip(f"public fixture bag {name} not found in {PUBLIC_BAGS} (set ADLPIPE_PUBLIC_BAGS to its folder)")
    return path
SMALL = ["--size", "64", "--camera-hz", "5"]


def run_module(module: str, *args: str, check: bool = False, timeout: float = 600,
               cwd: Path = REPO) -> subprocess.CompletedProcess:
    """Run `python -m adlpipe.<module>` as a user would (in `cwd`, the repository by default); returns the completed
    process (text output)."""
    proc = subprocess.run([sys.executable, "-m", f"adlpipe.{module}", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, cwd=cwd)
    if check and proc.returncode != 0:
        raise AssertionError(f"adlpipe.{module} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return proc


def record_seeded_world(root: Path, world: str, episodes: int, size: int, test_fraction: float) -> Path:
    """A seeded benchmark world's demonstrations (initial conditions 0..episodes-1) recorded, ingested with
    pipelines/<world>/topics.yaml into root/<world>.h5 and split into root/split.json; what record printed is kept
    in root/record.txt."""
    proc = run_module("record", "--world", world, "--episodes", episodes, "--size", size, "--out", root / "bags",
                      check=True)
    (root / "record.txt").write_text(proc.stdout)
    run_module("ingest", *sorted((root / "bags").glob("*.mcap")), "-o", root / f"{world}.h5", "--size", size,
               "--config", REPO / "pipelines" / world / "topics.yaml", check=True)
    run_module("split", root / f"{world}.h5", "-o", root / "split.json", "--test-fraction", test_fraction,
               check=True)
    return root


@pytest.fixture(scope="session")
def mcap_bags(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """One ROS2 MCAP episode of each of three tasks (64x64 camera at 5 Hz)."""
    out = tmp_path_factory.mktemp("bags")
    run_module("record", "--episodes", "1", "--tasks", "wipe the nose", "pass the water", "cover the food",
               "--out", out, *SMALL, check=True)
    bags = sorted(out.glob("*.mcap"))
    assert len(bags) == 3
    return bags


@pytest.fixture(scope="session")
def ingested(mcap_bags: list[Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("h5") / "adl.h5"
    run_module("ingest", *mcap_bags, "-o", out, "--size", "64", check=True)
    return out


@pytest.fixture(scope="session")
def closed_loop_model(ingested: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(split with every episode in test, a tiny closed-loop FM trained for one epoch on the command stream): the
    model gives the oracle its format (horizon, rate, statistics)."""
    import h5py

    from adlpipe.dataset import schema

    root = tmp_path_factory.mktemp("closed_loop")
    with h5py.File(ingested) as f:
        names = schema.episode_names(f)
    train, split = root / "train.json", root / "split.json"
    train.write_text(json.dumps({"train": names, "test": [], "seed": 0, "test_fraction": 0.0}))
    split.write_text(json.dumps({"train": [], "test": names, "seed": 0, "test_fraction": 1.0}))
    run_module("train", "--model", "fm_cnn", "--closed-loop", "--data", ingested, "--split", train, "--out",
               root / "fm", "--epochs", "1", "--batch-size", "3", "--val-fraction", "0", check=True)
    return split, root / "fm"


def copy_dataset(src: Path, dst: Path) -> Path:
    """Copy a dataset: its index and the folder of episode files it links to (kept under the same name beside the
    copy, as the links are relative)."""
    shards = src.with_name(src.stem + ".shards")
    shutil.copy2(src, dst)
    if shards.exists() and not (dst.parent / shards.name).exists():
        shutil.copytree(shards, dst.parent / shards.name)
    return dst


def one_line_error(proc: subprocess.CompletedProcess) -> str:
    """The error a CLI printed: exactly one line, no traceback."""
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert ": error: " in lines[0]
    return lines[0]
