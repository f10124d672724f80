"""Writers of one output exclude each other: a second `ingest -o same.h5` or `train --out same` started while the
first runs stops at once with "in use by pid N" instead of silently overwriting the other's work.

The lock is an fcntl lock on a small file beside the output, so it is released when its process ends, however it
ends (a kill leaves no stale lock behind)."""

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
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            raise AdlError(f"{output}: in use by pid {holder} (another adlpipe run writes it); wait for it to "
                           "finish") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock; the file stays (removing it would race with a waiting writer)
