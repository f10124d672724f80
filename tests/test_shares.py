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


def test_an_index_whose_catalog_and_links_disagree_loses_nothing(six_bags: list[Path], tmp_path: Path) -> None:
    """Two runs; the index's catalog is rewritten to name the first run's files for the second run's episodes too
    (the links still point into the second run). An append must not decide which is right by deleting a folder:
    one line, nothing changed."""
    from conftest import one_line_error, run_module

    out = tmp_path / "adl.h5"
    run_module("ingest", *six_bags[:2], "-o", out, "--size", "64", check=True)
    run_module("ingest", *six_bags[2:4], "-o", out, "--size", "64", check=True)
    runs = sorted(d.name for d in shards.shards_dir(out).iterdir())
    assert len(runs) == 2
    with h5py.File(out, "a") as f:
        files = f[schema.CATALOG]["file"]
        files[...] = [v.decode().replace(runs[1], runs[0]) for v in files[()]]
    before = out.read_bytes()
    line = one_line_error(run_module("ingest", *six_bags[4:], "-o", out, "--size", "64"))
    assert "the catalog names" in line and "but the index links" in line and "nothing was changed" in line, line
    assert sorted(d.name for d in shards.shards_dir(out).iterdir()) == runs and out.read_bytes() == before
    assert all(len(list((shards.shards_dir(out) / r).glob("*.h5"))) == 2 for r in runs)


def test_gather_leaves_a_share_that_is_still_being_written(six_bags: list[Path], tmp_path: Path) -> None:
    """--gather links the finished shares and leaves the hidden folder of a share whose process still runs (a
    live process of this machine, by the pid in the folder's name) and of a share of another machine; a killed
    share's folder and its stale lock file are removed."""
    import socket

    from conftest import run_module

    out = tmp_path / "adl.h5"
    run_module("ingest", *six_bags[:3], "-o", out, "--size", "64", "--shard", "1/2", check=True)
    host = "".join(c if c.isalnum() else "_" for c in socket.gethostname())[:40]
    live = subprocess.Popen(["sleep", "60"])
    dead = subprocess.Popen(["true"])
    dead.wait()
    root = shards.shards_dir(out)
    folders = {"live": root / f".share-0002-of-0002-20261201-000000-{host}-{live.pid}.tmp",
               "dead": root / f".share-0002-of-0002-20261201-000001-{host}-{dead.pid}.tmp",
               "elsewhere": root / f".share-0002-of-0002-20261201-000002-otherhost-{dead.pid}.tmp"}
    for d in folders.values():
        d.mkdir()
        (d / "000000.h5").write_bytes(b"work in progress")
    stale = out.with_name(f".{out.name}.share-2-of-2.lock")
    stale.write_text("12345")
    try:
        proc = run_module("ingest", "--gather", "-o", out, check=True)
    finally:
        live.kill()
    assert "2 episode(s) linked from 1 share(s)" in proc.stdout  # share 1 of 2: two of the three bags
    assert folders["live"].is_dir() and folders["elsewhere"].is_dir() and not folders["dead"].exists()
    assert (folders["live"] / "000000.h5").read_bytes() == b"work in progress"
    assert proc.stderr.count("a share still being written") == 2
    assert not stale.exists()


def test_a_malformed_share_catalog_is_one_line_and_gathers_nothing(six_bags: list[Path], tmp_path: Path) -> None:
    """A share catalog that is not JSON, not an object, without rows, with rows of wrong types or naming a file
    that is missing: --gather says so in one line, links nothing and removes nothing."""
    from conftest import one_line_error, run_module

    out = tmp_path / "adl.h5"
    run_module("ingest", *six_bags[:2], "-o", out, "--size", "64", "--shard", "1/1", check=True)
    share = next(shards.shards_dir(out).glob("share-*"))
    catalog_file = share / shards.SHARE_CATALOG
    good = json.loads(catalog_file.read_text())
    row = good["rows"][0]
    cases = {
        "not json": ("{not json", "not a share catalog"),
        "a list": ("[1, 2]", "not a share catalog"),
        "no rows": (json.dumps({k: v for k, v in good.items() if k != "rows"}), "no list of rows"),
        "wrong types": (json.dumps({**good, "rows": [{**row, "name": 7}]}), "a row without the text fields"),
        "missing file": (json.dumps({**good, "rows": [{**row, "file": "999999.h5"}]}), "is missing; nothing was"),
    }
    files = sorted(p.name for p in share.iterdir())
    for name, (text, needle) in cases.items():
        catalog_file.write_text(text)
        line = one_line_error(run_module("ingest", "--gather", "-o", out))
        assert needle in line, (name, line)
        assert not out.exists() and sorted(p.name for p in share.iterdir()) == files, name
    catalog_file.write_text(json.dumps(good))  # mended, it gathers
    assert "2 episode(s) linked" in run_module("ingest", "--gather", "-o", out, check=True).stdout
