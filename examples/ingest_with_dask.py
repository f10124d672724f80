"""Ingest bags on a Dask cluster: one task per share (ingest --shard I/N), then one --gather.

    pip install -e ".[dask]"
    python examples/ingest_with_dask.py data/bags/* -o data/adl.h5 --shares 8 --local-workers 2    # this machine
    python examples/ingest_with_dask.py data/bags/* -o data/adl.h5 --shares 64 --scheduler tcp://head:8786

Dask only places the tasks: each task is the plain command line a Slurm array would run, so what a share writes
and how a failed one is retried (run it again) is the same on any scheduler. Every worker must see the bags and
the output folder at the same paths (a shared file system). Extra arguments after `--` go to every share
(e.g. -- --size 128 --config topics.yaml).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path


def run_share(i: int, n: int, bags: list[str], output: str, extra: list[str]) -> tuple[int, int, str]:
    """One share as its own process, started by a Dask worker: (share, exit status, last error line).
    --workers 1: Dask gives the parallelism."""
    cmd = [sys.executable, "-m", "adlpipe.ingest", *bags, "-o", output, "--shard", f"{i}/{n}", "--workers", "1",
           *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    return i, proc.returncode, (proc.stderr.strip().splitlines() or [""])[-1]


def main() -> int:
    from dask.distributed import Client, LocalCluster

    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bags", nargs="+")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--shares", type=int, default=8, help="tasks (shares of the bags); more than workers balances")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (default: a local cluster)")
    p.add_argument("--local-workers", type=int, default=2, help="worker processes of the local cluster")
    a = p.parse_args(argv)
    bags = [str(Path(b).resolve()) for b in a.bags]
    output = str(Path(a.output).resolve())
    cluster = None if a.scheduler else LocalCluster(n_workers=a.local_workers, threads_per_worker=1,
                                                    processes=True, dashboard_address=None)
    with Client(a.scheduler or cluster) as client:
        futures = [client.submit(run_share, i, a.shares, bags, output, extra, pure=False)
                   for i in range(1, a.shares + 1)]
        results = client.gather(futures)
    if cluster is not None:
        cluster.close()
    failed = [(i, line) for i, rc, line in results if rc]
    for i, line in failed:
        print(f"share {i}/{a.shares} failed: {line}", file=sys.stderr)
    if failed:
        print("run the failed shares again (the same command with --shard I/N), then --gather", file=sys.stderr)
        return 1
    return subprocess.run([sys.executable, "-m", "adlpipe.ingest", "--gather", "-o", output]).returncode


if __name__ == "__main__":
    sys.exit(main())
