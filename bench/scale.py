"""A dataset of the paper's size: 10,000 episodes, against 1,000, on this machine.

    python bench/scale.py [--sizes 1000 10000] [--workers 2] [--work DIR] [--dask-shares 8]

Bags: short synthetic demonstrations (2 s, 64x48 RGB at 10 Hz, tf at 50 Hz, joint states; tests/layouts.py, a
Kinova arm and an Azure Kinect camera) written with the real mcap writer, 10 tasks. For each size, each in a fresh
process:
(1) ingest (`ingest --workers N`, every frame, stored at 64 px): seconds, bags/s, peak RSS of the ingesting process
    and of its largest worker, dataset size (index + episode files);
(2) one epoch of the paper preset's data (first frame -> 32 waypoints at 224 px, the train statistics computed
    first, augmentation on) through the training DataLoader (N persistent workers, batch 64): seconds, episodes/s,
    peak RSS of the loading process and of its largest worker;
(3) with --dask-shares K: the same bags ingested as K shares on a local Dask cluster of N workers
    (examples/ingest_with_dask.py), then gathered: seconds.
Prints how each figure grows from the smallest size to the largest, and a JSON line.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests"), str(REPO / "bench")]

from ingest_scale import run, size_mb  # noqa: E402 - the fresh-process runner and folder size of the ingest bench

INGEST = """
import json, sys, time
sys.path.insert(0, "bench")
from peak import WorkerPeak, own_peak_mb
from pathlib import Path
from adlpipe.ingest import main
out, cfg, workers, listing = sys.argv[1:]
bags = Path(listing).read_text().split()
t = time.perf_counter()
with WorkerPeak() as workers_peak:
    rc = main([*bags, "-o", out, "--config", cfg, "--size", "64", "--workers", workers])
print(json.dumps({"rc": rc, "s": time.perf_counter() - t, "rss_mb": own_peak_mb(), "child_rss_mb": workers_peak.mb}))
"""
EPOCH = """
import json, sys, time
sys.path.insert(0, "bench")
from peak import WorkerPeak, own_peak_mb
from pathlib import Path
import torch
from torch.utils.data import DataLoader
from adlpipe.dataset import schema
from adlpipe.dataset.loader import Augment, TrajectoryDataset, compute_stats
from adlpipe.dataset.sampling import EpochSampler, TrainingSamples
from adlpipe.policy.models import preset
data, workers = sys.argv[1], int(sys.argv[2])
cfg = preset("paper", "fm_cnn")
with schema.open_dataset(Path(data)) as f:
    names = schema.episode_names(f)
    size = int(f.attrs["image_size"])
t = time.perf_counter()
stats = compute_stats(data, names)
stats_s = time.perf_counter() - t
ds = TrajectoryDataset(data, names, stats, cfg.image_size, augment=Augment(size))
sampler = EpochSampler(len(ds))
loader = DataLoader(TrainingSamples(ds, 0), batch_size=64, sampler=sampler, num_workers=workers,
                    persistent_workers=workers > 0)
t = time.perf_counter()
n = 0
with WorkerPeak() as workers_peak:
    for obs, act, eps, u in loader:
        n += len(act)
epoch_s = time.perf_counter() - t
print(json.dumps({"episodes": n, "stats_s": stats_s, "epoch_s": epoch_s, "cached": ds.cache,
                  "shape": list(obs.shape[1:]), "rss_mb": own_peak_mb(), "child_rss_mb": workers_peak.mb}))
