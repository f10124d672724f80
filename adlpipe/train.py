"""Train one of the policies with the one training loop.

    python -m adlpipe.train --model fm_cnn --data data/adl.h5 --split data/split.json --out models/fm_cnn

Diffusion Policy's optimiser settings for every model alike: AdamW (betas 0.95/0.999, weight decay 1e-6), cosine
schedule after 500 linear warm-up steps, EMA weights (decay capped at 0.9999; used for the losses, validation and
inference). Gradients are clipped at norm 1 for every model alike (--grad-clip 0: none, as Diffusion Policy at its lr
of 1e-4; the small preset trains at 1e-3); README measures the clip's effect on each objective.
A validation part of the train split (--val-fraction, stratified per task, seeded) is held out; every
--val-every epochs the EMA policy's val px (mean per-waypoint pixel error with the model's default sampler: FM 1
Euler step, DP 16 DDPM steps, BC direct) is measured, and the best EMA weights are kept in best.pt beside the last
ones in model.pt. A model whose best val px still fell by more than 2 % over the last fifth of training is marked
"converged": false in metrics.json. Every model trains for the same number of optimiser steps (epochs x batches).
The train loss of every epoch, and the test loss and val px of every --val-every epochs, go to a CSV that
`dvc plots` reads. A checkpoint is written atomically
after every epoch; re-running the same command resumes from it (after a kill, too), and each epoch's randomness
comes from (seed, epoch), so a resumed run ends where an uninterrupted one does. Checkpoints hold only tensors and
plain values: they load with torch.load(weights_only=True).

Training augments (a random shift of the image stack with the pixel targets moved alike, colour jitter); --no-augment
turns it off; validation and test never augment. --closed-loop trains on every frame (adlpipe.dataset.loader
.WindowDataset): To frames with the measured end effector and gripper at each in, the next Tp waypoints at a fixed
rate out: by default (--target command) of the commanded end effector (the bags' action stream), relative to the
command now, so that replay anchors each plan where the last one left the command, not at the lagging measurement.
An epoch draws as many windows as there are training episodes, uniformly over
every frame of every episode, so a closed-loop model takes the same optimiser steps as a first-frame one.
--target action learns the bags' action stream from their
state stream (val px is then the action's error in its own units); --no-image drops the image encoder, so the state
alone conditions the model (the seed's Franka Kitchen setting).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import csv
import math
import os
import shutil
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from .atomic import atomic_path, write_json_atomic
from .cli import NON_NEGATIVE, POSITIVE, SEED, Parser, float_range, int_range
from .dataset import schema
from .dataset.loader import (
    OPEN_FILES,
    STATE_DIM,
    Augment,
    Normalizer,
    TrajectoryDataset,
    WindowDataset,
    Windows,
    check_cameras,
    compute_action_stats,
    compute_stats,
    compute_window_stats,
)
from .dataset.memory_windows import MAX_BYTES, MemoryBatches, memory_bytes
from .dataset.sampling import EpochSampler, TrainingSamples
from .dataset.splits import load_split, make_split, recording_keys
from .dvc_outputs import refuse_pipeline_outputs
from .errors import AdlError, run_cli
from .lock import exclusive
from .policy.checkpoint import load_checkpoint, save_atomic
from .policy.models import MODELS, PRESET_LR, PRESETS, ModelConfig, Observation, Policy, preset
from .policy.nets.resnet import POOLS
from .policy.objectives import Noise
from .policy.optim import ADAMW_BETAS, EMA, WARMUP_STEPS, cosine_with_warmup
from .runtime import (
    Ranks,
    add_device_args,
    all_sum,
    autocast,
    barrier,
    generator,
    process_group,
    resolve_device,
    to_device,
)
from .stats import mean_interval

LOG_FIELDS = ["epoch", "step", "train_loss", "test_loss", "val_px", "lr", "seconds"]
CONVERGENCE_TOLERANCE = 0.02  # best val px may fall by at most 2 % over the last fifth of training


@torch.no_grad()
def evaluate_loss(policy: Policy, loader: DataLoader, device: torch.device, precision: str) -> float:
    """Mean loss over the loader (its samples carry fixed noise: comparable test losses from epoch to epoch)."""
    total, n = 0.0, 0
    for obs, act, eps, u in loader:
        obs, act, eps, u = to_device((obs, act, eps, u), device)
        with autocast(device, precision):
            total += float(policy.loss(obs, act, Noise(eps, u))) * len(act)
        n += len(act)
    return total / max(n, 1)


def collate_obs(items: list) -> Observation:
    """Stack observations: image tensors, or (image, state) pairs of closed-loop windows."""
    if isinstance(items[0], tuple | list):
        return tuple(torch.stack(parts) for parts in zip(*items, strict=True))
    return torch.stack(items)


def val_dims(cfg: ModelConfig) -> int:
    """How many target dimensions the validation error measures: the waypoints' pixels (u, v), or the whole
    recorded action (Push-T's is a pixel position; Franka Kitchen's, joint velocities)."""
    return cfg.action_dim if cfg.target == "action" else 2


def validation_px(policy: Policy, obs: Observation, target_px: torch.Tensor, norm: Normalizer, seed: int,
                  precision: str = "fp32") -> list[float]:
    """Per validation episode, the mean per-waypoint error (L2, the target's units: pixels, or the action's) of the
    default sampler (same noise every time); their mean is the val px that selects checkpoints."""
    device = target_px.device
    with autocast(device, precision):
        pred = policy.predict(obs, policy.default_steps, None, generator(device, seed))
    err = (norm.unnormalize(pred)[..., :target_px.shape[-1]] - target_px).norm(dim=-1)
    return err.flatten(1).mean(1).tolist()


def converged(history: list[dict], tolerance: float = CONVERGENCE_TOLERANCE) -> bool:
    """False if the best val px over the whole run is more than `tolerance` below the best of its first 4/5."""
    vals = [(r["epoch"], r["val_px"]) for r in history if r.get("val_px") is not None]
    if len(vals) < 2:
        return False
    cut = 0.8 * history[-1]["epoch"]
    early = [v for e, v in vals if e <= cut]
    return bool(early) and min(v for _, v in vals) >= (1 - tolerance) * min(early)


def split_validation(tasks: dict[str, str], fraction: float, seed: int,
                     keys: dict[str, str] | None = None) -> tuple[list[str], list[str]]:
    """(train, val): a stratified, seeded part of the train split (tasks: episode -> task) held out for checkpoint
    selection, ordered by the recording keys as the split is."""
    if fraction <= 0:
        return list(tasks), []
    parts = make_split(tasks, fraction, seed + 1, keys)
    return parts["train"], parts["test"]


def stream_sizes(data: Path) -> tuple[int, int]:
    """(state size, action size) of the first episode's per-frame streams (one line if it has none)."""
    with schema.open_dataset(data) as f:
        names = schema.episode_names(f)
        fr = f[schema.EPISODES][names[0]].get("frames") if names else None
        if fr is None or "state" not in fr or "action" not in fr:
            raise AdlError(f"{data}: no state/action per frame; ingest with the topic map's state and action topics "
                           "(--target action needs them)")
        return int(fr["state"].shape[1]), int(fr["action"].shape[1])


