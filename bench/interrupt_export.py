"""Ctrl-C at random moments of `export --format lerobot` (video): is any interrupt swallowed?

    python bench/interrupt_export.py [--runs 50]

Records 3 episodes of 4 tasks (96 px, 15 Hz) once and ingests them; each run exports the dataset as LeRobot v3
with MP4 video into a new folder and sends SIGINT after a random delay (0.2 s to the export's own duration). A run
is correct when
  - it exits 130 saying no output was replaced, and OUT does not exist (nor its hidden temp folder); or
  - it exits 130 saying OUT was written in full, and OUT holds the whole export; or
  - it exits 0, OUT complete, and the signal came after its last line was printed (the export had finished).
A swallowed interrupt (exit 0 although the signal came before the export finished, OUT committed after it) is BAD,
as is an "Exception ignored ... KeyboardInterrupt" trace on stderr beside the one line.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from verdicts import tally

PY = sys.executable


def export(data: Path, out: Path) -> subprocess.Popen:
    return subprocess.Popen([PY, "-m", "adlpipe.export", "--format", "lerobot", str(data), str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def complete(out: Path) -> bool:
    info = out / "meta" / "info.json"
    return info.exists() and json.loads(info.read_text())["total_episodes"] == 12


def one_run(root: Path, data: Path, delay: float) -> str:
    out = root / "out"
    shutil.rmtree(out, ignore_errors=True)
    proc = export(data, out)
    time.sleep(delay)
    sent = time.time()
    proc.send_signal(signal.SIGINT)
    stdout, err = proc.communicate(timeout=300)
    trace = " / BAD 'Exception ignored' trace" if "Exception ignored" in err else ""
    hidden = (root / ".out.tmp").exists()
    if proc.returncode == 0:
        # finished before the signal arrived only if its summary was printed before it: the export's own output is
        # written when the last frame is in, and a signal that lands later finds the process ending
        done_at = (out / "meta" / "info.json").stat().st_mtime if complete(out) else None
        verdict = ("finished before the signal" if done_at is not None and done_at <= sent
                   else f"BAD exit 0 after the signal (committed {done_at - sent:+.2f} s)" if done_at
                   else "BAD exit 0, OUT incomplete")
    elif proc.returncode in (130, -signal.SIGINT) and "no output was replaced" in err:
        verdict = "interrupted, nothing written" if not out.exists() and not hidden else "BAD said nothing, OUT there"
    elif proc.returncode in (130, -signal.SIGINT) and "written in full" in err:
        verdict = "interrupted after OUT was written" if complete(out) else "BAD said written, OUT incomplete"
    else:
        verdict = f"BAD exit {proc.returncode}: {err.strip().splitlines()[-1][:120] if err.strip() else ''}"
    return verdict + trace


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        subprocess.run([PY, "-m", "adlpipe.record", "--out", str(root / "bags"), "--episodes", "3", "--size", "96",
                        "--camera-hz", "15", "--tasks", "comb the hair", "pass the water", "wipe the nose",
                        "cover the food"], check=True, capture_output=True)
        data = root / "adl.h5"
        subprocess.run([PY, "-m", "adlpipe.ingest", *map(str, sorted((root / "bags").iterdir())), "-o", str(data),
                        "--size", "96"], check=True, capture_output=True)
        t0 = time.time()
        export(data, root / "timing").communicate()
        span = time.time() - t0
        return tally(args.runs, span, args.seed, lambda delay: one_run(root, data, delay),
                     f"of export --format lerobot (video; an uninterrupted export takes {span:.1f} s)")


if __name__ == "__main__":
    sys.exit(main())
