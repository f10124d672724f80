"""How long doctor takes on a dataset, and its peak memory: the goal is the default 300-episode dataset in under a
minute on 2 cores, with memory flat in the number of episodes.

    python bench/doctor.py [--data data/adl.h5] [--rounds 3]

Each round runs `python -m adlpipe.doctor DATA --json ...` in a fresh process and reads its wall time and its own
peak RSS (VmHWM, bench/peak.py); half the episodes are run as well, so the memory figure can be compared.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
PEAK = ("import runpy, sys; sys.argv = sys.argv[1:]; "
        "exec(\"try:\\n runpy.run_module('adlpipe.doctor', run_name='__main__')\\nexcept SystemExit: pass\"); "
        "sys.path.insert(0, 'bench'); from peak import own_peak_mb; print(f'PEAK {own_peak_mb():.1f}')")


def run(data: Path, names: list[str] | None) -> tuple[float, float, str]:
    out = Path(tempfile.mkdtemp(prefix="adlpipe-doctor-")) / "d.json"
    cmd = [sys.executable, "-c", PEAK, "adlpipe.doctor", str(data), "--json", str(out)]
    if names:
        cmd += ["--episodes", *names]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    seconds = time.perf_counter() - t0
    peak = float(proc.stdout.rsplit("PEAK ", 1)[1])
    summary = [ln for ln in proc.stdout.splitlines() if "flagged" in ln and ln.startswith(str(data))][0]
    return seconds, peak, summary


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=REPO / "data" / "adl.h5")
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args()
    import h5py

    with h5py.File(a.data) as f:
        names = sorted(f["episodes"])
    half = names[::2]
    for label, subset in (("all", None), ("half", half)):
        runs = [run(a.data, subset) for _ in range(a.rounds)]
        secs = sorted(r[0] for r in runs)
        print(f"{label}: {len(subset or names)} episodes, wall {secs[0]:.1f} s min / {secs[len(secs) // 2]:.1f} s "
              f"median, peak RSS {max(r[1] for r in runs):.0f} MB; {runs[0][2]}")


if __name__ == "__main__":
    main()
