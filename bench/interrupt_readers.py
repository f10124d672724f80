"""Ctrl-C at random moments of the stages that read a dataset (`export`, `train`): what each run says (issue R.1).

    python bench/interrupt_readers.py [--runs 50] [--stage export|train]

Records and ingests 6 small bags once; each run starts the stage on that dataset and sends SIGINT after a random
delay (0.2 s to the stage's own duration). A run is correct when it exits 0 having finished, or exits 130 saying it
was interrupted and nothing of its output was replaced, without calling the dataset damaged; and the dataset still
opens and its every episode passes the readers' checks afterwards. Anything else is counted and shown (h5py raises
an interrupt during a read as a SystemError, which once read as "its file ... is damaged").
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
CHECK = ("import sys\nfrom adlpipe.dataset import schema\n"
         "with schema.open_dataset(sys.argv[1]) as f:\n"
         "    for n in schema.episode_names(f): schema.check_episode(f[schema.EPISODES][n], n)\n"
         "print('ok')")


def command(stage: str, data: Path, out: Path) -> list[str]:
    if stage == "export":
        return [PY, "-m", "adlpipe.export", str(data), str(out)]
    return [PY, "-m", "adlpipe.train", "--model", "bc_cnn", "--data", str(data), "--epochs", "3", "--image-size",
            "32", "--batch-size", "2", "--threads", "1", "--out", str(out)]


def one_run(root: Path, data: Path, stage: str, delay: float) -> str:
    out = root / "out"
    shutil.rmtree(out, ignore_errors=True)
    proc = subprocess.Popen(command(stage, data, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    last = err.strip().splitlines()[-1][:150] if err.strip() else ""
    if "damaged" in err:
        verdict = f"BAD called the dataset damaged: {last}"
    elif proc.returncode == 0:
        verdict = "finished"
    elif proc.returncode in (130, -signal.SIGINT) and "interrupted" in err:
        verdict = "interrupted" + ("" if proc.returncode == 130 else " (then died by SIGINT, not exit 130)")
    else:
        verdict = f"BAD exit {proc.returncode}: {last}"
    check = subprocess.run([PY, "-c", CHECK, str(data)], capture_output=True, text=True)
    if check.stdout.strip() != "ok":
        verdict += f" / BAD dataset afterwards: {check.stderr.strip()[-150:]}"
    return verdict


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=50)
    p.add_argument("--stage", choices=["export", "train"], default="export")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        bags = record_small(root / "bags")
        data = root / "adl.h5"
        subprocess.run([PY, "-m", "adlpipe.ingest", *map(str, bags), "-o", str(data),
                        "--size", "32"], check=True, capture_output=True)
        subprocess.run([PY, "-m", "adlpipe.split", str(data)], check=True, capture_output=True)
        t0 = time.time()
        subprocess.run(command(args.stage, data, root / "timing"), check=True, capture_output=True)
        span = time.time() - t0
        return tally(args.runs, span, args.seed, lambda delay: one_run(root, data, args.stage, delay),
                     f"of {args.stage} (uninterrupted it takes {span:.1f} s)")

if __name__ == "__main__":
    sys.exit(main())