def datasets(data: Path, cfg: ModelConfig, split: dict, train_names: list[str], val_names: list[str],
             aug: Augment | None, seed: int, windows_per_epoch: str = "episodes", open_files: int = OPEN_FILES
             ) -> tuple[dict, Dataset, Dataset, Dataset | None]:
    """(stats, train, test, val) datasets of the model's kind: windows of every frame (closed loop) or first frames.
    aug: the training augmentation (validation and test never augment). windows_per_epoch (closed loop): an epoch
    draws as many windows as there are training episodes ("episodes") or every window once ("all")."""
    if cfg.closed_loop:
        w = Windows(cfg.n_obs, cfg.horizon, cfg.rate_hz, cfg.target, cfg.use_image)
        stats = (compute_action_stats(data, train_names) if cfg.target == "action"
                 else compute_window_stats(data, train_names, w))

        def windows(names: list[str], **kw: object) -> WindowDataset:
            return WindowDataset(data, names, stats, cfg.image_size, w, cfg.use_depth, seed=seed, cameras=cfg.cameras,
                                 **kw)

        train_ds = windows(train_names, augment=aug, draws_per_epoch=len(train_names), open_files=open_files)
        if windows_per_epoch == "all":
            train_ds.draws = len(train_ds.items)
        return (stats, train_ds,
                windows(split["test"] or train_names, frames_per_episode=2),
                windows(val_names, frames_per_episode=4) if val_names else None)
    stats = compute_stats(str(data), train_names)

    def firsts(names: list[str], **kw: object) -> TrajectoryDataset:
        return TrajectoryDataset(str(data), names, stats, cfg.image_size, cfg.use_depth, cameras=cfg.cameras, **kw)

    return (stats, firsts(train_names, augment=aug, seed=seed), firsts(split["test"] or train_names),
            firsts(val_names, cache=False) if val_names else None)


