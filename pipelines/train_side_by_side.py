"""Run a pipeline's training stages two at a time, one thread each, then record them in dvc.lock.

    cd pipelines/study && dvc repro split && python ../train_side_by_side.py && dvc repro
    python ../train_side_by_side.py train_seeds train_closed_loop     # only these stages (names or their prefixes)
    ADLPIPE_SIDE_BY_SIDE=3 python ../train_side_by_side.py            # three at once (a trio on 2 cores: all end
                                                                      # together instead of the third alone)

Any pipeline under pipelines/ whose training stages are foreach stages named train...@... (train@, train_state@,
train_closed_loop@, train_seeds@, train_reg@: pipelines/study, pipelines/pusht, pipelines/pusht_levers, ...).

`dvc repro` runs one stage at a time; on 2 cores two one-thread trainings side by side finish sooner than two
two-thread trainings in turn. This runs each training stage's own command (as DVC renders it from dvc.yaml and
params.yaml, so the models are exactly what `dvc repro` would train), the stages in ORDER and then as dvc.yaml
lists them, and `dvc commit`s each stage that finished; the `dvc repro` after it skips them. A stage already up to
date is not run again; a killed run resumes each training from its last checkpoint (adlpipe.train).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from dvc.repo import Repo

ORDER = ("train@", "train_closed_loop@", "train_seeds@")  # run first, in this order; other train...@ stages after
SIDE_BY_SIDE = int(os.environ.get("ADLPIPE_SIDE_BY_SIDE", "2"))


def is_training(name: str) -> bool:
    return "@" in name and name.startswith("train")


def stale_training_stages(repo: Repo, wanted: tuple[str, ...] = ("train",)) -> list:
    """The training stages named by `wanted` (names or prefixes) that are not up to date, in ORDER, then as
    dvc.yaml lists them."""
    stale = set(repo.status())  # names of the stages whose deps, params or outs changed
    stages = [s for s in repo.index.stages if is_training(s.name) and s.name.startswith(wanted) and s.name in stale]
    return sorted(stages, key=lambda s: next((i for i, p in enumerate(ORDER) if s.name.startswith(p)), len(ORDER)))


def run(stage, logs: Path) -> tuple[str, int, float]:  # noqa: ANN001 - a dvc Stage
    t0 = time.time()
    for out in stage.outs:  # as dvc repro does: a stale stage's outputs go before its command runs
        path = Path(out.fs_path)
        shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    with open(logs / f"{stage.name.replace('@', '_')}.log", "w") as log:
        env = {**os.environ, "DVC_STAGE": stage.addressing}  # what dvc repro sets: a stage writes its own outputs
        rc = subprocess.run(stage.cmd, shell=True, stdout=log, stderr=subprocess.STDOUT, env=env).returncode
    return stage.name, rc, time.time() - t0


def main(argv: list[str]) -> int:
    repo = Repo(".")
    stages = stale_training_stages(repo, tuple(argv) or ("train",))
    logs = Path("logs")
    logs.mkdir(exist_ok=True)
    print(f"{len(stages)} training stage(s) to run, {SIDE_BY_SIDE} at a time: {', '.join(s.name for s in stages)}")
    failed = []
    with ThreadPoolExecutor(SIDE_BY_SIDE) as pool:
        for name, rc, seconds in pool.map(lambda s: run(s, logs), stages):
            print(f"{name}: {'done' if rc == 0 else f'failed ({rc})'} in {seconds / 60:.1f} min", flush=True)
            if rc:
                failed.append(name)
    done = [s.name for s in stages if s.name not in failed]
    if done:
        subprocess.run([sys.executable, "-m", "dvc", "commit", "-f", *done], check=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
