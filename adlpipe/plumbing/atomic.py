"""Atomic output: every file a stage writes appears complete or not at all.

The content goes to a hidden temp file beside the target (same file system, so the rename is atomic), which
replaces the target only when writing succeeded; a failure or a kill leaves the old file (or none) and no temp.
"""

from __future__ import annotations

import errno
import json
import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import AdlError, check_interrupted, note_committed

# Never an output, whatever link leads there (/dev's nodes are refused by their type: /dev/shm holds regular files)
SYSTEM_TREES = (Path("/proc"), Path("/sys"))
KINDS = {stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device", stat.S_IFIFO: "a FIFO",
         stat.S_IFSOCK: "a socket"}


def special_output(path: Path | str) -> str | None:
    """Why `path` cannot be an output (a device node, a FIFO, a socket, or a link into /proc or /sys: the
    atomic rename would replace a device with a file, and a FIFO blocks the writer), or None for a regular file, a
    folder or a new name."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode  # follows links: what the output would really be
    except (FileNotFoundError, NotADirectoryError):
        mode = None
    except OSError as exc:
        return f"cannot be examined ({exc.strerror})"
    if mode is not None and stat.S_IFMT(mode) in KINDS:
        return f"is {KINDS[stat.S_IFMT(mode)]}"
    for hop in _link_chain(path):
        tree = _system_tree(hop)
        if tree is not None:
            return f"leads into {tree} ({hop})"
    return None


def _system_tree(p: Path) -> Path | None:
    return next((tree for tree in SYSTEM_TREES if p == tree or tree in p.parents), None)


def _link_chain(path: Path) -> list[Path]:
    """The absolute path and every place its links point to, hop by hop (realpath alone would resolve /proc's
    magic fd links to wherever the fd points, hiding that the output goes through /proc)."""
    chain = [Path(os.path.abspath(path))]
    for _ in range(40):
        p = chain[-1]
        resolved_parent = Path(os.path.realpath(p.parent))
        if _system_tree(resolved_parent) is not None:  # a folder link into /proc, e.g. out/ -> /proc/self/fd
            return [*chain, resolved_parent / p.name]
        if not os.path.islink(p):
            break
        chain.append(Path(os.path.abspath(resolved_parent / os.readlink(p))))
    return chain


def refuse_special_outputs(*paths: Path | str) -> None:
    """One line before any work when an output is not a regular file or a new name (special_output)."""
    for path in paths:
        why = special_output(path)
        if why is not None:
            raise AdlError(f"{path}: {why}, not a regular file; outputs are regular files, give another path")


def temp_name(path: Path) -> Path:
    """The temp file for `path` in this process: .<name>.tmp<pid> (ingest removes those of dead processes)."""
    return path.with_name(f".{path.name}.tmp{os.getpid()}")


@contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temp path to write to; on success it replaces `path`, on an exception it is removed."""
    path = Path(path)
    refuse_special_outputs(path)
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
    refuse_special_outputs(*paths)
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