"""


def _write(args: tuple[int, str]) -> None:
    from layouts import Layout, write_layout_bag

    i, path = args
    if not Path(path).exists():
        tmp = Path(path + ".tmp")
        write_layout_bag(tmp, Layout(size=(64, 48), duration_s=2.0, depth=None, task=f"task {i % 10} take {i}"))
        tmp.rename(path)


def main() -> None:
    import yaml
    from layouts import Layout, topic_map

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--dask-shares", type=int, default=0, help="also ingest as K shares on a local Dask cluster")
    p.add_argument("--work", type=Path, help="folder for the bags and datasets (default: a temp folder)")
    a = p.parse_args()
    work = Path(a.work or tempfile.mkdtemp(prefix="adlpipe-scale-"))
    bags_dir = work / "bags"
    bags_dir.mkdir(parents=True, exist_ok=True)
    cfg = work / "topics.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(Layout(size=(64, 48), duration_s=2.0, depth=None))))
    n_max = max(a.sizes)
    bags = [bags_dir / f"b{i:05d}.mcap" for i in range(n_max)]
    t = time.perf_counter()
    with multiprocessing.get_context("fork").Pool(a.workers) as pool:
        pool.map(_write, [(i, str(b)) for i, b in enumerate(bags)], chunksize=50)
    print(f"{n_max} bags ready in {time.perf_counter() - t:.0f} s ({size_mb(bags_dir):.0f} MB)", file=sys.stderr)

    rows = {}
    for n in sorted(a.sizes):
        out = work / f"n{n}" / "adl.h5"
        shutil.rmtree(out.parent, ignore_errors=True)
        out.parent.mkdir()
        listing = work / f"n{n}.txt"
        listing.write_text("\n".join(map(str, bags[:n])))
        ing = run(INGEST, out, cfg, a.workers, listing)
        assert ing["rc"] == 0, ing
        mb = size_mb(out, out.with_name("adl.shards"))
        ep = run(EPOCH, out, a.workers)
        assert ep["episodes"] == n, ep
        row = {"ingest_s": ing["s"], "ingest_rss_mb": ing["rss_mb"], "ingest_worker_rss_mb": ing["child_rss_mb"],
               "dataset_mb": mb, "stats_s": ep["stats_s"], "epoch_s": ep["epoch_s"], "epoch_rss_mb": ep["rss_mb"],
               "epoch_worker_rss_mb": ep["child_rss_mb"], "cached": ep["cached"]}
        if a.dask_shares:
            d_out = work / f"n{n}-dask" / "adl.h5"
            shutil.rmtree(d_out.parent, ignore_errors=True)
            t = time.perf_counter()
            proc = subprocess.run([sys.executable, str(REPO / "examples" / "ingest_with_dask.py"), *map(str, bags[:n]),
                                   "-o", str(d_out), "--shares", str(a.dask_shares), "--local-workers",
                                   str(a.workers), "--", "--size", "64", "--config", str(cfg)],
                                  capture_output=True, text=True, cwd=REPO)
            if proc.returncode:
                raise SystemExit(proc.stderr[-2000:])
            row["dask_s"] = time.perf_counter() - t
        rows[n] = row
        print(f"{n} episodes: ingest {ing['s']:.0f} s ({n / ing['s']:.0f} bags/s), peak RSS {ing['rss_mb']:.0f} MB "
              f"(largest worker {ing['child_rss_mb']:.0f} MB), dataset {mb:.0f} MB; paper-preset epoch "
              f"(input {ep['shape']}) {ep['epoch_s']:.0f} s ({n / ep['epoch_s']:.0f} episodes/s) after "
              f"{ep['stats_s']:.0f} s of statistics, peak RSS {ep['rss_mb']:.0f} MB (largest worker "
              f"{ep['child_rss_mb']:.0f} MB)" + (f"; Dask, {a.dask_shares} shares on {a.workers} workers + gather: "
                                                f"{row['dask_s']:.0f} s" if a.dask_shares else ""))
    lo, hi = min(rows), max(rows)
    print(f"growth {lo} -> {hi} episodes (x{hi / lo:.0f}): " + ", ".join(
        f"{k} x{rows[hi][k] / rows[lo][k]:.2f}" for k in rows[lo] if k != "cached"))
    print(json.dumps({"workers": a.workers, "rows": rows}))


if __name__ == "__main__":
    main()