class LoaderBatches:
    """The streamed training batches: one DataLoader for the run (its workers, each with its own HDF5 handles, live
    as long as it does) over (epoch, index) keys."""

    def __init__(self, train_ds: Dataset, batch_size: int, seed: int, workers: int, device: torch.device,
                 ranks: Ranks) -> None:
        self.sampler = EpochSampler(len(train_ds), ranks.world, ranks.rank, seed)
        self.loader = DataLoader(TrainingSamples(train_ds, seed), batch_size=batch_size // ranks.world,
                                 sampler=self.sampler, num_workers=workers, persistent_workers=workers > 0,
                                 pin_memory=device.type == "cuda")

    def set_epoch(self, epoch: int) -> None:
        self.sampler.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.loader)

    def __iter__(self) -> Iterator:
        return iter(self.loader)


def training_batches(train_ds: Dataset, cfg: ModelConfig, batch_size: int, seed: int, workers: int,
                     device: torch.device, ranks: Ranks) -> LoaderBatches | MemoryBatches:
    """A state-only closed-loop model's windows from memory (no per-sample loading: a batch is one gather) when they
    fit; otherwise streamed."""
    if isinstance(train_ds, WindowDataset) and not cfg.use_image:
        if memory_bytes(train_ds, cfg.state_dim + cfg.horizon * cfg.action_dim) <= MAX_BYTES:
            every = copy.copy(train_ds)  # the same windows, item i = window i
            every.draws = None
            return MemoryBatches(every, batch_size, len(train_ds), seed, ranks.world, ranks.rank)
    return LoaderBatches(train_ds, batch_size, seed, workers, device, ranks)


