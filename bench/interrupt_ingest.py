"""Ctrl-C at random moments of `ingest` into an existing dataset: what each run says and what the dataset holds.

    python bench/interrupt_ingest.py [--runs 50] [--workers 1]

Records 2 + 4 small bags once; each run copies a dataset of the first 2, ingests the other 4 into it and sends
SIGINT after a random delay (0.2 s to the ingest's own duration). A run is correct when
  - it exits 0 after its summary, the index holding all 6 episodes;
  - it exits 130 saying no output was replaced, the index byte for byte what it was; or
  - it exits 130 saying the index was written in full, the index holding all 6 episodes, every one readable;
and whatever it did, the next ingest of the same bags into that dataset succeeds. Anything else is counted and
shown: an interrupt swallowed (exit 0 with a KeyboardInterrupt traceback), a message that says the opposite of
what the dataset holds, a dataset refused as damaged.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from verdicts import record_small, tally

PY = sys.executable


def ingest(bags: list[Path], out: Path, workers: int) -> subprocess.Popen:
    return subprocess.Popen([PY, "-m", "adlpipe.ingest", *map(str, bags), "-o", str(out), "--size", "32",
                             "--workers", str(workers)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def episodes(index: Path) -> int | None:
    proc = subprocess.run([PY, "-c", "import sys, h5py\nfrom adlpipe.dataset import schema\n"
                           "with schema.open_dataset(sys.argv[1]) as f: print(len(schema.episode_names(f)))",
                           str(index)], capture_output=True, text=True)
    return int(proc.stdout) if proc.returncode == 0 else None


def one_run(root: Path, base: Path, bags: list[Path], delay: float, workers: int) -> str:
    work = root / "run"
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(base, work)
    index = work / "adl.h5"
    before = index.read_bytes()
    proc = ingest(bags, index, workers)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    held = episodes(index)
    if proc.returncode == 0:
        verdict = "finished" if held == 6 and "KeyboardInterrupt" not in err else f"BAD exit 0, {held} held"
    elif proc.returncode in (130, -signal.SIGINT) and "no output was replaced" in err:
        how = "" if proc.returncode == 130 else " (then died by SIGINT, not exit 130)"
        verdict = (f"interrupted, unchanged{how}" if index.read_bytes() == before
                   else "BAD said unchanged, index changed")
    elif proc.returncode in (130, -signal.SIGINT) and "written in full" in err and "adl.h5" in err:
        how = "" if proc.returncode == 130 else " (then died by SIGINT, not exit 130)"
        verdict = f"interrupted after the index{how}" if held == 6 else f"BAD said written, {held} held"
    else:
        verdict = f"BAD exit {proc.returncode}: {err.strip().splitlines()[-1][:120] if err.strip() else ''}"
    again = ingest(bags, index, workers)
    _, err2 = again.communicate(timeout=300)
    if again.returncode != 0 or episodes(index) != 6:
        verdict += f" / BAD next ingest: {err2.strip()[-150:]}"
    return verdict


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=50)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        bags = record_small(root / "bags")
        base = root / "base"
        base.mkdir()
        subprocess.run([PY, "-m", "adlpipe.ingest", *map(str, bags[:2]), "-o", str(base / "adl.h5"), "--size", "32"],
                       check=True, capture_output=True)
        t0 = time.time()
        proc = ingest(bags[2:], root / "timing.h5", args.workers)
        proc.communicate()
        span = time.time() - t0
        return tally(args.runs, span, args.seed, lambda delay: one_run(root, base, bags[2:], delay, args.workers),
                     f"--workers {args.workers} (an uninterrupted ingest takes {span:.1f} s)")

if __name__ == "__main__":
    sys.exit(main())
