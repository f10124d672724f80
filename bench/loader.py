"""Does the data loader keep up? Training windows per second against one training step of the small preset.

    python bench/loader.py [--data data/adl.h5] [--batches 30] [--threads 2]

Windows (To = 2 frames in, Tp = 16 waypoints at 10 Hz out, augmentation on, as training draws them) are loaded in
the training process (DataLoader, no workers) and with 2 workers, from every frame of the dataset's episodes at
random, after a warm-up of about three windows per episode (a training run's steady state). A training step
is forward, backward and AdamW of the closed-loop FM-CNN small preset on one batch (32), with --threads CPU threads.
Without --data it records and ingests one MuJoCo ADL episode per task (128 px, 15 Hz) first.
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


def make_data(work: Path) -> Path:
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    py = sys.executable
    subprocess.run([py, "-m", "adlpipe.record", "--episodes", "1", "--out", str(work / "bags"), "--size", "128"],
                   check=True, cwd=REPO, env=env, capture_output=True)
    out = work / "adl.h5"
    subprocess.run([py, "-m", "adlpipe.ingest", *map(str, sorted((work / "bags").glob("*.mcap"))), "-o", str(out),
                    "--size", "128"], check=True, cwd=REPO, env=env, capture_output=True)
    return out


def main() -> None:
    import h5py
    import numpy as np
    import torch
    from torch.utils.data import DataLoader, RandomSampler

    from adlpipe.dataset.loader import Augment, WindowDataset, Windows, compute_window_stats
    from adlpipe.policy.models import Policy, preset

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path)
    p.add_argument("--batches", type=int, default=30)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--workers", type=int, nargs="+", default=[0, 2], help="DataLoader worker processes to measure")
    p.add_argument("--open-files", type=int, default=32, help="episode files each loader process keeps open")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    data = a.data or make_data(Path(tempfile.mkdtemp(prefix="adlpipe-loader-")))
    with h5py.File(data) as f:
        names = sorted(f["episodes"])
        size = int(f.attrs["image_size"])
    windows = Windows(2, 16, 10.0)
    stats = compute_window_stats(data, names, windows)
    cfg = preset("small", "fm_cnn", n_obs=2, horizon=16, rate_hz=10.0, state_dim=8, target="command")  # as train
    #                                                                                         --closed-loop
    ds = WindowDataset(data, names, stats, cfg.image_size, windows, augment=Augment(size), open_files=a.open_files)
    gen = torch.Generator().manual_seed(0)
    load_s = {}
    # a training run draws thousands of batches: the first ones start the workers, open the episode files and read
    # each episode's small arrays once; about three windows per episode warm every worker's caches first
    warm = -(-3 * len(names) // a.batch_size) + 4
    for workers in a.workers:
        sampler = RandomSampler(ds, replacement=True, num_samples=(a.batches + warm) * a.batch_size, generator=gen)
        loader = DataLoader(ds, batch_size=a.batch_size, sampler=sampler, num_workers=workers)
        it = iter(loader)
        batches = [next(it) for _ in range(warm)]
        t = time.perf_counter()
        for _ in range(a.batches):
            batches.append(next(it))
        load_s[workers] = (time.perf_counter() - t) / a.batches
        del it, loader

    policy = Policy(cfg)
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    times = []
    for obs, act in batches[:10] + batches[:10]:
        t = time.perf_counter()
        loss = policy.loss(obs, act, gen=gen)
        opt.zero_grad()
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t)
    step_s = float(np.median(times[5:]))
    print(f"{len(ds)} windows in {len(names)} episodes at {size} px, {a.open_files} files open per process; one "
          "training step of the small preset "
          f"(closed-loop FM-CNN, batch {a.batch_size}, {a.threads} threads): {1000 * step_s:.1f} ms")
    for workers, s in load_s.items():
        print(f"  {workers} loader workers: a batch every {1000 * s:.1f} ms ({a.batch_size / s:.0f} windows/s), "
              f"{step_s / s:.1f}x faster than a training step")


if __name__ == "__main__":
    main()
