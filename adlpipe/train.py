"""Train one of the policies with the one training loop.

    python -m adlpipe.train --model fm_cnn --data data/adl.h5 --split data/split.json --out models/fm_cnn

AdamW (weight decay 1e-6), cosine schedule with linear warm-up, EMA weights (used for the losses, validation and
inference). A validation part of the train split (--val-fraction, stratified per task, seeded) is held out; every
--val-every epochs the EMA policy's val px (mean per-waypoint pixel error with the model's default sampler: FM 1
Euler step, DP 16 DDPM steps, BC direct) is measured, and the best EMA weights are kept in best.pt beside the last
ones in model.pt. A model whose best val px still fell by more than 2 % over the last fifth of training is marked
"converged": false in metrics.json. Every model trains for the same number of optimiser steps (epochs x batches).
Train, test and val figures are logged per epoch to a CSV that `dvc plots` reads. A checkpoint is written atomically
after every epoch; re-running the same command resumes from it (after a kill, too), and each epoch's randomness
comes from (seed, epoch), so a resumed run ends where an uninterrupted one does. Checkpoints hold only tensors and
plain values: they load with torch.load(weights_only=True).

Training augments (a random shift of the image stack with the pixel targets moved alike, colour jitter); --no-augment
turns it off; validation and test never augment. --closed-loop trains on every frame (adlpipe.dataset.loader
.WindowDataset): To frames and the end effector's position at each in, the next Tp waypoints at a fixed rate out,
relative to the end effector now. An epoch draws one random window per training episode, so a closed-loop model
takes the same optimiser steps as a first-frame one.
"""

from __future__ import annotations

import copy
import csv
import math
import sys
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from .atomic import atomic_path, write_json_atomic
from .cli import NON_NEGATIVE, POSITIVE, Parser, float_range, int_range
from .dataset import schema
from .dataset.loader import (
    Augment,
    Normalizer,
    TrajectoryDataset,
    WindowDataset,
    Windows,
    compute_stats,
    compute_window_stats,
)
from .dataset.splits import load_split, make_split
from .errors import AdlError, run_cli
from .lock import exclusive
from .policy.checkpoint import load_checkpoint, save_atomic
from .policy.models import MODELS, PRESET_LR, PRESETS, ModelConfig, Observation, Policy, preset

LOG_FIELDS = ["epoch", "step", "train_loss", "test_loss", "val_px", "lr", "seconds"]
CONVERGENCE_TOLERANCE = 0.02  # best val px may fall by at most 2 % over the last fifth of training


def cosine_with_warmup(opt: torch.optim.Optimizer, warmup: int, total: int) -> torch.optim.lr_scheduler.LambdaLR:
    def f(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        progress = (step - warmup) / max(1, total - warmup)
        return 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))

    return torch.optim.lr_scheduler.LambdaLR(opt, f)


class EMA:
    """Exponential moving average of the weights with Diffusion Policy's warm-up: decay = 1 - (1 + step/1)^-0.75,
    capped at max_decay, so early averages are not dominated by the random initialisation."""

    def __init__(self, model: torch.nn.Module, max_decay: float = 0.999) -> None:
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.max_decay = max_decay
        self.step = 0

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.step += 1
        decay = min(self.max_decay, max(0.0, 1 - (1 + self.step) ** -0.75))
        for e, p in zip(self.model.parameters(), model.parameters(), strict=True):
            e.mul_(decay).add_(p.detach(), alpha=1 - decay)
        for e, b in zip(self.model.buffers(), model.buffers(), strict=True):
            e.copy_(b)


@torch.no_grad()
def evaluate_loss(policy: Policy, loader: DataLoader, seed: int) -> float:
    gen = torch.Generator().manual_seed(seed)  # the same noise every epoch: comparable test losses
    total, n = 0.0, 0
    for obs, act in loader:
        total += float(policy.loss(obs, act, gen)) * len(act)
        n += len(act)
    return total / max(n, 1)


@torch.no_grad()
def collate_obs(items: list) -> Observation:
    """Stack observations: image tensors, or (image, state) pairs of closed-loop windows."""
    if isinstance(items[0], tuple | list):
        return tuple(torch.stack(parts) for parts in zip(*items, strict=True))
    return torch.stack(items)


