"""A stage's finished parts, kept beside its output while it runs, so that a killed run resumes without redoing them.

evaluate journals each model's figures, replay each policy's outcomes. The journal's first line is the fingerprint of
everything the figures depend on (the stage's arguments, the split, the dataset's file, every checkpoint's sha256):
a run with other inputs starts a new journal. A finished stage writes its outputs and removes the journal. A line a
kill cut short is not read (each line is one JSON document, flushed and synced before the next part starts).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from .errors import AdlError

# arguments that change where or how fast a stage runs, never its figures
NOT_FIGURES = ("force", "workers", "threads", "metrics", "details", "plots", "table", "failures")


def fingerprint(options: object, checkpoints: list[Path], split: Path, data: Path) -> str:
    """What a stage's figures depend on: its options (a configuration dataclass or parsed arguments, by field), the
    dataset's file by size and modification time (hashing a large dataset would cost more than most parts), the
    split and the checkpoints by content."""
    st = data.stat()
    what = {"args": {k: v for k, v in sorted(vars(options).items()) if k not in NOT_FIGURES},
            "split": _file_sha256(split), "data": [str(data.resolve()), st.st_size, st.st_mtime_ns],
            "checkpoints": {str(p): _file_sha256(p) for p in checkpoints if p.exists()}}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()


def _file_sha256(path: Path) -> str:
    """A file's sha256 (the split, a checkpoint), read in blocks (a bag's hash, of its parts or folder, is
    adlpipe.dataset.from_bag.sha256_of)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


class Journal:
    def __init__(self, output: Path, fingerprint: str) -> None:
        self.path = output.with_name(f".{output.name}.journal")
        self.fingerprint = fingerprint
        self.done: dict[str, object] = {}
        if not self._resume():
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.path.unlink(missing_ok=True)  # another run's: its parts are not this run's
            self._append({"fingerprint": fingerprint})

    def _resume(self) -> bool:
        """Whether this run's journal is there; its finished parts into self.done."""
        try:
            lines = self.path.read_text().splitlines()
        except (OSError, UnicodeDecodeError):
            return False
        parts = []
        for line in lines:
            try:
                parts.append(json.loads(line))
            except json.JSONDecodeError:
                break  # cut short by a kill: this part and none after it
        if not parts or parts[0] != {"fingerprint": self.fingerprint}:
            return False
        self.done = {p["key"]: p["value"] for p in parts[1:] if isinstance(p, dict) and "key" in p}
        return True

    def _append(self, doc: dict) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps(doc) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def add(self, key: str, value: object) -> None:
        self._append({"key": key, "value": value})
        self.done[key] = value

    def close(self) -> None:
        """The stage wrote its outputs: nothing to resume."""
        self.path.unlink(missing_ok=True)

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, kind: type | None, exc: BaseException | None, tb: object) -> None:
        """A clean failure (a user error: bad input, to be fixed and run again with other inputs) leaves no journal
        behind; a kill or a Ctrl-C keeps it, for the run that resumes."""
        if isinstance(exc, AdlError):
            self.close()


class Section:
    """The part of a journal under one key prefix (a sequential replay's batch), with the journal's interface."""

    def __init__(self, journal: Journal, prefix: str) -> None:
        self.journal, self.prefix = journal, prefix
        self.done = {k[len(prefix):]: v for k, v in journal.done.items() if k.startswith(prefix)}

    def add(self, key: str, value: object) -> None:
        self.journal.add(self.prefix + key, value)
        self.done[key] = value
