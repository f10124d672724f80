"""Ingest across machines: disjoint shares of the bags (--shard I/N) written side by side, linked by --gather; the
worked Dask example on a local cluster of 2 worker processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from adlpipe.dataset import schema, shards
from adlpipe.ingest import share_of

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def six_bags(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    from conftest import SMALL, run_module

    out = tmp_path_factory.mktemp("bags6")
    run_module("record", "--episodes", "2", "--tasks", "wipe the nose", "pass the water", "cover the food", "--out",
               out, *SMALL, check=True)
    return sorted(out.glob("*.mcap"))


def catalog(index: Path) -> dict[str, str]:
    with h5py.File(index, "r") as f:
        return {r["key"]: r["name"] for r in schema.read_catalog(f)}


def test_shares_are_disjoint_and_cover_every_bag_in_any_order() -> None:
    bags = [Path(f"b{i}.mcap") for i in range(10)]
    parts = [share_of(bags, (i, 3)) for i in (1, 2, 3)]
    assert sorted(b for p in parts for b in p) == bags
    assert [len(p) for p in parts] == [4, 3, 3]
    assert share_of(list(reversed(bags)), (2, 3)) == parts[1]


def test_shares_written_at_once_and_gathered_equal_one_ingest(six_bags: list[Path], tmp_path: Path) -> None:
    from conftest import run_module

    one = tmp_path / "one" / "adl.h5"
    run_module("ingest", *six_bags, "-o", one, "--size", "64", check=True)
    out = tmp_path / "sharded" / "adl.h5"
    procs = [subprocess.Popen([sys.executable, "-m", "adlpipe.ingest", *map(str, six_bags), "-o", str(out),
                               "--size", "64", "--workers", "1", "--shard", f"{i}/3"], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in (1, 2, 3)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    assert all("2 episode(s) added into share" in o for o, _ in outs)
    assert not out.exists()  # the shares leave the index to --gather
    proc = run_module("ingest", "--gather", "-o", out, check=True)
    assert "6 episode(s) linked from 3 share(s)" in proc.stdout
    assert catalog(out) == catalog(one)
    with schema.open_dataset(out) as f:
        for name in schema.episode_names(f):
            assert schema.read_episode(f, name).rgb.shape == (64, 64, 3)
    # gathering again adds nothing; a share of bags the dataset has already adds nothing and leaves no folder
    run_module("ingest", *six_bags, "-o", out, "--size", "64", "--shard", "1/1", check=True)
    assert "0 episode(s) linked" in run_module("ingest", "--gather", "-o", out, check=True).stdout
    assert len([d for d in shards.shards_dir(out).iterdir()]) == 3


def test_gather_refuses_shares_of_other_settings(six_bags: list[Path], tmp_path: Path) -> None:
    from conftest import one_line_error, run_module

    out = tmp_path / "adl.h5"
    run_module("ingest", *six_bags[:3], "-o", out, "--size", "64", "--shard", "1/1", check=True)
    run_module("ingest", *six_bags[3:], "-o", out, "--size", "32", "--shard", "1/1", check=True)
    line = one_line_error(run_module("ingest", "--gather", "-o", out))
    assert "ingest every share with the same --waypoints and --size" in line
    assert not out.exists()


def test_the_dask_example_ingests_on_two_local_workers(six_bags: list[Path], tmp_path: Path) -> None:
    pytest.importorskip("dask.distributed")
    out = tmp_path / "adl.h5"
    proc = subprocess.run([sys.executable, str(REPO / "examples" / "ingest_with_dask.py"), *map(str, six_bags),
                           "-o", str(out), "--shares", "4", "--local-workers", "2", "--", "--size", "64"],
                          capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "6 episode(s) linked from 4 share(s)" in proc.stdout
    assert len(catalog(out)) == 6
    folders = [d.name for d in shards.shards_dir(out).iterdir()]
    assert sorted(n[:18] for n in folders) == [f"share-000{i}-of-0004" for i in range(1, 5)]
    assert json.loads((shards.shards_dir(out) / sorted(folders)[0] / "catalog.json").read_text())["image_size"] == 64
