"""Which torch thread settings to train with on a small machine, idle and shared with another job.

    python bench/threads.py [--steps 40]

One training step (forward, backward, AdamW) of the small preset's first-frame FM-CNN at batch 32 (the default
pipeline's model), timed in a fresh process per setting: torch threads 1 or 2, with OpenMP's default spin-waiting or
OMP_WAIT_POLICY=PASSIVE; each on an idle machine and beside one busy process spinning on a core (a second job on a
shared machine). Settings are interleaved over rounds; the median step of each run, the median over rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STEP = """
import json, sys, time
import torch
from adlpipe.policy.models import Policy, preset
threads, steps = int(sys.argv[1]), int(sys.argv[2])
torch.set_num_threads(threads)
torch.manual_seed(0)
cfg = preset("small", "fm_cnn")
policy = Policy(cfg)
opt = torch.optim.AdamW(policy.parameters(), lr=1e-4, fused=True)
obs = torch.randn(32, 4, cfg.image_size, cfg.image_size)
act = torch.randn(32, cfg.horizon, cfg.action_dim)
gen = torch.Generator().manual_seed(0)
times = []
for _ in range(steps):
    t = time.perf_counter()
    loss = policy.loss(obs, act, gen=gen)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    times.append((time.perf_counter() - t) * 1000)
times = sorted(times[5:])
print(json.dumps({"ms": times[len(times) // 2]}))
"""
SPIN = "while True: pass"


def step_ms(threads: int, passive: bool, steps: int) -> float:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY")}
    if passive:
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    out = subprocess.run([sys.executable, "-c", STEP, str(threads), str(steps)], capture_output=True, text=True,
                         check=True, cwd=REPO, env=env).stdout
    return json.loads(out.strip().splitlines()[-1])["ms"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--rounds", type=int, default=2)
    a = p.parse_args()
    settings = [(t, passive) for t in (1, 2) for passive in (False, True)]
    results: dict[str, list[float]] = {}
    for load in ("idle", "busy"):
        spinner = subprocess.Popen([sys.executable, "-c", SPIN]) if load == "busy" else None
        try:
            for _ in range(a.rounds):
                for threads, passive in settings:
                    key = f"{load}, {threads} thread(s){', OMP_WAIT_POLICY=PASSIVE' if passive else ''}"
                    results.setdefault(key, []).append(step_ms(threads, passive, a.steps))
        finally:
            if spinner is not None:
                spinner.kill()
    for key, v in results.items():
        print(f"{key}: {statistics.median(v):.1f} ms a step ({' / '.join(f'{x:.1f}' for x in v)})")


if __name__ == "__main__":
    main()
