"""Outputs a DVC pipeline owns: a stage run by hand that would replace them says so, unless told --force.

A README example or an experiment run by hand with the default paths would silently replace what `dvc repro`
made (its metrics, tables, models), and `dvc status` would then report a pipeline that no longer matches its lock
file. The owner of a path is found in the dvc.lock files of the folders above it (up to the DVC project's root): a
lock file lists every output of the stages that ran, with its path resolved. Inside `dvc repro` (DVC sets
DVC_STAGE in the stage's environment) a stage writes its own outputs as usual.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import yaml

from .errors import AdlError

LOCK = "dvc.lock"
MAX_LOCK_BYTES = 16 << 20  # a lock file larger than this is not read (never parse an unbounded file)


def _lock_outputs(lock: Path) -> Iterable[tuple[str, Path]]:
    """(stage, output path) for every output a lock file records; nothing for an unreadable or foreign file."""
    try:
        if lock.stat().st_size > MAX_LOCK_BYTES:
            return []
        data = yaml.safe_load(lock.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return []
    stages = data.get("stages") if isinstance(data, dict) else None
    if not isinstance(stages, dict):
        return []
    out = []
    for stage, entry in stages.items():
        for o in (entry.get("outs") or []) if isinstance(entry, dict) else []:
            if isinstance(o, dict) and isinstance(o.get("path"), str):
                out.append((str(stage), (lock.parent / o["path"]).resolve()))
    return out


def dvc_owner(path: Path) -> tuple[str, Path] | None:
    """(stage, lock file) of the DVC stage whose output `path` is or lies in; None if no pipeline owns it."""
    target = Path(path).resolve()
    for folder in target.parents:
        lock = folder / LOCK
        if lock.is_file():
            for stage, out in _lock_outputs(lock):
                if target == out or out in target.parents:
                    return stage, lock
        if (folder / ".dvc").is_dir():
            return None  # the DVC project's root: nothing above it owns this path
    return None


def refuse_pipeline_outputs(paths: Iterable[Path | str | None], force: bool) -> None:
    """One line and no work when a path belongs to a DVC stage, outside `dvc repro` and without --force."""
    if force or os.environ.get("DVC_STAGE"):
        return
    for path in paths:
        if path is None:
            continue
        owner = dvc_owner(Path(path))
        if owner is not None:
            stage, lock = owner
            raise AdlError(f"{path}: an output of DVC stage '{stage}' ({lock}); replacing it by hand leaves the "
                           "pipeline out of date: write elsewhere, or pass --force")
