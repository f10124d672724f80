"""Where a default training's time goes: one optimiser step split into its parts, and an epoch's share of
validation and checkpointing, for each model of the default trio at each thread setting (time to a decision).

    python bench/train_profile.py [--epochs 30] -o results/bench/train_profile.json   # on the default's data/

Each (model, threads) runs in a fresh process with the default stage's settings (`adlpipe train`'s own parser and
model configuration: small preset, batch 32, the loader in the main process) on the default pipeline's data. The
step is `training.loop.optimise_epoch`'s, timed part by part: the next batch from the real loader (HDF5 read,
decode, augmentation), forward with the loss, backward with gradient clipping, AdamW and the schedule, the EMA
update. Per epoch: the resumable checkpoint the loop writes after every epoch (last.pt), and the validation the
loop runs every --val-every epochs (test loss and val px), shared over those epochs. The first 5 epochs warm up
and are not counted; medians over the rest.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PHASES = ("loader", "forward", "backward", "optimiser", "ema")


def profile(data: Path, split: Path, model: str, threads: int, epochs: int, val_every: int) -> dict:
    import torch
    from torch.utils.data import DataLoader

    from adlpipe.dataset.loader import Augment, Normalizer
    from adlpipe.dataset.sampling import EpochSampler, TrainingSamples
    from adlpipe.dataset.splits import load_split
    from adlpipe.plumbing.runtime import Ranks
    from adlpipe.policy.checkpoint import save_atomic
    from adlpipe.policy.objectives import Noise
    from adlpipe.train import model_config, parse_args
    from adlpipe.training.data import datasets, training_batches, training_episodes
    from adlpipe.training.loop import optimisation, resumable
    from adlpipe.training.validation import measure, validation_set

    torch.set_num_threads(threads)
    args = parse_args(["--model", model, "--data", str(data), "--split", str(split), "--threads", str(threads)])
    cfg, device, ranks = model_config(args), torch.device("cpu"), Ranks()
    sp = load_split(split)
    train_names, val_names, stored, _ = training_episodes(data, sp, cfg, 0.1, 0)
    stats, train_ds, test_ds, val_ds = datasets(data, cfg, sp, train_names, val_names,
                                                Augment(stored, crop=cfg.crop), 0)
    norm = Normalizer(stats)
    val_obs, val_target = validation_set(val_ds, norm, cfg, device)
    loader = training_batches(train_ds, cfg, 32, 0, 0, device, ranks)
    test_loader = DataLoader(TrainingSamples(test_ds, 0), batch_size=32,
                             sampler=EpochSampler(len(test_ds), shuffle=False), num_workers=0)
    torch.manual_seed(0)
    policy, net, opt, sched, ema = optimisation(cfg, device, ranks, 1e-3, 1e-6, 500, 800 * len(loader))
    steps: dict[str, list[float]] = {k: [] for k in PHASES}
    epoch_s, save_s, val_s = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for epoch in range(epochs):
            t_epoch = time.perf_counter()
            loader.set_epoch(epoch)
            net.train()
            it = iter(loader)
            while True:
                t0 = time.perf_counter()
                batch = next(it, None)
                if batch is None:
                    break
                obs, act, eps, u = batch
                t1 = time.perf_counter()
                loss = net(obs, act, Noise(eps, u))
                t2 = time.perf_counter()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
                t3 = time.perf_counter()
                opt.step()
                sched.step()
                t4 = time.perf_counter()
                ema.update(policy)
                t5 = time.perf_counter()
                if epoch >= 5:
                    for k, a, b in zip(PHASES, (t0, t1, t2, t3, t4), (t1, t2, t3, t4, t5), strict=True):
                        steps[k].append(b - a)
            t_save = time.perf_counter()
            save_atomic(resumable(policy, ema, opt, sched, epoch + 1, [], cfg, {}, stats), Path(tmp) / "last.pt")
            done = time.perf_counter()
            if epoch >= 5:
                save_s.append(done - t_save)
                epoch_s.append(done - t_epoch)
            if epoch in (5, epochs - 1):  # two validations: the loop's every --val-every epochs
                t_val = time.perf_counter()
                measure(ema.model, test_loader, val_obs, val_target, norm, 0, device, "fp32")
                val_s.append(time.perf_counter() - t_val)
    ms = {k: round(1000 * statistics.median(v), 2) for k, v in steps.items()}
    per_epoch, validation, save = (statistics.median(x) for x in (epoch_s, val_s, save_s))
    total = 800 * per_epoch + math.ceil(800 / val_every) * validation  # the default: 800 epochs, val every 20
    share = {**{k: v / 1000 * len(loader) * 800 for k, v in ms.items()}, "checkpoint": 800 * save,
             "validation": math.ceil(800 / val_every) * validation}
    return {"model": model, "threads": threads, "steps_per_epoch": len(loader), "step_ms": ms,
            "step_total_ms": round(sum(ms.values()), 2), "checkpoint_ms": round(1000 * save, 1),
            "epoch_s": round(per_epoch, 4), "validation_s": round(validation, 3), "run_800_epochs_s": round(total, 1),
            "shares": {k: round(v / total, 3) for k, v in share.items()}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, default=Path("data/split.json"))
    p.add_argument("--models", nargs="+", default=["fm_cnn", "dp_cnn", "bc_cnn"])
    p.add_argument("--threads", type=int, nargs="+", default=[2, 1])
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--val-every", type=int, default=20)
    p.add_argument("-o", "--out", type=Path)
    p.add_argument("--one", nargs=2, metavar=("MODEL", "THREADS"), help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.one:
        print(json.dumps(profile(a.data, a.split, a.one[0], int(a.one[1]), a.epochs, a.val_every)))
        return
    runs = []
    for threads in a.threads:
        for model in a.models:
            cmd = [sys.executable, __file__, "--data", str(a.data), "--split", str(a.split), "--epochs",
                   str(a.epochs), "--val-every", str(a.val_every), "--one", model, str(threads)]
            runs.append(json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout))
            r = runs[-1]
            print(f"{model} threads {threads}: step {r['step_total_ms']} ms {r['step_ms']}, checkpoint "
                  f"{r['checkpoint_ms']} ms, epoch {r['epoch_s']} s, validation {r['validation_s']} s, "
                  f"800 epochs {r['run_800_epochs_s']} s", flush=True)
    if a.out:
        import torch

        from adlpipe.plumbing.runtime import host
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"host": host(torch.device("cpu")), "runs": runs}, indent=1) + "\n")


if __name__ == "__main__":
    main()
