"""Edit a dataset without ingesting again: a new index beside the old one, the episode files shared, not copied.

The new index (OUT) gets its own run folder (OUT's .shards/run-...) holding a hard link to every episode file it
keeps: the bytes are the old dataset's, and deleting either dataset later leaves the other whole. Only an episode
renamed or given another task is written anew (its file's kept episodes copied with the new name or task): the old
files are never changed. Like an ingest, the run folder is written hidden, renamed into place, and the index is
written last by a rename, so a kill leaves no OUT (and the next ingest or edit into OUT removes the leftovers).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import h5py

from ..dataset import schema, shards
from ..plumbing.errors import AdlError


@dataclass
class Edits:
    drop: set[str] = field(default_factory=set)  # episode names left out
    rename: dict[str, str] = field(default_factory=dict)  # old name -> new name
    retask: dict[str, str] = field(default_factory=dict)  # name -> new task (the name follows the task)
    merge: list[Path] = field(default_factory=list)  # other datasets whose episodes are added


@dataclass
class Row:
    name: str  # in the new index
    key: str
    task: str
    source: Path  # the episode file it is read from
    old_name: str  # its group name in that file
    rewrite: bool = False  # renamed or re-tasked: written anew, not linked


def _rows(index: Path) -> tuple[list[Row], tuple[int, int]]:
    """Every episode of a dataset (checked readable) with its file, and (n_waypoints, image_size)."""
    with schema.open_dataset(index) as f:
        attrs = (int(f.attrs["n_waypoints"]), int(f.attrs["image_size"]))
        rows = [Row(r["name"], r["key"], r["task"], schema.episode_path(index, f, r["name"]), r["name"])
                for r in schema.read_catalog(f)]
    return rows, attrs


def plan(data: Path, edits: Edits) -> tuple[list[Row], tuple[int, int], list[str]]:
    """(the new index's rows, its attributes, notes) after checking every edit names an episode that is there."""
    rows, attrs = _rows(data)
    notes = []
    for other in edits.merge:
        more, other_attrs = _rows(other)
        if other_attrs != attrs:
            raise AdlError(f"{other}: {other_attrs[0]} waypoints at {other_attrs[1]} px, {data} has {attrs[0]} at "
                           f"{attrs[1]} px; only datasets of the same format merge")
        keys = {r.key for r in rows}
        twice = [r for r in more if r.key in keys]
        if twice:
            notes.append(f"{other}: {len(twice)} episode(s) already in {data} (same bag), kept once")
        rows += [r for r in more if r.key not in keys]
    names = {r.name for r in rows}
    for what, wanted in (("--drop", edits.drop), ("--rename", set(edits.rename)), ("--retask", set(edits.retask))):
        unknown = sorted(wanted - names)
        if unknown:
            raise AdlError(f"{what}: no episode {unknown[0]!r} in the dataset ({len(unknown)} unknown)")
    both = sorted(set(edits.rename) & set(edits.retask))
    if both:
        raise AdlError(f"episode {both[0]} is both renamed and re-tasked; a re-task renames it after its task")
    kept = []
    for r in rows:
        if r.name in edits.drop:
            continue
        task = edits.retask.get(r.name, r.task)
        if r.name in edits.retask:
            sha, _, seg = r.key.partition("#")
            new = schema.episode_name(task, sha, int(seg) if seg else -1)
        else:
            new = edits.rename.get(r.name, r.name)
        if not re.fullmatch(r"[A-Za-z0-9_-]{1,200}", new):
            raise AdlError(f"--rename {r.name}={new}: a name holds letters, digits, '_' and '-' only")
        kept.append(Row(new, r.key, task, r.source, r.old_name, new != r.old_name or r.name in edits.retask))
    clash = _first_duplicate([r.name for r in kept])
    if clash:
        raise AdlError(f"two episodes would be named {clash!r}; choose another name")
    if not kept:
        raise AdlError("every episode would be dropped; nothing to write")
    return kept, attrs, notes


def _first_duplicate(names: list[str]) -> str | None:
    seen: set[str] = set()
    for n in names:
        if n in seen:
            return n
        seen.add(n)
    return None


def write(out: Path, rows: list[Row], attrs: tuple[int, int]) -> None:
    """The new index and its run folder (hard links, and new files for the renamed or re-tasked episodes)."""
    shards.remove_unreferenced(out)
    made_root = not shards.shards_dir(out).exists()
    run, tmp = shards.new_run(out)
    committed = False
    try:
        by_file: dict[Path, list[Row]] = {}
        for r in rows:
            by_file.setdefault(r.source, []).append(r)
        catalog = []
        for i, (source, file_rows) in enumerate(by_file.items()):
            target = tmp / f"{i:06d}.h5"
            if not any(r.rewrite for r in file_rows):
                _link(source, target, out)
            else:
                _rewrite(source, target, file_rows)
            catalog += [{"name": r.name, "key": r.key, "task": r.task, "file": target.name} for r in file_rows]
        shards.commit(out, run, tmp, catalog, *attrs)
        committed = True
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if made_root and not committed:  # a refused edit (another file system, a Ctrl-C) leaves no empty folder
            shutil.rmtree(shards.shards_dir(out), ignore_errors=True)


def _link(source: Path, target: Path, out: Path) -> None:
    try:
        os.link(source, target)
    except OSError as exc:
        if exc.errno in (errno.EXDEV, errno.EPERM, errno.EMLINK):
            raise AdlError(f"{out}: cannot share {source} by a hard link ({exc.strerror}); write the new dataset on "
                           "the same file system as the old one") from None
        raise


def _rewrite(source: Path, target: Path, rows: list[Row]) -> None:
    """A new episode file holding the file's kept episodes under their new names and tasks."""
    with h5py.File(source, "r") as src, h5py.File(target, "w") as dst:
        group = dst.require_group(schema.EPISODES)
        for r in rows:
            src.copy(src[schema.EPISODES][r.old_name], group, name=r.name)
            group[r.name].attrs["task"] = r.task


def edit(data: Path, out: Path, edits: Edits) -> dict:
    """Write OUT: DATA with the edits. Returns counts and notes."""
    if out.resolve() == data.resolve() or out.exists():
        raise AdlError(f"{out}: already exists; an edit writes a new index beside the old one")
    rows, attrs, notes = plan(data, edits)
    write(out, rows, attrs)
    return {"episodes": len(rows), "dropped": len(edits.drop), "renamed": len(edits.rename),
            "retasked": len(edits.retask), "notes": notes}
