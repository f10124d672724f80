"""No output ever replaces a device: every stage's output options, pointed at a character device, a FIFO or a link
into /proc, are refused in one line before any work, and the node is still what it was (as root, the atomic rename
would otherwise turn a device into a regular file, and a FIFO would block the writer)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from test_outputs_never_inputs import run_stage, world  # noqa: F401 - the fixture is used by name

# (stage, arguments with {out} for the output under test and {names} of the world's inputs)
CASES = [
    ("assess", "--models {models} --data {data} --details {out}"),
    ("assess", "--models {models} --data {data} --table {out}"),
    ("benchmark", "--compare {details} --metrics {out}"),
    ("benchmark", "--compare {details} --details {out}"),
    ("benchmark", "--compare {details} --table {out}"),
    ("doctor", "{data} --json {out}"),
    ("doctor", "{data} --png {out}"),
    ("edit", "{data} -o {out} --drop x"),
    ("evaluate", "--models {models} --data {data} --metrics {out}"),
    ("evaluate", "--models {models} --data {data} --details {out}"),
    ("evaluate", "--models {models} --data {data} --plots {out}"),
    ("evaluate", "--models {models} --data {data} --table {out}"),
    ("export", "{data} {out}"),
    ("ingest", "{shard} -o {out}"),
    ("inspect", "--dataset --data {data} -o {out}"),
    ("replay", "--models {models} --data {data} --metrics {out}"),
    ("replay", "--models {models} --data {data} --details {out}"),
    ("replay", "--models {models} --data {data} --table {out}"),
    ("report", "--eval {details} --replay {details} -o {out}"),
    ("rollout", "{models} --data {data} --out {out}"),
    ("rollout", "{models} --data {data} --out {models} --summary {out}"),
    ("seeds", "--eval {details} --replay {details} -o {out}"),
    ("seeds", "--eval {details} --replay {details} --metrics {out}"),
    ("serve", "{models} --log {out}"),
    ("serve", "{models} --port-file {out}"),
    ("split", "{data} -o {out}"),
    ("train", "--model fm_cnn --data {data} --log {out}"),
    ("trials", "{trials} -o {out}"),
]


def special(kind: str, root: Path) -> Path:
    """A character device (a copy of /dev/null's numbers, made here: root only), a FIFO, or a link into /proc."""
    path = root / kind
    if kind == "device":
        try:
            os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        except PermissionError:
            pytest.skip("making a device node needs root")
    elif kind == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/proc/self/fd/1")
    return path


@pytest.mark.parametrize("kind", ["device", "fifo", "proc-link"])
@pytest.mark.parametrize(("stage", "argv"), CASES, ids=[f"{s}:{a.split(' ')[-2]}" for s, a in CASES])
def test_an_output_that_is_a_device_a_fifo_or_a_proc_link_is_refused(capsys: pytest.CaptureFixture,
                                                                        world: dict[str, Path],  # noqa: F811
                                                                        tmp_path: Path, stage: str, argv: str,
                                                                        kind: str) -> None:
    out = special(kind, tmp_path)
    before = os.lstat(out)
    proc = run_stage(capsys, stage, argv.format(out=out, **world).split())
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "not a regular file" in lines[0] and str(out) in lines[0], proc.stderr
    after = os.lstat(out)
    assert stat.S_IFMT(after.st_mode) == stat.S_IFMT(before.st_mode) and after.st_ino == before.st_ino
