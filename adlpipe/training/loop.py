"""The one training loop every model shares: optimiser, schedule and EMA; an epoch of steps; the checkpoint a killed
run resumes from; the per-epoch log; and the finished run's files."""

from __future__ import annotations

import contextlib
import csv
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader
from tqdm import tqdm

from ..dataset.loader import OPEN_FILES, Augment, Normalizer
from ..dataset.sampling import EpochSampler, TrainingSamples
from ..dataset.splits import load_split
from ..evaluation.training_log import converged
from ..plumbing.atomic import atomic_path, write_json_atomic
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Ranks, all_sum, autocast, barrier, to_device
from ..policy.checkpoint import load_checkpoint, save_atomic
from ..policy.models import ModelConfig, Policy
from ..policy.objectives import Noise
from ..policy.optim import ADAMW_BETAS, EMA, WARMUP_STEPS, cosine_with_warmup
from .data import datasets, training_batches, training_episodes
from .validation import final_metrics, measure, validation_set

CHECKPOINT_EVERY_S = 60.0  # last.pt at least this often, and at every validation (the default's: every 20 epochs)

LOG_FIELDS = ["epoch", "step", "train_loss", "test_loss", "val_px", "lr", "seconds"]


def train(data: Path, split_path: Path, out: Path, cfg: ModelConfig, epochs: int, batch_size: int = 32,
          lr: float = 1e-4, weight_decay: float = 1e-6, warmup_steps: int = WARMUP_STEPS, grad_clip: float = 1.0,
          seed: int = 0, log_csv: Path | None = None, progress: bool = False, stop_after_epoch: int | None = None,
          val_fraction: float = 0.1, val_every: int = 5, augment: bool = True, workers: int = 0,
          device: torch.device | None = None, precision: str = "fp32", ranks: Ranks | None = None,
          windows_per_epoch: str = "episodes", save_every: int = 0, open_files: int = OPEN_FILES,
          resume_dir: Path | None = None, init: Path | None = None, corrections_only: bool = False,
          steps: int | None = None, stop_floor: int | None = None) -> dict:
    """Train (or resume) and return the final metrics. stop_after_epoch simulates an interruption (tests).
    resume_dir: where a run in progress keeps its checkpoints (default: out; see publish). batch_size is the global
    batch: under torchrun (ranks) each process takes batch_size / world of it; rank 0
    validates, logs and writes the checkpoints. save_every: also keep the EMA weights of every this many epochs
    in <out>/checkpoints/ (the benchmark's learning curves). init: a trained model's checkpoint to start from (its
    EMA weights and normalisation; a DAgger round goes on from the previous round's policy), with a fresh optimiser
    and schedule over this run's epochs. corrections_only: see training.data.datasets. steps: the optimiser steps
    in all instead of `epochs` (as many epochs as that takes: one budget whatever the number of episodes).
    stop_floor: stop at the first validation from this epoch on at which the run has converged by the 2 % rule
    that judges convergence (evaluation.training_log.converged); the schedule stays the cap's (`epochs`), so a
    stopped run is the capped run's first epochs exactly, and its best.pt the capped run's whenever the best epoch
    came before the stop."""
    device, ranks = device or torch.device("cpu"), ranks or Ranks()
    out.mkdir(parents=True, exist_ok=True)
    work = resume_dir or out
    work.mkdir(parents=True, exist_ok=True)
    split = load_split(split_path)
    check_run(split, split_path, batch_size, ranks)
    train_names, val_names, stored_size, train_keys = training_episodes(data, split, cfg, val_fraction, seed)
    aug = Augment(stored_size, crop=cfg.crop) if augment else None  # windows without images skip it
    start = warm_start(init, cfg) if init is not None else None
    stats, train_ds, test_ds, val_ds = datasets(data, cfg, split, train_names, val_names, aug, seed,
                                                windows_per_epoch, open_files, corrections_only,
                                                start["stats"] if start else None)
    norm = Normalizer(stats)
    val_obs, val_px_target = validation_set(val_ds, norm, cfg, device) if ranks.main else (None, None)
    loader = training_batches(train_ds, cfg, batch_size, seed, workers, device, ranks)
    test_loader = DataLoader(TrainingSamples(test_ds, seed), batch_size=batch_size,
                             sampler=EpochSampler(len(test_ds), shuffle=False), num_workers=0)
    steps_per_epoch = len(loader)
    if steps:
        epochs = math.ceil(steps / steps_per_epoch)
    hparams = {"epochs": epochs, "batch_size": batch_size, "lr": lr, "weight_decay": weight_decay,
               "warmup_steps": warmup_steps, "grad_clip": grad_clip, "seed": seed, "data": str(data),
               "split": train_keys,  # by recording, so a run resumes on the same scenes re-recorded elsewhere
               "val_fraction": val_fraction, "val_every": val_every, "augment": augment,
               "windows_per_epoch": windows_per_epoch,
               **({"init": str(init), "corrections_only": corrections_only} if init or corrections_only else {}),
               **({"stop_floor": stop_floor} if stop_floor else {})}

    torch.manual_seed(seed)
    policy, model, opt, sched, ema = optimisation(cfg, device, ranks, lr, weight_decay, warmup_steps,
                                                  epochs * steps_per_epoch)
    if start is not None:
        policy.load_state_dict(start["ema"])
        ema.model.load_state_dict(start["ema"])
    last = work / "last.pt"
    history, start_epoch = resume(last, cfg, hparams, stats, policy, ema, opt, sched,
                                  replace_stale=resume_dir is not None)
    best_px = min((r["val_px"] for r in history if r.get("val_px") is not None), default=math.inf)

    def inference_checkpoint(epoch: int) -> dict:
        """What evaluate, replay and inspect load: the EMA weights with their config, stats and history."""
        return {"ema": ema.model.state_dict(), "config": cfg.to_dict(), "stats": stats, "history": history,
                "hparams": hparams, "epoch": epoch}

    bar = tqdm(range(start_epoch, epochs), initial=start_epoch, total=epochs, desc=f"train {cfg.model}",
               unit="epoch", file=sys.stderr, disable=None if progress and ranks.main else True)
    saved = time.time()
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
            if checkpoint_due(test_loss is not None, epoch == start_epoch, time.time() - saved,
                              epoch + 1 == stop_after_epoch):
                save_atomic(resumable(policy, ema, opt, sched, epoch + 1, history, cfg, hparams, stats), last)
                saved = time.time()
        barrier(ranks)  # the others wait while rank 0 validates and writes
        if stop_after_epoch is not None and epoch + 1 >= stop_after_epoch:
            return {"interrupted_at": epoch + 1}
        if stop_floor and epoch + 1 >= stop_floor and converged_everywhere(history, device, ranks):
            break
    if not ranks.main:
        return {}
    ran = int(history[-1]["epoch"]) if history else epochs
    publish(inference_checkpoint(ran), work, out)
    final = final_metrics(history, cfg, ran, steps_per_epoch, len(train_names), len(val_names), ranks, device,
                          precision)
    if ran < epochs:
        final["stopped_converged_at"] = ran  # of the cap's `epochs`
    write_json_atomic(out / "metrics.json", final)
    write_log(log_csv, history)
    return final


