"""Atomic output: every file a stage writes appears complete or not at all.

The content goes to a hidden temp file beside the target (same file system, so the rename is atomic), which
replaces the target only when writing succeeded; a failure or a kill leaves the old file (or none) and no temp.
"""

from __future__ import annotations

import errno
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import check_interrupted, note_committed


def temp_name(path: Path) -> Path:
    """The temp file for `path` in this process: .<name>.tmp<pid> (ingest removes those of dead processes)."""
    return path.with_name(f".{path.name}.tmp{os.getpid()}")


@contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temp path to write to; on success it replaces `path`, on an exception it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    try:
        yield tmp
        check_interrupted()  # a Ctrl-C swallowed while the temp was written still keeps the old file
        os.replace(tmp, path)
        note_committed(path)
    except OSError as exc:
        if exc.errno == errno.ENOSPC or not exc.filename:  # name the output the user asked for, not the temp
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise
    except RuntimeError as exc:  # HDF5 and torch report a full disk as RuntimeError text
        if "No space left" in str(exc) or "failed writing" in str(exc):
            raise OSError(errno.ENOSPC, "No space left on device", str(path)) from exc
        raise
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text_atomic(path: Path | str, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json_atomic(path: Path | str, obj: object) -> None:
    write_text_atomic(path, json_text(obj))


def check_outputs(*paths: Path | str) -> None:
    """Fail before the work, not after it: every output must be a file path whose folder can be written."""
    for path in map(Path, paths):
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, "is a folder; give a file path", str(path))
        parent = path.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, f"{parent} is a file, not a folder", str(path))
        if not os.access(parent, os.W_OK):
            err = errno.EROFS if os.statvfs(parent).f_flag & os.ST_RDONLY else errno.EACCES
            raise OSError(err, os.strerror(err), str(path))


def write_all_atomic(texts: dict[Path, str | bytes]) -> None:
    """A stage's outputs (text, or bytes such as a PNG) all or none: every file is written to its temp first; only
    when all are written do they replace their targets (a folder in the way or a full disk leaves every old output
    as it was)."""
    check_outputs(*texts)
    done: list[tuple[Path, Path]] = []
    try:
        for path, text in texts.items():
            path = Path(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = temp_name(path)
            done.append((tmp, path))
            try:
                tmp.write_bytes(text) if isinstance(text, bytes) else tmp.write_text(text)
            except OSError as exc:
                raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        check_interrupted()
        for tmp, path in done:
            os.replace(tmp, path)
            note_committed(path)
    finally:
        for tmp, _ in done:
            if tmp.exists():
                tmp.unlink()


def json_text(obj: object) -> str:
    return json.dumps(obj, indent=1, sort_keys=True) + "\n"