def train(data: Path, split_path: Path, out: Path, cfg: ModelConfig, epochs: int, batch_size: int = 32,
          lr: float = 1e-4, weight_decay: float = 1e-6, warmup_steps: int = WARMUP_STEPS, grad_clip: float = 1.0,
          seed: int = 0, log_csv: Path | None = None, progress: bool = False, stop_after_epoch: int | None = None,
          val_fraction: float = 0.1, val_every: int = 5, augment: bool = True, workers: int = 0,
          device: torch.device | None = None, precision: str = "fp32", ranks: Ranks | None = None,
          windows_per_epoch: str = "episodes", save_every: int = 0, open_files: int = OPEN_FILES,
          resume_dir: Path | None = None) -> dict:
    """Train (or resume) and return the final metrics. stop_after_epoch simulates an interruption (tests).
    resume_dir: where a run in progress keeps its checkpoints (default: out; see publish). batch_size is the global
    batch: under torchrun (ranks) each process takes batch_size / world of it; rank 0
    validates, logs and writes the checkpoints. save_every: also keep the EMA weights of every this many epochs
    in <out>/checkpoints/ (the benchmark's learning curves)."""
    device, ranks = device or torch.device("cpu"), ranks or Ranks()
    out.mkdir(parents=True, exist_ok=True)
    work = resume_dir or out
    work.mkdir(parents=True, exist_ok=True)
    split = load_split(split_path)
    check_run(split, split_path, batch_size, ranks)
    train_names, val_names, stored_size = training_episodes(data, split, cfg, val_fraction, seed)
    aug = Augment(stored_size, crop=cfg.crop) if augment else None  # windows without images skip it
    stats, train_ds, test_ds, val_ds = datasets(data, cfg, split, train_names, val_names, aug, seed,
                                                windows_per_epoch, open_files)
    norm = Normalizer(stats)
    val_obs, val_px_target = validation_set(val_ds, norm, cfg, device) if ranks.main else (None, None)
    loader = training_batches(train_ds, cfg, batch_size, seed, workers, device, ranks)
    test_loader = DataLoader(TrainingSamples(test_ds, seed), batch_size=batch_size,
                             sampler=EpochSampler(len(test_ds), shuffle=False), num_workers=0)
    steps_per_epoch = len(loader)
    hparams = {"epochs": epochs, "batch_size": batch_size, "lr": lr, "weight_decay": weight_decay,
               "warmup_steps": warmup_steps, "grad_clip": grad_clip, "seed": seed, "data": str(data),
               "split": sorted(split["train"]),
               "val_fraction": val_fraction, "val_every": val_every, "augment": augment,
               "windows_per_epoch": windows_per_epoch}

    torch.manual_seed(seed)
    policy, model, opt, sched, ema = optimisation(cfg, device, ranks, lr, weight_decay, warmup_steps,
                                                  epochs * steps_per_epoch)
    last = work / "last.pt"
    history, start_epoch = resume(last, cfg, hparams, policy, ema, opt, sched, replace_stale=resume_dir is not None)
    best_px = min((r["val_px"] for r in history if r.get("val_px") is not None), default=math.inf)

    def inference_checkpoint(epoch: int) -> dict:
        """What evaluate, replay and inspect load: the EMA weights with their config, stats and history."""
        return {"ema": ema.model.state_dict(), "config": cfg.to_dict(), "stats": stats, "history": history,
                "hparams": hparams, "epoch": epoch}

    bar = tqdm(range(start_epoch, epochs), initial=start_epoch, total=epochs, desc=f"train {cfg.model}",
               unit="epoch", file=sys.stderr, disable=None if progress and ranks.main else True)
    for epoch in bar:
        t0 = time.time()
        loader.set_epoch(epoch)  # the epoch's permutation, windows, augmentation and noise: resumable exactly
        total, n = optimise_epoch(model, policy, loader, opt, sched, ema, grad_clip, device, precision,
                                  f"{cfg.model}: training diverged", f"epoch {epoch + 1}", last)
        total, n = all_sum([total, n], device, ranks)
        if ranks.main:
            val_px, val_ci, test_loss = None, None, None
            if (epoch + 1) % val_every == 0 or epoch + 1 == epochs:  # with validation: the test loss is for the
                # curves, and every epoch it cost a tenth of the training time
                test_loss, val_px, val_ci = measure(ema.model, test_loader, val_obs, val_px_target, norm, seed,
                                                    device, precision)
            row = {"epoch": epoch + 1, "step": (epoch + 1) * steps_per_epoch, "train_loss": total / n,
                   "test_loss": test_loss, "val_px": val_px, "val_px_ci": val_ci, "lr": sched.get_last_lr()[0],
                   "seconds": time.time() - t0}
            history.append(row)
            bar.set_postfix(train=f"{row['train_loss']:.4f}")
            if val_px is not None and val_px < best_px:  # written before last.pt: a resumed run never lacks it
                best_px = val_px
                save_atomic(inference_checkpoint(epoch + 1), work / "best.pt")
            if save_every and (epoch + 1) % save_every == 0:
                save_atomic(inference_checkpoint(epoch + 1),
                            work / "checkpoints" / f"step_{(epoch + 1) * steps_per_epoch:07d}.pt")
            save_atomic(resumable(policy, ema, opt, sched, epoch + 1, history, cfg, hparams, stats), last)
        barrier(ranks)  # the others wait while rank 0 validates and writes
        if stop_after_epoch is not None and epoch + 1 >= stop_after_epoch:
            return {"interrupted_at": epoch + 1}
    if not ranks.main:
        return {}
    publish(inference_checkpoint(epochs), work, out)
    final = final_metrics(history, cfg, epochs, steps_per_epoch, len(train_names), len(val_names), ranks, device,
                          precision)
    write_json_atomic(out / "metrics.json", final)
    write_log(log_csv, history)
    return final


def write_log(log_csv: Path | None, history: list[dict]) -> None:
    """The per-epoch CSV that dvc plots reads (plain columns only)."""
    if log_csv is not None:
        with atomic_path(log_csv) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, LOG_FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(history)



def training_episodes(data: Path, split: dict, cfg: ModelConfig, val_fraction: float,
                      seed: int) -> tuple[list[str], list[str], int]:
    """(train, validation) episodes of the split's train part, and the dataset's stored image size; the data must
    hold the model's cameras and (first-frame models) its horizon."""
    with schema.open_dataset(data, split["train"] + split["test"]) as f:
        horizon, stored_size = int(f.attrs["n_waypoints"]), int(f.attrs["image_size"])
        tasks = {n: str(f[schema.EPISODES][n].attrs["task"]) for n in split["train"]}
        keys = recording_keys(f, split["train"])
        check_cameras(f, split["train"] + split["test"], cfg.cameras, str(data))
    if horizon != cfg.horizon and not cfg.closed_loop:
        raise AdlError(f"{data}: trajectories of {horizon} waypoints, the model is configured for {cfg.horizon}")
    return (*split_validation(tasks, val_fraction, seed, keys), stored_size)


