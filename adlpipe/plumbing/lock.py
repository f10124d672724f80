"""Writers of one output exclude each other: a second `ingest -o same.h5` or `train --out same` started while the
first runs stops at once with "in use by pid N" instead of silently overwriting the other's work.

The lock is an fcntl lock on a small file beside the output, so it is released when its process ends, however it
ends (a kill leaves no stale lock behind). The holder removes the file when it is done; a writer that locked a file
which was removed meanwhile tries again on the new one (the usual lock-file-with-unlink pattern)."""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .errors import AdlError


def lock_path(output: Path) -> Path:
    return output.with_name(f".{output.name}.lock")


@contextmanager
def exclusive(output: Path | str) -> Iterator[None]:
    """Hold the write lock of `output` (a file or folder) for the duration of the block."""
    output = Path(output)
    path = lock_path(output)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = _acquire(path, output)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        path.unlink(missing_ok=True)  # while still locked: nobody can take this file's lock after us
        os.close(fd)


def _acquire(path: Path, output: Path) -> int:
    for _ in range(100):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise AdlError(f"{output}: in use by pid {holder} (another adlpipe run writes it); wait for it to "
                           "finish") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # the holder removed the file as we locked it: lock the new one
    raise AdlError(f"{output}: cannot take its write lock {path}")


def remove_if_unlocked(path: Path) -> bool:
    """Remove a lock file nobody holds (its process was killed: the lock went with it, the file stayed)."""
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return False
    try:
        if os.fstat(fd).st_ino == os.stat(path).st_ino:
            path.unlink()  # while locked, as the holder does: a writer that locked it meanwhile retries
        return True
    except FileNotFoundError:
        return False
    finally:
        os.close(fd)
