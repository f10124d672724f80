"""Peak memory of a benchmarked process, measured so that no other process's memory leaks into the figure.

resource's ru_maxrss is not that figure: Linux keeps the largest RSS a process had before exec, so a benchmark
spawned from a 500 MB parent reports at least 500 MB whatever it really used. VmHWM in /proc/<pid>/status is the
high-water mark of the process's own address space since its exec. Worker processes forked by the benchmarked
process share its pages until they write them; what a worker costs is its unique set (psutil's USS), sampled while
it runs. Every benchmark runs each measurement in a fresh process and reads it with these.
"""

from __future__ import annotations

import threading
from types import TracebackType

import psutil


def own_peak_mb(pid: int | str = "self") -> float:
    """The process's peak resident set since exec (VmHWM), MB."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmHWM in /proc/{pid}/status")


class WorkerPeak:
    """Largest unique memory (USS, MB) of any child process of this one while the block runs, sampled every
    `every` s (a peak shorter than that can be missed: the figure is a lower bound)."""

    def __init__(self, every: float = 0.05) -> None:
        self.every, self.mb = every, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        me = psutil.Process()
        while not self._stop.wait(self.every):
            for child in me.children(recursive=True):
                try:
                    self.mb = max(self.mb, child.memory_full_info().uss / 2**20)
                except psutil.Error:
                    pass  # it ended between listing and reading

    def __enter__(self) -> WorkerPeak:
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join()
