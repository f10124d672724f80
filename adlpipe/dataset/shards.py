"""The index file and its episode files: how a dataset grows without copying itself.

    adl.h5                      index: attrs, /catalog, /episodes/<name> -> external link into an episode file
    adl.shards/<run>/<bag>.h5   one file per bag, one folder per ingest run

An ingest writes its bags' files into a hidden run folder, renames the folder into place, then replaces the index
(temp file + rename). A kill before the index is replaced leaves the old index, which names none of the new files:
the old dataset, whole. The folder of a run that never reached the index is removed by the next ingest. Appending
writes the new bags' files and an index of a few bytes per episode: work in proportion to the new data.

A share of a larger ingest (ingest --shard I/N, one per machine or scheduler task) commits its folder (share-*)
with a catalog.json and leaves the index alone; `ingest --gather` then links every finished share into the index at
once, so no two shares ever write the same file.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import time
from pathlib import Path

import h5py

from ..plumbing.atomic import atomic_path
from ..plumbing.errors import AdlError, check_interrupted, note_committed
from ..plumbing.lock import remove_if_unlocked
from . import schema

shards_dir = schema.shards_root  # adl.h5 -> adl.shards beside it


SHARE_CATALOG = "catalog.json"


def new_run(index: Path, share: tuple[int, int] | None = None) -> tuple[str, Path]:
    """(run name, hidden folder to write it into). A share's name says which share and where it ran (its pid means
    nothing on the machine that gathers)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    if share:
        name = f"share-{share[0]:04d}-of-{share[1]:04d}-{stamp}-{_host()}-{os.getpid()}"
    else:
        name = f"run-{stamp}-{os.getpid()}"
    tmp = shards_dir(index) / f".{name}.tmp"
    tmp.mkdir(parents=True, exist_ok=False)
    return name, tmp


def commit(index: Path, run: str, tmp_dir: Path, rows: list[dict[str, str]], n_waypoints: int,
           image_size: int) -> None:
    """Move the run's folder into place and replace the index with the old rows plus `rows` (file names relative
    to the run folder)."""
    final = shards_dir(index) / run
    check_interrupted()  # a swallowed Ctrl-C: the dataset stays as it was
    os.replace(tmp_dir, final)
    old = []
    if index.exists():
        with h5py.File(index, "r") as f:
            old = schema.read_catalog(f)
    new = [dict(r, file=f"{shards_dir(index).name}/{run}/{r['file']}") for r in rows]
    write_index(index, old + new, n_waypoints, image_size)


def commit_share(index: Path, run: str, tmp_dir: Path, rows: list[dict[str, str]], n_waypoints: int,
                 image_size: int) -> None:
    """A share's folder moves into place with its catalog; the index is left to --gather."""
    (tmp_dir / SHARE_CATALOG).write_text(json.dumps(
        {"format_version": schema.FORMAT_VERSION, "n_waypoints": n_waypoints, "image_size": image_size,
         "rows": rows}))
    check_interrupted()
    os.replace(tmp_dir, shards_dir(index) / run)
    note_committed(shards_dir(index) / run)


def gather(index: Path) -> dict[str, int]:
    """Link the episodes of every committed share into the index (the episodes it already names are kept, a key
    is linked once). Run it after every share has finished: the hidden folders of unfinished shares are removed,
    as are shares that added nothing (all their bags were in the dataset already)."""
    root = shards_dir(index)
    folders = sorted(d for d in root.iterdir() if d.name.startswith("share-")) if root.is_dir() else []
    old, attrs = [], None
    if index.exists():
        with h5py.File(index, "r") as f:
            schema.check_file(f, str(index))
            old = schema.read_catalog(f)
            attrs = (int(f.attrs["n_waypoints"]), int(f.attrs["image_size"]))
            named = referenced_folders(index, f)
    else:
        named = set()
    known = {r["key"] for r in old}
    new: list[dict[str, str]] = []
    unused: list[Path] = []
    for d in folders:
        try:
            cat = json.loads((d / SHARE_CATALOG).read_text())
            share_attrs = (int(cat["n_waypoints"]), int(cat["image_size"]))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise AdlError(f"{d / SHARE_CATALOG}: not a share catalog ({type(exc).__name__}: {exc})") from exc
        if cat.get("format_version") != schema.FORMAT_VERSION:
            raise AdlError(f"{d}: a share of format version {cat.get('format_version')}, this adlpipe writes "
                           f"{schema.FORMAT_VERSION}; ingest its bags again")
        if attrs is not None and share_attrs != attrs:
            raise AdlError(f"{d}: {share_attrs[0]} waypoints at {share_attrs[1]} px, the dataset has {attrs[0]} at "
                           f"{attrs[1]} px; ingest every share with the same --waypoints and --size")
        attrs = share_attrs
        rows = [dict(r, file=f"{root.name}/{d.name}/{r['file']}") for r in _share_rows(d, cat)
                if r["key"] not in known]
        known |= {r["key"] for r in rows}
        new += rows
        if not rows and d.name not in named:
            unused.append(d)
    if new:
        write_index(index, old + new, *attrs)
    for d in unused:
        shutil.rmtree(d, ignore_errors=True)
    unfinished = []
    for d in sorted(root.glob(".share-*.tmp")) if root.is_dir() else []:
        if _writer_gone(d.name[1:-4]):
            shutil.rmtree(d, ignore_errors=True)  # a killed share's leftovers
        else:
            unfinished.append(d.name)  # still being written, or on a machine whose processes we cannot see
    for lock in index.parent.glob(f".{index.name}.share-*.lock"):
        remove_if_unlocked(lock)  # a killed share's lock file (its lock went with its process)
    return {"shares": len(folders), "new": len(new), "episodes": len(old) + len(new), "unfinished": unfinished}


