"""Ingest throughput: adlpipe.ingest MB/s against raw mcap iteration of the same bags, and peak RSS.

    python bench/ingest.py [--episodes 4] [--size 224]

Records episodes with the MuJoCo recorder (or uses --bags), then times (a) iterating every record of each bag with
the mcap reader (no decoding) and (b) a full single-process ingest, each in a fresh process whose peak RSS is read
back (VmHWM, bench/peak.py). Ingest keeps only the first frame's images, so its RSS should stay flat as bags grow.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RAW = """
import sys, time
sys.path.insert(0, "bench")
from peak import own_peak_mb
from mcap.reader import make_reader
t = time.perf_counter(); n = 0
for p in sys.argv[1:]:
    with open(p, "rb") as f:
        for _ in make_reader(f).iter_messages():
            n += 1
print(time.perf_counter() - t, n, own_peak_mb())
"""
INGEST = """
import sys, time
sys.path.insert(0, "bench")
from peak import own_peak_mb
from pathlib import Path
from adlpipe.ingest import ingest
from adlpipe.bags.topics import TopicMap
t = time.perf_counter()
ingest([Path(p) for p in sys.argv[2:]], Path(sys.argv[1]), TopicMap(), 32, 224, workers=1)
print(time.perf_counter() - t, 0, own_peak_mb())
"""


def run(code: str, *args: str) -> tuple[float, float]:
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=True,
                         cwd=REPO).stdout
    secs, _n, rss_mb = out.split()
    return float(secs), float(rss_mb)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--bags", nargs="*", type=Path)
    p.add_argument("--episodes", type=int, default=2, help="episodes per task when recording (default 2)")
    p.add_argument("--tasks", nargs="+", default=["put on the hat", "comb the hair"])
    p.add_argument("--size", type=int, default=224)
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bags = args.bags
        if not bags:
            subprocess.run([sys.executable, "-m", "adlpipe.record", "--episodes", str(args.episodes), "--tasks",
                            *args.tasks, "--size", str(args.size), "--out", tmp], check=True, capture_output=True)
            bags = sorted(Path(tmp).glob("*.mcap"))
        mb = sum(b.stat().st_size for b in bags) / 1e6
        raw_s, raw_rss = run(RAW, *map(str, bags))
        t0 = time.perf_counter()
        ing_s, ing_rss = run(INGEST, str(Path(tmp) / "bench.h5"), *map(str, bags))
        largest = max(b.stat().st_size for b in bags) / 1e6
        result = {"bags": len(bags), "total_mb": round(mb, 1), "largest_bag_mb": round(largest, 1),
                  "raw_mcap_iteration_mb_s": round(mb / raw_s, 1), "ingest_mb_s": round(mb / ing_s, 1),
                  "ingest_vs_raw": round(raw_s / ing_s, 3), "raw_peak_rss_mb": round(raw_rss, 1),
                  "ingest_peak_rss_mb": round(ing_rss, 1), "wall_s": round(time.perf_counter() - t0, 1)}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