def validation_set(val_ds: Dataset | None, norm: Normalizer, cfg: ModelConfig,
                   device: torch.device) -> tuple[Observation | None, torch.Tensor | None]:
    """The validation episodes' observations and their targets in the target's units, on the device, once."""
    if val_ds is None:
        return None, None
    items = [val_ds[i] for i in range(len(val_ds))]
    obs = to_device(collate_obs([o for o, _ in items]), device)
    return obs, norm.unnormalize(torch.stack([a for _, a in items]))[..., :val_dims(cfg)].to(device)


@torch.no_grad()
def measure(model: Policy, test_loader: DataLoader, val_obs: Observation | None, val_target: torch.Tensor | None,
            norm: Normalizer, seed: int, device: torch.device,
            precision: str) -> tuple[float, float | None, list[float] | None]:
    """(test loss, val px, its interval) of the EMA model; no val px without a validation part."""
    test_loss = evaluate_loss(model, test_loader, device, precision)
    if val_obs is None:
        return test_loss, None, None
    per_episode = validation_px(model, val_obs, val_target, norm, seed, precision)
    return test_loss, float(np.mean(per_episode)), list(mean_interval(per_episode))


def resumable(policy: Policy, ema: EMA, opt: torch.optim.Optimizer, sched: object, epoch: int, history: list[dict],
              cfg: ModelConfig, hparams: dict, stats: dict) -> dict:
    """last.pt: everything a killed run needs to go on exactly where it stopped."""
    return {"model": policy.state_dict(), "ema": ema.model.state_dict(), "ema_step": ema.step,
            "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "epoch": epoch, "history": history,
            "config": cfg.to_dict(), "hparams": hparams, "stats": stats}


def optimise_epoch(model: torch.nn.Module, policy: Policy, loader: object, opt: torch.optim.Optimizer, sched: object,
                   ema: EMA, grad_clip: float, device: torch.device, precision: str, diverged: str, when: str,
                   last: Path) -> tuple[float, int]:
    """One epoch of optimiser steps: (sum of the batch losses x batch sizes, samples). A non-finite gradient
    stops training before the weights or last.pt take it (the same on every process: gradients are synchronised)."""
    model.train()
    total, n = 0.0, 0
    for batch in loader:
        obs, act, eps, u = to_device(batch, device)
        with autocast(device, precision):
            loss = model(obs, act, Noise(eps, u))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(policy.parameters(), grad_clip or math.inf)
        if not torch.isfinite(grad_norm):
            raise AdlError(f"{diverged} (loss {float(loss.detach())}, gradient norm {float(grad_norm)} in {when}); "
                           f"the last good checkpoint is kept in {last}; try a lower --lr")
        opt.step()
        sched.step()
        ema.update(policy)
        total += loss.item() * len(act)
        n += len(act)
    return total, n


def resume(last: Path, cfg: ModelConfig, hparams: dict, policy: Policy, ema: EMA, opt: torch.optim.Optimizer,
           sched: object, replace_stale: bool = False) -> tuple[list[dict], int]:
    """(history, epochs done) from the checkpoint a killed run left, its state loaded into the model, EMA,
    optimiser and schedule; ([], 0) without one. A checkpoint of other settings is one line, or (replace_stale)
    removed with best.pt and checkpoints/ beside it."""
    if not last.exists():
        return [], 0
    ck = load_checkpoint(last)
    if (ck.get("config") != cfg.to_dict() or ck.get("hparams") != hparams) and replace_stale:
        print(f"{last}: a checkpoint of other settings; training from scratch", file=sys.stderr)
        for name in ("last.pt", "best.pt"):
            (last.parent / name).unlink(missing_ok=True)
        shutil.rmtree(last.parent / "checkpoints", ignore_errors=True)
        return [], 0
    if ck.get("config") != cfg.to_dict() or ck.get("hparams") != hparams:
        raise AdlError(f"{last}: checkpoint is from other settings; remove {last.parent} (or use --restart) to retrain")
    print(f"{last}: resuming after epoch {int(ck['epoch'])}", file=sys.stderr)
    policy.load_state_dict(ck["model"])
    ema.model.load_state_dict(ck["ema"])
    ema.step = int(ck["ema_step"])
    opt.load_state_dict(ck["optimizer"])
    sched.load_state_dict(ck["scheduler"])
    return list(ck["history"]), int(ck["epoch"])