def validation_px(policy: Policy, obs: Observation, target_px: torch.Tensor, norm: Normalizer, seed: int) -> float:
    """Mean per-waypoint pixel error of the default sampler on the validation episodes (same noise every time)."""
    gen = torch.Generator().manual_seed(seed)
    pred = norm.unnormalize(policy.predict(obs, policy.default_steps, None, gen))
    return float((pred[..., :2] - target_px).norm(dim=-1).mean())


def converged(history: list[dict], tolerance: float = CONVERGENCE_TOLERANCE) -> bool:
    """False if the best val px over the whole run is more than `tolerance` below the best of its first 4/5."""
    vals = [(r["epoch"], r["val_px"]) for r in history if r.get("val_px") is not None]
    if len(vals) < 2:
        return False
    cut = 0.8 * history[-1]["epoch"]
    early = [v for e, v in vals if e <= cut]
    return bool(early) and min(v for _, v in vals) >= (1 - tolerance) * min(early)


def split_validation(tasks: dict[str, str], fraction: float, seed: int) -> tuple[list[str], list[str]]:
    """(train, val): a stratified, seeded part of the train split (tasks: episode -> task) held out for checkpoint
    selection."""
    if fraction <= 0:
        return list(tasks), []
    parts = make_split(tasks, fraction, seed + 1)
    return parts["train"], parts["test"]


