"""A dataset reads only itself (U.1): crafted indexes, episode files and share catalogs that would make a reading
stage open or export another file are refused in one line naming the episode and the target, before any of their
bytes is read. Real HDF5 external links, external raw storage and virtual datasets, made with h5py."""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import copy_dataset, one_line_error, run_module

from adlpipe.dataset import schema

SECRET = b"top secret bytes outside the dataset\n" * 8


def _dataset(ingested: Path, tmp_path: Path) -> tuple[Path, str, Path]:
    """A private copy of the session's dataset: (index, first episode, its file)."""
    (tmp_path / "d").mkdir(parents=True)
    index = copy_dataset(ingested, tmp_path / "d" / "adl.h5")
    with h5py.File(index) as f:
        name = schema.episode_names(f)[0]
        file = index.parent / f[schema.EPISODES].get(name, getlink=True).filename
    return index, name, file


def _relink(index: Path, name: str, target: str) -> None:
    with h5py.File(index, "a") as f:
        del f[schema.EPISODES][name]
        f[schema.EPISODES][name] = h5py.ExternalLink(target, f"/{schema.EPISODES}/{name}")


def _export(index: Path, tmp_path: Path) -> object:
    return run_module("export", index, tmp_path / "export")


@pytest.mark.parametrize("where", ["absolute", "relative"])
def test_a_link_out_of_the_dataset_is_refused(ingested: Path, tmp_path: Path, where: str) -> None:
    index, name, file = _dataset(ingested, tmp_path)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "x.h5").write_bytes(file.read_bytes())  # a valid episode file, but not the dataset's
    target = str(outside / "x.h5") if where == "absolute" else "../outside/x.h5"
    _relink(index, name, target)
    for stage, args in (("export", [tmp_path / "export"]), ("split", ["-o", tmp_path / "s.json"])):
        line = one_line_error(run_module(stage, index, *args))
        assert f"episode {name}: links to {target}, outside the dataset's adl.shards folder" in line, stage
    assert not (tmp_path / "export").exists() and not (tmp_path / "s.json").exists()


def test_a_symlink_out_of_the_shards_folder_is_refused(ingested: Path, tmp_path: Path) -> None:
    index, name, file = _dataset(ingested, tmp_path)
    moved = tmp_path / "elsewhere.h5"
    file.rename(moved)
    file.symlink_to(moved)  # the link's name is inside adl.shards, the bytes are not
    line = one_line_error(_export(index, tmp_path))
    assert f"episode {name}" in line and "outside the dataset's adl.shards folder" in line


def test_external_raw_storage_and_virtual_datasets_are_refused(ingested: Path, tmp_path: Path) -> None:
    """An episode whose rgb reads another file's bytes (HDF5 external storage) would export that file byte for
    byte; a virtual dataset maps another file in. Both are refused, and nothing is exported."""
    secret = tmp_path / "secret.bin"
    secret.write_bytes(SECRET)
    index, name, file = _dataset(ingested, tmp_path)
    with h5py.File(file, "a") as f:
        g = f[schema.EPISODES][name]
        shape = g["rgb"].shape
        del g["rgb"]
        g.create_dataset("rgb", shape=shape, dtype=np.uint8, external=[(str(secret), 0, h5py.h5f.UNLIMITED)])
    line = one_line_error(_export(index, tmp_path))
    assert f"episode {name}" in line and f"stores its data in '{secret}'" in line and "refused" in line
    assert not (tmp_path / "export").exists()

    index, name, file = _dataset(ingested, tmp_path / "v")
    src = tmp_path / "v" / "src.h5"
    with h5py.File(src, "w") as s:
        s["x"] = np.zeros((2, 3), np.float32)
    with h5py.File(file, "a") as f:
        g = f[schema.EPISODES][name]
        layout = h5py.VirtualLayout(shape=(2, 3), dtype=np.float32)
        layout[:] = h5py.VirtualSource(str(src), "x", shape=(2, 3))
        del g["traj3d"]
        g.create_virtual_dataset("traj3d", layout)
    line = one_line_error(run_module("split", index, "-o", tmp_path / "s.json"))
    assert f"episode {name}" in line and "virtual dataset over" in line and str(src) in line


def test_a_missing_episode_file_is_not_replaced_from_the_current_folder(ingested: Path, tmp_path: Path) -> None:
    """HDF5 looks for a missing link target in the current folder (and first under HDF5_EXT_PREFIX): adlpipe
    resolves the file itself, so a same-named decoy there is never read."""
    index, name, file = _dataset(ingested, tmp_path)
    rel = file.relative_to(index.parent)
    decoy_root = tmp_path / "cwd"
    (decoy_root / rel).parent.mkdir(parents=True)
    (decoy_root / rel).write_bytes(file.read_bytes())
    file.unlink()
    cwd = os.getcwd()
    os.chdir(decoy_root)
    try:
        line = one_line_error(run_module("split", index, "-o", tmp_path / "s.json"))
    finally:
        os.chdir(cwd)
    assert f"episode {name}: its file {index.parent / rel} is missing" in line


def test_hdf5_ext_prefix_cannot_swap_an_episode_file(ingested: Path, tmp_path: Path) -> None:
    index, name, file = _dataset(ingested, tmp_path)
    rel = file.relative_to(index.parent)
    decoy_root = tmp_path / "prefix"
    (decoy_root / rel).parent.mkdir(parents=True)
    (decoy_root / rel).write_bytes(file.read_bytes())
    env = dict(os.environ, HDF5_EXT_PREFIX=str(decoy_root))
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "adlpipe.split", str(index), "-o", str(tmp_path / "s.json")],
                          capture_output=True, text=True, env=env, timeout=300)
    line = one_line_error(proc)
    assert f"episode {name}: HDF5 opened {decoy_root / rel}" in line


def test_gather_refuses_a_share_catalog_naming_a_file_outside_its_share(ingested: Path, mcap_bags: list[Path],
                                                                          tmp_path: Path) -> None:
    index = tmp_path / "g.h5"
    run_module("ingest", mcap_bags[0], "-o", index, "--size", "64", "--shard", "1/2", check=True)
    (share,) = [d for d in (tmp_path / "g.shards").iterdir() if d.name.startswith("share-")]
    cat = json.loads((share / "catalog.json").read_text())
    cat["rows"][0]["file"] = "../../../etc/passwd"
    (share / "catalog.json").write_text(json.dumps(cat))
    proc = run_module("ingest", "--gather", "-o", index)
    line = one_line_error(proc)
    assert "names '../../../etc/passwd', outside its share" in line and "nothing was gathered" in line
    assert not index.exists()