def checkpoint_due(validated: bool, first_of_run: bool, since_saved_s: float, stopping: bool) -> bool:
    """Whether last.pt is written after this epoch: at validations, a run's first epoch, a stop, and at least
    every CHECKPOINT_EVERY_S. Not every epoch: an epoch of the default is 5 steps, and writing the optimiser's
    state after each took a seventh of the run (bench/train_profile.py); a kill loses at most this much."""
    return validated or first_of_run or stopping or since_saved_s >= CHECKPOINT_EVERY_S


def converged_everywhere(history: list[dict], device: torch.device, ranks: Ranks) -> bool:
    """Whether the run has converged by the 2 % rule at this validation (rank 0 judges, it holds the history);
    every process calls it at the same epoch and gets the same answer, so all stop together."""
    done = ranks.main and history[-1]["val_px"] is not None and converged(history)
    return all_sum([float(done)], device, ranks)[0] > 0


def check_run(split: dict, split_path: Path, batch_size: int, ranks: Ranks) -> None:
    if not split["train"]:
        raise AdlError(f"{split_path}: the train split is empty")
    if batch_size % ranks.world:
        raise AdlError(f"--batch-size {batch_size}: the global batch must split evenly over {ranks.world} processes")


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


def resumable(policy: Policy, ema: EMA, opt: torch.optim.Optimizer, sched: object, epoch: int, history: list[dict],
              cfg: ModelConfig, hparams: dict, stats: dict) -> dict:
    """last.pt: everything a killed run needs to go on exactly where it stopped."""
    return {"model": policy.state_dict(), "ema": ema.model.state_dict(), "ema_step": ema.step,
            "optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "epoch": epoch, "history": history,
            "config": cfg.to_dict(), "hparams": hparams, "stats": stats}


STATS_RTOL = 1e-6  # another host's re-recording of the same scenes: its physics differs in the 10th digit


def same_stats(a: dict, b: dict) -> bool:
    """Normalisation statistics of the same data: equal up to the float noise between hosts."""
    return set(a) == set(b) and all(np.shape(a[k]) == np.shape(b[k]) and np.allclose(a[k], b[k], rtol=STATS_RTOL,
                                                                                       atol=1e-9) for k in a)


