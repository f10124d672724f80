"""The policy server against in-process planning, and under load: what the transport costs a robot.

    python bench/serve.py --models pipelines/closed_loop/models/fm_cnn pipelines/closed_loop/models/dp_cnn \
        --data data/adl.h5 --out results/deploy/serve_bench.json
    python bench/serve.py --models M --data D --load-seconds 600 --out results/deploy/serve_load.json   # 8 clients

For each model: a real `adlpipe serve` process on loopback (one inference thread, --threads torch threads) and the
same checkpoint in this process at the same threads. The observation is a recorded test episode's frames (2 frames
of the dataset's size, its state and command), as a robot sends them. Round trip (client send to reply decoded)
and in-process planning are timed in alternating rounds, medians over --repeats each: their difference is the
transport's overhead per plan. Then plans per second with 1, 2, 4 and 8 clients at once (each its own connection,
a thread here) for --seconds each, with the median round trip a client sees. --load-seconds: 8 clients for that
long, the server's resident memory sampled every 5 s (flat: no growth with the plans served).
"""

from __future__ import annotations

import argparse
import json
import platform
import random
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import torch

from adlpipe.dataset import schema
from adlpipe.deploy import Observation, Planner
from adlpipe.deploy.client import PolicyClient

REPO = Path(__file__).resolve().parents[1]


def observation(data: Path, k: int = 10) -> Observation:
    with h5py.File(data) as f:
        g = f[schema.EPISODES][schema.episode_names(f)[0]]
        fr = g["frames"]
        state = np.concatenate([fr["ee_pos"][k - 1:k + 1], fr["gripper"][k - 1:k + 1][:, None]], 1).astype(float)
        return Observation(rgb=fr["rgb"][k - 1:k + 1], affordance=g["affordance"][()], state=state,
                           command=fr["action"][k, :3].astype(float), task=str(g.attrs["task"]))


def request(obs: Observation) -> dict:
    return {"task": obs.task, "rgb": obs.rgb, "affordance": obs.affordance, "state": obs.state,
            "command": obs.command}


def start(model: Path, threads: int, root: Path) -> tuple[subprocess.Popen, str]:
    port_file = root / f"port_{model.name}_{time.monotonic_ns()}"
    proc = subprocess.Popen([sys.executable, "-m", "adlpipe.serve", str(model), "--port", "0", "--port-file",
                             str(port_file), "--threads", str(threads)], stderr=subprocess.DEVNULL, cwd=REPO)
    while not port_file.exists():
        if proc.poll() is not None:
            raise SystemExit(f"serve {model} did not start")
        time.sleep(0.05)
    return proc, f"ws://127.0.0.1:{port_file.read_text()}"


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def round_trip_vs_in_process(url: str, planner: Planner, obs: Observation, repeats: int) -> dict:
    req = request(obs)
    with PolicyClient(url) as client:
        for _ in range(5):  # warm-up on both sides
            client.plan(**req)
            planner.plan(obs)
        series: dict[str, list[float]] = {"round_trip": [], "in_process": [], "server_inference": []}
        rng = random.Random(0)
        for _ in range(repeats):
            order = ["round_trip", "in_process"]
            rng.shuffle(order)
            for which in order:
                t0 = time.perf_counter()
                if which == "round_trip":
                    reply = client.plan(**req)
                    series["server_inference"].append(reply["timing"]["inference_ms"])
                else:
                    planner.plan(obs)
                series[which].append(1000 * (time.perf_counter() - t0))
    med = {k: statistics.median(v) for k, v in series.items()}
    diffs = sorted(a - b for a, b in zip(series["round_trip"], series["in_process"], strict=True))
    return {**{f"{k}_ms": round(v, 2) for k, v in med.items()},
            "overhead_ms": round(med["round_trip"] - med["in_process"], 2),
            "overhead_iqr_ms": [round(diffs[len(diffs) // 4], 2), round(diffs[3 * len(diffs) // 4], 2)]}


def hammer(url: str, obs: Observation, clients: int, seconds: float, server_pid: int | None = None) -> dict:
    """clients connections planning back to back for `seconds`: plans per second, each client's median round trip,
    and (with server_pid) the server's RSS every 5 s."""
    req = request(obs)
    stop = threading.Event()
    times: list[list[float]] = [[] for _ in range(clients)]
    errors: list[str] = []

    def run(i: int) -> None:
        try:
            with PolicyClient(url, seed=i) as c:
                while not stop.is_set():
                    t0 = time.perf_counter()
                    c.plan(**req)
                    times[i].append(1000 * (time.perf_counter() - t0))
        except Exception as exc:  # noqa: BLE001 - reported, not raised: the bench counts what failed
            errors.append(f"{type(exc).__name__}: {exc}")

    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    rss, t_start = [], time.monotonic()
    while time.monotonic() - t_start < seconds:
        time.sleep(min(5.0, seconds))
        if server_pid is not None:
            rss.append((round(time.monotonic() - t_start), round(rss_mb(server_pid), 1)))
    stop.set()
    for t in threads:
        t.join()
    n = sum(len(t) for t in times)
    out = {"clients": clients, "seconds": seconds, "plans": n, "plans_per_s": round(n / seconds, 1),
           "median_round_trip_ms": round(statistics.median([x for t in times for x in t]), 2),
           "plans_per_client": [len(t) for t in times], "errors": errors}
    if rss:
        out["server_rss_mb"] = rss
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", type=Path, required=True)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=100)
    p.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4, 8])
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--load-seconds", type=float, default=0.0)
    p.add_argument("--out", type=Path)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    obs = observation(args.data)
    root = Path("/tmp")
    result: dict = {"host": {"machine": platform.machine(), "processor": platform.processor(),
                             "cpus": __import__("os").cpu_count(), "torch": torch.__version__,
                             "threads": args.threads}, "image": list(obs.rgb.shape), "models": {}}
    for model in args.models:
        planner = Planner.load(model)
        proc, url = start(model, args.threads, root)
        try:
            row: dict = {"steps": planner.spec.steps, "family": planner.spec.family}
            if args.load_seconds:
                row["load"] = hammer(url, obs, 8, args.load_seconds, proc.pid)
            else:
                row["latency"] = round_trip_vs_in_process(url, planner, obs, args.repeats)
                row["throughput"] = [hammer(url, obs, c, args.seconds) for c in args.clients]
            print(json.dumps({model.name: row}), flush=True)
            result["models"][str(model)] = row
        finally:
            proc.terminate()
            proc.wait()
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
