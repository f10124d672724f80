"""The index file and its episode files: how a dataset grows without copying itself.

    adl.h5                      index: attrs, /catalog, /episodes/<name> -> external link into an episode file
    adl.shards/<run>/<bag>.h5   one file per bag, one folder per ingest run

An ingest writes its bags' files into a hidden run folder, renames the folder into place, then replaces the index
(temp file + rename). A kill before the index is replaced leaves the old index, which names none of the new files:
the old dataset, whole. The folder of a run that never reached the index is removed by the next ingest. Appending
writes the new bags' files and an index of a few bytes per episode: work in proportion to the new data.
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import h5py

from ..atomic import atomic_path
from . import schema


def shards_dir(index: Path) -> Path:
    """adl.h5 -> adl.shards beside it."""
    return index.with_name(index.stem + ".shards") if index.suffix else index.with_name(index.name + ".shards")


def new_run(index: Path) -> tuple[str, Path]:
    """(run name, hidden folder to write it into)."""
    name = time.strftime("run-%Y%m%d-%H%M%S") + f"-{os.getpid()}"
    tmp = shards_dir(index) / f".{name}.tmp"
    tmp.mkdir(parents=True, exist_ok=False)
    return name, tmp


def commit(index: Path, run: str, tmp_dir: Path, rows: list[dict[str, str]], n_waypoints: int,
           image_size: int) -> None:
    """Move the run's folder into place and replace the index with the old rows plus `rows` (file names relative
    to the run folder)."""
    final = shards_dir(index) / run
    os.replace(tmp_dir, final)
    old = []
    if index.exists():
        with h5py.File(index, "r") as f:
            old = schema.read_catalog(f)
    new = [dict(r, file=f"{shards_dir(index).name}/{run}/{r['file']}") for r in rows]
    write_index(index, old + new, n_waypoints, image_size)


def write_index(index: Path, rows: list[dict[str, str]], n_waypoints: int, image_size: int) -> None:
    with atomic_path(index) as tmp, h5py.File(tmp, "w") as f:
        schema.create_file(f, n_waypoints, image_size)
        cat = f.create_group(schema.CATALOG)
        for key in schema.CATALOG_FIELDS:
            cat.create_dataset(key, data=[r[key] for r in rows], dtype=h5py.string_dtype())
        for r in rows:
            f[schema.EPISODES][r["name"]] = h5py.ExternalLink(r["file"], f"/{schema.EPISODES}/{r['name']}")


def remove_unreferenced(index: Path) -> None:
    """What killed ingests left: temp files of the index (.adl.h5.tmp<pid>), hidden folders of runs whose process
    is gone, and run folders no index names (killed between the folder's rename and the index's)."""
    for tmp in index.parent.glob(f".{index.name}.tmp*"):
        pid = tmp.name.rsplit(".tmp", 1)[1]
        if pid.isdigit() and not _alive(int(pid)):
            tmp.unlink(missing_ok=True)
    root = shards_dir(index)
    if not root.is_dir():
        return
    named: set[str] = set()
    if index.exists():
        with h5py.File(index, "r") as f:
            named = {Path(r["file"]).parts[1] for r in schema.read_catalog(f) if len(Path(r["file"]).parts) > 2}
    for d in root.iterdir():
        if d.name.startswith(".run-") and d.name.endswith(".tmp"):
            pid = d.name[:-4].rsplit("-", 1)[-1]
            if pid.isdigit() and _alive(int(pid)):
                continue
            shutil.rmtree(d, ignore_errors=True)
        elif d.name.startswith("run-") and d.name not in named:
            shutil.rmtree(d, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether a process exists (another user's counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def episode_file(index: Path, f: h5py.File, name: str) -> Path:
    """The episode file an index links `name` to (readers that open episode files directly, e.g. a DataLoader)."""
    link = f[schema.EPISODES].get(name, getlink=True)
    return index.parent / link.filename