def optimisation(cfg: ModelConfig, device: torch.device, ranks: Ranks, lr: float, weight_decay: float,
                 warmup_steps: int, total_steps: int) -> tuple[Policy, torch.nn.Module, torch.optim.Optimizer, object,
                                                            EMA]:
    """(policy, the module to train: the policy, or under torchrun its DistributedDataParallel wrapper, which
    averages the gradients over the processes in backward; AdamW, its schedule, the EMA weights)."""
    policy = Policy(cfg).to(device)
    model = DistributedDataParallel(policy, device_ids=[device.index] if device.type == "cuda" else None) \
        if ranks.world > 1 else policy
    opt = torch.optim.AdamW(policy.parameters(), lr=lr, betas=ADAMW_BETAS, weight_decay=weight_decay, fused=True)
    return policy, model, opt, cosine_with_warmup(opt, warmup_steps, total_steps), EMA(policy)


def check_run(split: dict, split_path: Path, batch_size: int, ranks: Ranks) -> None:
    if not split["train"]:
        raise AdlError(f"{split_path}: the train split is empty")
    if batch_size % ranks.world:
        raise AdlError(f"--batch-size {batch_size}: the global batch must split evenly over {ranks.world} processes")


def publish(final: dict, work: Path, out: Path) -> None:
    """A finished run's model.pt (the final EMA weights) into out, and best.pt (the last weights without a
    validation part). A run kept in a resume folder (a DVC stage's: DVC deletes a stage's outputs before it runs it
    again, so its checkpoints live apart) moves best.pt and checkpoints/ into out and removes the folder."""
    save_atomic(final, out / "model.pt")
    if not (work / "best.pt").exists():
        save_atomic(final, work / "best.pt")
    if work == out:
        return
    os.replace(work / "best.pt", out / "best.pt")
    if (work / "checkpoints").exists():
        shutil.rmtree(out / "checkpoints", ignore_errors=True)
        shutil.move(work / "checkpoints", out / "checkpoints")
    shutil.rmtree(work)