def train(data: Path, split_path: Path, out: Path, cfg: ModelConfig, epochs: int, batch_size: int = 32,
          lr: float = 1e-4, weight_decay: float = 1e-6, warmup_steps: int = 50, seed: int = 0,
          log_csv: Path | None = None, progress: bool = False, stop_after_epoch: int | None = None,
          val_fraction: float = 0.1, val_every: int = 5, augment: bool = True, workers: int = 0) -> dict:
    """Train (or resume) and return the final metrics. stop_after_epoch simulates an interruption (tests).
    A closed-loop config (cfg.rate_hz > 0) trains on windows of every frame; augmentation is for training only."""
    out.mkdir(parents=True, exist_ok=True)
    split = load_split(split_path)
    if not split["train"]:
        raise AdlError(f"{split_path}: the train split is empty")
    with schema.open_dataset(data, split["train"] + split["test"]) as f:
        horizon = int(f.attrs["n_waypoints"])
        size = int(f.attrs["image_size"])
        tasks = {n: str(f[schema.EPISODES][n].attrs["task"]) for n in split["train"]}
    if horizon != cfg.horizon and not cfg.closed_loop:
        raise AdlError(f"{data}: trajectories of {horizon} waypoints, the model is configured for {cfg.horizon}")
    train_names, val_names = split_validation(tasks, val_fraction, seed)
    aug = Augment(size) if augment else None
    if cfg.closed_loop:
        w = Windows(cfg.n_obs, cfg.horizon, cfg.rate_hz)
        stats = compute_window_stats(data, train_names, w)

        def dataset(names: list[str], **kw: object) -> WindowDataset:
            return WindowDataset(data, names, stats, cfg.image_size, w, cfg.use_depth, seed=seed, **kw)

        train_ds = dataset(train_names, augment=aug, per_episode=True)
        test_ds = dataset(split["test"] or train_names, frames_per_episode=2)
        val_ds = dataset(val_names, frames_per_episode=4) if val_names else None
    else:
        stats = compute_stats(str(data), train_names)
        train_ds = TrajectoryDataset(str(data), train_names, stats, cfg.image_size, cfg.use_depth, augment=aug,
                                     seed=seed)
        test_ds = TrajectoryDataset(str(data), split["test"] or train_names, stats, cfg.image_size, cfg.use_depth)
        val_ds = (TrajectoryDataset(str(data), val_names, stats, cfg.image_size, cfg.use_depth, cache=False)
                  if val_names else None)
    norm = Normalizer(stats)
    val_obs, val_px_target = None, None
    if val_ds is not None:
        items = [val_ds[i] for i in range(len(val_ds))]
        val_obs = collate_obs([o for o, _ in items])
        val_px_target = norm.unnormalize(torch.stack([a for _, a in items]))[..., :2]
    steps_per_epoch = math.ceil(len(train_ds) / batch_size)
    hparams = {"epochs": epochs, "batch_size": batch_size, "lr": lr, "weight_decay": weight_decay,
               "warmup_steps": warmup_steps, "seed": seed, "data": str(data), "split": sorted(split["train"]),
               "val_fraction": val_fraction, "val_every": val_every, "augment": augment}

    torch.manual_seed(seed)
    policy = Policy(cfg)
    opt = torch.optim.AdamW(policy.parameters(), lr=lr, weight_decay=weight_decay)
    sched = cosine_with_warmup(opt, warmup_steps, epochs * steps_per_epoch)
    ema = EMA(policy)
    history: list[dict] = []
    start_epoch = 0
    last = out / "last.pt"
    if last.exists():
        ck = load_checkpoint(last)
        if ck.get("config") != cfg.to_dict() or ck.get("hparams") != hparams:
            raise AdlError(f"{last}: checkpoint is from other settings; remove {out} (or use --restart) to retrain")
        policy.load_state_dict(ck["model"])
        ema.model.load_state_dict(ck["ema"])
        ema.step = int(ck["ema_step"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        history, start_epoch = list(ck["history"]), int(ck["epoch"])
    best_px = min((r["val_px"] for r in history if r.get("val_px") is not None), default=math.inf)

    def inference_checkpoint(epoch: int) -> dict:
        """What evaluate, replay and inspect load: the EMA weights with their config, stats and history."""
        return {"ema": ema.model.state_dict(), "config": cfg.to_dict(), "stats": stats, "history": history,
                "hparams": hparams, "epoch": epoch}

    test_loader = DataLoader(test_ds, batch_size=batch_size, shuffle=False)
    bar = tqdm(range(start_epoch, epochs), initial=start_epoch, total=epochs, desc=f"train {cfg.model}",
               unit="epoch", file=sys.stderr, disable=None if progress else True)
    for epoch in bar:
        t0 = time.time()
        gen = torch.Generator().manual_seed(seed * 100_003 + epoch)  # the epoch's randomness: resumable exactly
        train_ds.epoch = epoch  # the windows drawn and the augmentation, too
        loader = DataLoader(train_ds, batch_size=batch_size, shuffle=True, generator=gen, num_workers=workers)
        policy.train()
        total, n = 0.0, 0
        for obs, act in loader:
            loss = policy.loss(obs, act, gen)
            if not torch.isfinite(loss):  # stop before the weights or last.pt take the NaN
                raise AdlError(f"{cfg.model}: training diverged (loss {float(loss.detach())} in epoch {epoch + 1}); "
                               f"the last good checkpoint is kept in {out / 'last.pt'}; try a lower --lr")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
            opt.step()
            sched.step()
            ema.update(policy)
            total += loss.item() * len(act)
            n += len(act)
        val_px = None
        if val_obs is not None and ((epoch + 1) % val_every == 0 or epoch + 1 == epochs):
            val_px = validation_px(ema.model, val_obs, val_px_target, norm, seed)
        row = {"epoch": epoch + 1, "step": (epoch + 1) * steps_per_epoch, "train_loss": total / n,
               "test_loss": evaluate_loss(ema.model, test_loader, seed), "val_px": val_px,
               "lr": sched.get_last_lr()[0], "seconds": time.time() - t0}
        history.append(row)
        bar.set_postfix(train=f"{row['train_loss']:.4f}", test=f"{row['test_loss']:.4f}")
        if val_px is not None and val_px < best_px:  # written before last.pt: a resumed run never lacks it
            best_px = val_px
            save_atomic(inference_checkpoint(epoch + 1), out / "best.pt")
        save_atomic({"model": policy.state_dict(), "ema": ema.model.state_dict(), "ema_step": ema.step,
                     "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "epoch": epoch + 1,
                     "history": history, "config": cfg.to_dict(), "hparams": hparams, "stats": stats}, last)
        if stop_after_epoch is not None and epoch + 1 >= stop_after_epoch:
            return {"interrupted_at": epoch + 1}

    save_atomic(inference_checkpoint(epochs), out / "model.pt")
    if not (out / "best.pt").exists():  # no validation part: the last weights are the only choice
        save_atomic(inference_checkpoint(epochs), out / "best.pt")
    if log_csv is not None:
        with atomic_path(log_csv) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, LOG_FIELDS)
            w.writeheader()
            w.writerows(history)
    vals = [r for r in history if r.get("val_px") is not None]
    best = min(vals, key=lambda r: r["val_px"]) if vals else None
    final = {"model": cfg.model, "epochs": epochs, "optimizer_steps": epochs * steps_per_epoch,
             "train_episodes": len(train_names), "val_episodes": len(val_names),
             "train_loss": history[-1]["train_loss"], "test_loss": history[-1]["test_loss"],
             "val_px_last": vals[-1]["val_px"] if vals else None, "val_px_best": best["val_px"] if best else None,
             "best_epoch": best["epoch"] if best else epochs, "converged": converged(history),
             "val_history": [[r["epoch"], r["val_px"]] for r in vals],
             "seconds": sum(r["seconds"] for r in history)}
    write_json_atomic(out / "metrics.json", final)
    return final


def main(argv: list[str] | None = None) -> int:
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
    p.add_argument("--warmup-steps", type=NON_NEGATIVE, default=50)
    p.add_argument("--seed", type=NON_NEGATIVE, default=0)
    p.add_argument("--threads", type=NON_NEGATIVE, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--log", type=Path, help="per-epoch CSV for dvc plots (default: <out>/log.csv)")
    p.add_argument("--val-fraction", type=float_range(0, 0.9), default=0.1,
                   help="part of the train split held out for validation and checkpoint selection (0: none)")
    p.add_argument("--val-every", type=POSITIVE, default=5, help="measure val px every N epochs (and at the last)")
    p.add_argument("--workers", type=int_range(0, 64), default=0,
                   help="DataLoader worker processes that load (and augment) batches beside training (default 0)")
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
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    overrides = {"use_depth": args.depth}
    if args.image_size:
        overrides["image_size"] = args.image_size
    out = args.out or Path("models") / args.model
    if args.restart:
        with exclusive(out):
            for name in ("last.pt", "best.pt"):
                (out / name).unlink(missing_ok=True)
    with schema.open_dataset(args.data, names=[]) as f:  # train() checks the split's episodes
        horizon = int(f.attrs["n_waypoints"])
    if args.closed_loop:
        if args.action_steps % 4:
            raise AdlError(f"--action-steps {args.action_steps}: the U-Net needs a multiple of 4")
        horizon = args.action_steps
        overrides.update(n_obs=args.obs_frames, rate_hz=args.rate_hz, state_dim=3 * args.obs_frames)
    elif horizon % 4:  # the U-Net halves the sequence twice; the transformers take any length
        raise AdlError(f"{args.data}: {horizon} waypoints per trajectory; the models need a multiple of 4 "
                       "(re-ingest with --waypoints 32)")
    overrides["horizon"] = horizon
    cfg = preset(args.config, args.model, **overrides)
    split = args.split or args.data.with_name("split.json")
    lr = args.lr if args.lr is not None else PRESET_LR[args.config]
    with exclusive(out):
        m = train(args.data, split, out, cfg, args.epochs, args.batch_size, lr, args.weight_decay,
                  args.warmup_steps, args.seed, args.log or out / "log.csv", progress=True,
                  val_fraction=args.val_fraction, val_every=args.val_every, augment=not args.no_augment,
                  workers=args.workers)
    val = (f", val px best {m['val_px_best']:.2f} (epoch {m['best_epoch']}) last {m['val_px_last']:.2f}"
           f"{'' if m['converged'] else ', NOT CONVERGED'}" if m["val_px_best"] is not None else "")
    print(f"{out}: {cfg.model} trained {m['epochs']} epochs ({m['optimizer_steps']} steps) in {m['seconds']:.0f} s, "
          f"train loss {m['train_loss']:.4f}, test loss {m['test_loss']:.4f}{val}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.train", main))