def _writer_gone(run: str) -> bool:
    """Whether the process writing a share's hidden folder has ended: its name ends in -<host>-<pid>; a share of
    another machine is never taken for gone."""
    head, _, pid = run.rpartition("-")
    return pid.isdigit() and head.endswith(f"-{_host()}") and not _alive(int(pid))


def _host() -> str:
    """This machine's name as share folders carry it (letters and digits, at most 40)."""
    return "".join(c if c.isalnum() else "_" for c in socket.gethostname())[:40]


def _share_rows(d: Path, cat: dict) -> list[dict[str, str]]:
    """A share catalog's rows, each naming an episode file that exists inside the share's folder (a name such as
    ../../x would become a link out of the dataset): one line naming the catalog and the row otherwise."""
    rows = cat.get("rows")
    if not isinstance(rows, list):
        raise AdlError(f"{d / SHARE_CATALOG}: no list of rows")
    for r in rows:
        if not isinstance(r, dict) or not all(isinstance(r.get(k), str) and r.get(k) for k in schema.CATALOG_FIELDS):
            raise AdlError(f"{d / SHARE_CATALOG}: a row without the text fields {list(schema.CATALOG_FIELDS)}: "
                           f"{str(r)[:80]}")
        schema.confined_file(d, r["file"], d,
                             outside=f"{d / SHARE_CATALOG}: episode {r['name']} names {r['file']!r}, outside its "
                             "share; refused, nothing was gathered",
                             missing=f"{d / SHARE_CATALOG}: episode {r['name']}: its file {r['file']} is missing; "
                             "nothing was gathered")
    return rows


def write_index(index: Path, rows: list[dict[str, str]], n_waypoints: int, image_size: int) -> None:
    with atomic_path(index) as tmp, h5py.File(tmp, "w") as f:
        schema.create_file(f, n_waypoints, image_size)
        cat = f.create_group(schema.CATALOG)
        for key in schema.CATALOG_FIELDS:
            cat.create_dataset(key, data=[r[key] for r in rows], dtype=h5py.string_dtype())
        for r in rows:
            f[schema.EPISODES][r["name"]] = h5py.ExternalLink(r["file"], f"/{schema.EPISODES}/{r['name']}")


def referenced_folders(index: Path, f: h5py.File) -> set[str]:
    """The run and share folders an index references. Its catalog and its episode links must name the same file
    for every episode: where they disagree, nothing may be cleaned up (either could be the truth), so it is one
    line and nothing changes."""
    links = f[schema.EPISODES] if schema.EPISODES in f else {}
    folders = set()
    for r in schema.read_catalog(f):
        link = links.get(r["name"], getlink=True) if r["name"] in links else None
        target = link.filename if isinstance(link, h5py.ExternalLink) else None
        if target != r["file"]:
            raise AdlError(f"{index}: episode {r['name']}: the catalog names {r['file']} but the index links "
                           f"{target}; the dataset is inconsistent, nothing was changed (ingest it again into a "
                           "new output)")
        parts = Path(r["file"]).parts
        if len(parts) > 2:
            folders.add(parts[1])
    return folders


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
            named = referenced_folders(index, f)
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
    """The episode file an index links `name` to (readers that open episode files directly, e.g. a DataLoader),
    confined to the dataset's .shards folder (schema.episode_path)."""
    return schema.episode_path(index, f, name)