def final_metrics(history: list[dict], cfg: ModelConfig, epochs: int, steps_per_epoch: int, n_train: int, n_val: int,
                  ranks: Ranks, device: torch.device, precision: str) -> dict:
    """metrics.json: the run's losses, its best and last val px with their intervals, and whether it converged."""
    vals = [r for r in history if r.get("val_px") is not None]
    best = min(vals, key=lambda r: r["val_px"]) if vals else None
    final = {"model": cfg.model, "epochs": epochs, "optimizer_steps": epochs * steps_per_epoch,
             "train_episodes": n_train, "val_episodes": n_val,
             "train_loss": history[-1]["train_loss"], "test_loss": history[-1]["test_loss"],
             "val_px_last": vals[-1]["val_px"] if vals else None, "val_px_best": best["val_px"] if best else None,
             "val_px_last_ci": vals[-1].get("val_px_ci") if vals else None,
             "val_px_best_ci": best.get("val_px_ci") if best else None,
             "best_epoch": best["epoch"] if best else epochs, "converged": converged(history),
             "val_history": [[r["epoch"], r["val_px"]] for r in vals], "processes": ranks.world,
             "device": device.type, "precision": precision,
             "seconds": sum(r["seconds"] for r in history)}
    return final


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = Parser("python -m adlpipe.train", __doc__)
    p.add_argument("--model", required=True, choices=sorted(MODELS))
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--out", type=Path, help="output folder (default: models/<model>)")
    p.add_argument("--config", choices=sorted(PRESETS), default="small",
                   help="small: trains on 2 CPU cores in minutes (default); paper: 224x224, full-size networks")
    p.add_argument("--image-size", type=int_range(16, 1024), help="override the preset's input size")
    p.add_argument("--depth", action="store_true", help="add the depth image as an input channel")
    p.add_argument("--epochs", type=POSITIVE, default=100)
    p.add_argument("--batch-size", type=POSITIVE, default=32)
    p.add_argument("--lr", type=float_range(0, 1, lo_open=True),
                   help="AdamW learning rate (default: the preset's, small 1e-3, paper 1e-4)")
    p.add_argument("--weight-decay", type=float_range(0, 1), default=1e-6)
    p.add_argument("--warmup-steps", type=NON_NEGATIVE, default=WARMUP_STEPS,
                   help=f"linear learning-rate warm-up (default {WARMUP_STEPS}, Diffusion Policy's)")
    p.add_argument("--grad-clip", type=float_range(0, 1e6), default=1.0,
                   help="clip the gradient norm at this (default 1; 0: no clipping, as Diffusion Policy at lr 1e-4)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--threads", type=NON_NEGATIVE, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--log", type=Path, help="per-epoch CSV for dvc plots (default: <out>/log.csv)")
    p.add_argument("--val-fraction", type=float_range(0, 0.9), default=0.1,
                   help="part of the train split held out for validation and checkpoint selection (0: none)")
    p.add_argument("--val-every", type=POSITIVE, default=5, help="measure val px every N epochs (and at the last)")
    p.add_argument("--workers", type=int_range(0, 64), default=0,
                   help="DataLoader worker processes (per training process) that load and augment batches beside "
                   "training; they persist for the whole run (default 0: the training process loads)")
    p.add_argument("--open-files", type=int_range(1, 100_000), default=OPEN_FILES,
                   help=f"closed loop: episode files each loader process keeps open (default {OPEN_FILES}; about "
                   "0.6 MB each: as many as the training episodes makes random windows about 1.6x cheaper)")
    p.add_argument("--windows-per-epoch", choices=["episodes", "all"], default="episodes",
                   help="closed loop: an epoch draws as many windows as there are training episodes (default: as "
                   "many optimiser steps as a first-frame model) or every window once (all)")
    p.add_argument("--save-every", type=NON_NEGATIVE, default=0,
                   help="keep the EMA weights of every N epochs in <out>/checkpoints/ for learning curves "
                   "(benchmark --curve; default 0: none)")
    p.add_argument("--resume-dir", type=Path,
                   help="keep the checkpoints of the run in progress here (default: in --out); a finished run "
                        "moves best.pt into --out and removes it. For DVC stages, whose outputs DVC deletes "
                        "before it runs a stage again: a killed `dvc repro` then resumes where it stopped")
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint and train from scratch")
    p.add_argument("--no-augment", action="store_true",
                   help="train without random shifts and colour jitter (on by default; never at evaluation)")
    p.add_argument("--closed-loop", action="store_true",
                   help="train on every frame: --obs-frames frames in, the next --action-steps waypoints at "
                   "--rate-hz out (for replay --closed-loop); default: the first frame -> the whole trajectory")
    p.add_argument("--obs-frames", type=int_range(1, 16), default=2, help="closed loop: To (default 2)")
    p.add_argument("--action-steps", type=int_range(4, 256), default=16,
                   help="closed loop: Tp, a multiple of 4 (default 16)")
    p.add_argument("--rate-hz", type=float_range(0.1, 1000), default=10.0,
                   help="closed loop: waypoint rate (default 10 Hz)")
    p.add_argument("--no-image", action="store_true",
                   help="closed loop: a state-only model (no image encoder; the state stream alone conditions it, "
                   "as the seed's Franka Kitchen policies)")
    p.add_argument("--cameras", nargs="+", metavar="NAME",
                   help="the cameras the model sees, in order (names of the topic map's cameras list), each through "
                   "one shared image encoder; default: the first camera alone")
    p.add_argument("--pool", choices=POOLS, default="avg",
                   help="the image encoder's pooling: avg (global average; default) or spatial_softmax (32 "
                   "keypoints, as Diffusion Policy, robomimic and LeRobot)")
    p.add_argument("--crop", type=NON_NEGATIVE, default=0,
                   help="the encoder sees a crop x crop window of the input: a random one in training, the centre "
                   "at test (Diffusion Policy's Push-T: 84 of 96); replaces the random shift; default 0: none")
    p.add_argument("--per-frame", action="store_true",
                   help="each observation frame through the shared image encoder, features concatenated (Diffusion "
                   "Policy); default: the frames stacked as channels into one encoder pass")
    p.add_argument("--target", choices=["command", "ee", "action"], default="command",
                   help="closed loop: command (the commanded end effector's waypoints relative to the command now: "
                   "the action stream's x, y, z; default), ee (the measured end effector's, relative to where it "
                   "is: for bags without a command topic) or action (the bags' action stream per frame, absolute, "
                   "with their state stream as the state input: Push-T, joint-space policies)")
    add_device_args(p)
    p.add_force()
    return p.parse_args(argv)


def model_config(args: argparse.Namespace) -> ModelConfig:
    """The model's configuration from the preset, the options and the data (its horizon, its streams' sizes)."""
    overrides = {"use_depth": args.depth, "pool": args.pool, "crop": args.crop, "per_frame": args.per_frame}
    if args.image_size:
        overrides["image_size"] = args.image_size
    with schema.open_dataset(args.data, names=[]) as f:  # train() checks the split's episodes
        horizon = int(f.attrs["n_waypoints"])
    if args.closed_loop:
        if args.action_steps % 4:
            raise AdlError(f"--action-steps {args.action_steps}: the U-Net needs a multiple of 4")
        horizon = args.action_steps
        overrides.update(n_obs=args.obs_frames, rate_hz=args.rate_hz, state_dim=STATE_DIM * args.obs_frames,
                         use_image=not args.no_image, target=args.target)
        if args.target == "action":
            state_dim, action_dim = stream_sizes(args.data)
            overrides.update(target="action", action_dim=action_dim, state_dim=state_dim * args.obs_frames)
    elif args.no_image:
        raise AdlError("--no-image needs --closed-loop: a first-frame model has no state input")
    if args.cameras:
        if args.closed_loop and args.no_image:
            raise AdlError("--cameras with --no-image: a state-only model sees no camera")
        if len(set(args.cameras)) < len(args.cameras):
            raise AdlError(f"--cameras {' '.join(args.cameras)}: a camera is named twice")
        overrides["cameras"] = tuple(args.cameras)
    elif horizon % 4:  # the U-Net halves the sequence twice; the transformers take any length
        raise AdlError(f"{args.data}: {horizon} waypoints per trajectory; the models need a multiple of 4 "
                       "(re-ingest with --waypoints 32)")
    overrides["horizon"] = horizon
    cfg = preset(args.config, args.model, **overrides)
    if cfg.crop and cfg.crop >= cfg.image_size:
        raise AdlError(f"--crop {cfg.crop}: not smaller than the {cfg.image_size} px input (--image-size)")
    return cfg


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    out = args.out or Path("models") / args.model
    refuse_pipeline_outputs([out, args.log], args.force)
    cfg = model_config(args)
    split = args.split or args.data.with_name("split.json")
    lr = args.lr if args.lr is not None else PRESET_LR[args.config]
    with process_group(device) as ranks:  # under torchrun: one process per GPU (or CPU share), rank 0 writes
        with exclusive(out) if ranks.main else contextlib.nullcontext():
            if args.restart and ranks.main:
                for name in ("last.pt", "best.pt"):
                    ((args.resume_dir or out) / name).unlink(missing_ok=True)
                shutil.rmtree((args.resume_dir or out) / "checkpoints", ignore_errors=True)
            barrier(ranks)  # no process reads a checkpoint that --restart is about to remove
            m = train(args.data, split, out, cfg, args.epochs, args.batch_size, lr, args.weight_decay,
                      args.warmup_steps, args.grad_clip, args.seed, args.log or out / "log.csv", progress=True,
                      val_fraction=args.val_fraction, val_every=args.val_every, augment=not args.no_augment,
                      workers=args.workers, device=device, precision=args.precision, ranks=ranks,
                      windows_per_epoch=args.windows_per_epoch, save_every=args.save_every,
                      open_files=args.open_files, resume_dir=args.resume_dir)
    if not ranks.main:
        return 0
    val = (f", val px best {m['val_px_best']:.2f} (epoch {m['best_epoch']}) last {m['val_px_last']:.2f}"
           f"{'' if m['converged'] else ', NOT CONVERGED'}" if m["val_px_best"] is not None else "")
    print(f"{out}: {cfg.model} trained {m['epochs']} epochs ({m['optimizer_steps']} steps) in {m['seconds']:.0f} s, "
          f"train loss {m['train_loss']:.4f}, test loss {m['test_loss']:.4f}{val}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.train", main))