def warm_start(path: Path, cfg: ModelConfig) -> dict:
    """The checkpoint a run starts from (init): a trained model of the same network and format. Its target may be
    "command" where this run's is "recovery" (the same waypoints, labelled by the demonstrator's law)."""
    if not path.is_file():
        raise AdlError(f"--init {path}: no such checkpoint; train the model first")
    ck = load_checkpoint(path)
    if not isinstance(ck, dict) or not {"config", "ema", "stats"} <= set(ck):
        raise AdlError(f"--init {path}: not an adlpipe policy checkpoint (needs config, ema and stats)")
    mine, theirs = cfg.to_dict(), dict(ck["config"])
    if {mine.get("target"), theirs.get("target")} <= {"command", "recovery"}:
        theirs["target"] = mine.get("target")
    differ = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
    if differ:
        raise AdlError(f"--init {path}: a model of other settings ({', '.join(differ[:4])} differ); warm-start "
                       "from the same model, closed loop, frames, steps and rate")
    return ck


def resume(last: Path, cfg: ModelConfig, hparams: dict, stats: dict, policy: Policy, ema: EMA,
           opt: torch.optim.Optimizer, sched: object, replace_stale: bool = False) -> tuple[list[dict], int]:
    """(history, epochs done) from the checkpoint a killed run left, its state loaded into the model, EMA,
    optimiser and schedule; ([], 0) without one. A checkpoint of other settings, or of other data (its
    normalisation statistics differ: a recording redone otherwise), is one line, or (replace_stale) removed with
    best.pt and checkpoints/ beside it."""
    if not last.exists():
        return [], 0
    ck = load_checkpoint(last)
    need = {"model", "ema", "ema_step", "optimizer", "scheduler", "epoch", "history"}
    if not isinstance(ck, dict) or not need <= set(ck):
        raise AdlError(f"{last}: not a training checkpoint adlpipe wrote (it holds "
                       f"{type(ck).__name__ if not isinstance(ck, dict) else ', '.join(sorted(map(str, ck))[:4])}); "
                       "remove it or use --restart")
    same_data = same_stats(ck.get("stats", stats), stats)
    other = ck.get("config") != cfg.to_dict() or ck.get("hparams") != hparams or not same_data
    if other and replace_stale and ck.get("config", {}).get("model") != cfg.model:
        raise AdlError(f"{last}: a checkpoint of another model ({ck.get('config', {}).get('model')}, not "
                       f"{cfg.model}); give each training a resume folder of its own, or use --restart")
    if other and replace_stale:
        print(f"{last}: a checkpoint of other settings or data; training from scratch", file=sys.stderr)
        for name in ("last.pt", "best.pt"):
            (last.parent / name).unlink(missing_ok=True)
        shutil.rmtree(last.parent / "checkpoints", ignore_errors=True)
        return [], 0
    if other:
        raise AdlError(f"{last}: checkpoint is from other settings or data; remove {last.parent} (or use --restart) "
                       "to retrain")
    print(f"{last}: resuming after epoch {int(ck['epoch'])}", file=sys.stderr)
    policy.load_state_dict(ck["model"])
    ema.model.load_state_dict(ck["ema"])
    ema.step = int(ck["ema_step"])
    opt.load_state_dict(ck["optimizer"])
    sched.load_state_dict(ck["scheduler"])
    return list(ck["history"]), int(ck["epoch"])


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
    (work / "last.pt").unlink(missing_ok=True)  # file by file: only what training wrote there, never the folder's rest
    with contextlib.suppress(OSError):
        work.rmdir()  # only if nothing else is left in it


RESUME_FILES = {"last.pt", "best.pt", "checkpoints"}


def check_resume_dir(resume_dir: Path, out: Path, inputs: list[Path]) -> None:
    """One line before training when a resume folder holds anything training does not write there (a user's file,
    the dataset, the output): a finished run removes what it wrote, and only that."""
    rd = resume_dir.resolve()
    for what, p in [("the output", out), *(("an input", q) for q in inputs)]:
        q = Path(p).resolve()
        if q == rd or rd in q.parents:
            raise AdlError(f"--resume-dir {resume_dir}: holds {what} ({p}); give training a folder of its own")
    if not rd.is_dir():
        return
    for entry in sorted(rd.iterdir()):
        ours = entry.name in RESUME_FILES or (entry.name.startswith(".") and ".pt.tmp" in entry.name)
        if entry.name == "checkpoints" and entry.is_dir():
            ours = all(c.name.startswith("step_") and c.suffix == ".pt" for c in entry.iterdir())
        if not ours:
            raise AdlError(f"--resume-dir {resume_dir}: holds {entry.name}, which training did not write; give "
                           "training a folder of its own (a finished run removes what it wrote there)")


def write_log(log_csv: Path | None, history: list[dict]) -> None:
    """The per-epoch CSV that dvc plots reads (plain columns only)."""
    if log_csv is not None:
        with atomic_path(log_csv) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, LOG_FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(history)
