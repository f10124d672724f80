"""A training run from its configuration (`adlpipe train` parses its options into a TrainConfig and calls
run_training): the model's configuration from the preset, the options and the data; the output folder locked
against a second writer; under torchrun one process per GPU (or CPU share); then the one training loop."""

from __future__ import annotations

import contextlib
import shutil
from dataclasses import dataclass
from pathlib import Path

import torch

from ..dataset import schema
from ..dataset.loader import OPEN_FILES, STATE_DIM
from ..plumbing.errors import AdlError
from ..plumbing.lock import exclusive
from ..plumbing.runtime import barrier, process_group, resolve_device
from ..policy.models import PRESET_LR, ModelConfig, preset
from ..policy.optim import WARMUP_STEPS
from .data import stream_sizes
from .loop import check_resume_dir, train


@dataclass(frozen=True)
class TrainConfig:
    """What `adlpipe train` was asked (its options, one field each: `adlpipe train --help` says what each does)."""

    model: str
    data: Path
    split: Path  # the stage defaults it to split.json beside the data
    out: Path  # the stage defaults it to models/<model>
    # the network: the preset and what overrides it
    config: str = "small"
    image_size: int | None = None
    depth: bool = False
    pool: str = "avg"
    crop: int = 0
    per_frame: bool = False
    cameras: list[str] | None = None
    # closed loop: To frames in, Tp steps out, the target they are made of
    closed_loop: bool = False
    obs_frames: int = 2
    action_steps: int = 16
    rate_hz: float = 10.0
    no_image: bool = False
    target: str = "command"
    # the optimisation
    epochs: int = 100
    steps: int | None = None
    batch_size: int = 32
    lr: float | None = None  # None: the preset's
    weight_decay: float = 1e-6
    warmup_steps: int = WARMUP_STEPS
    grad_clip: float = 1.0
    seed: int = 0
    no_augment: bool = False
    windows_per_epoch: str = "episodes"
    corrections_only: bool = False
    init: Path | None = None
    stop_when_converged: int | None = None
    # validation, outputs, resuming
    val_fraction: float = 0.1
    val_every: int = 5
    save_every: int = 0
    log: Path | None = None  # None: <out>/log.csv
    resume_dir: Path | None = None  # None (or --out itself): checkpoints in out
    restart: bool = False
    # where it runs
    device: str = "auto"
    precision: str = "fp32"
    threads: int = 0
    workers: int = 0
    open_files: int = OPEN_FILES


def model_config(c: TrainConfig) -> ModelConfig:
    """The model's configuration from the preset, the options and the data (its horizon, its streams' sizes)."""
    overrides: dict = {"use_depth": c.depth, "pool": c.pool, "crop": c.crop, "per_frame": c.per_frame}
    if c.image_size:
        overrides["image_size"] = c.image_size
    with schema.open_dataset(c.data, names=[]) as f:  # train() checks the split's episodes
        horizon = int(f.attrs["n_waypoints"])
    if c.closed_loop:
        if c.action_steps % 4:
            raise AdlError(f"--action-steps {c.action_steps}: the U-Net needs a multiple of 4")
        horizon = c.action_steps
        overrides.update(n_obs=c.obs_frames, rate_hz=c.rate_hz, state_dim=STATE_DIM * c.obs_frames,
                         use_image=not c.no_image, target=c.target)
        if c.target == "action":
            state_dim, action_dim = stream_sizes(c.data)
            overrides.update(target="action", action_dim=action_dim, state_dim=state_dim * c.obs_frames)
    elif c.no_image:
        raise AdlError("--no-image needs --closed-loop: a first-frame model has no state input")
    if c.cameras:
        if c.closed_loop and c.no_image:
            raise AdlError("--cameras with --no-image: a state-only model sees no camera")
        if len(set(c.cameras)) < len(c.cameras):
            raise AdlError(f"--cameras {' '.join(c.cameras)}: a camera is named twice")
        overrides["cameras"] = tuple(c.cameras)
    elif horizon % 4:  # the U-Net halves the sequence twice; the transformers take any length
        raise AdlError(f"{c.data}: {horizon} waypoints per trajectory; the models need a multiple of 4 "
                       "(re-ingest with --waypoints 32)")
    overrides["horizon"] = horizon
    cfg = preset(c.config, c.model, **overrides)
    if cfg.crop and cfg.crop >= cfg.image_size:
        raise AdlError(f"--crop {cfg.crop}: not smaller than the {cfg.image_size} px input (--image-size)")
    return cfg


def run_training(c: TrainConfig) -> tuple[ModelConfig, dict | None]:
    """Train (or resume) the run `c`: its model's configuration and final metrics (None on a process other than
    rank 0 under torchrun, which writes nothing)."""
    device = resolve_device(c.device)
    if c.threads:
        torch.set_num_threads(c.threads)
    cfg = model_config(c)
    lr = c.lr if c.lr is not None else PRESET_LR[c.config]
    resume_dir = None if c.resume_dir is None or c.resume_dir.resolve() == c.out.resolve() else c.resume_dir
    if resume_dir is not None:
        check_resume_dir(resume_dir, c.out, [c.data, c.split, *([c.log] if c.log else [])])
    with process_group(device) as ranks:  # under torchrun: one process per GPU (or CPU share), rank 0 writes
        with exclusive(c.out) if ranks.main else contextlib.nullcontext():
            if c.restart and ranks.main:
                for name in ("last.pt", "best.pt"):
                    ((resume_dir or c.out) / name).unlink(missing_ok=True)
                shutil.rmtree((resume_dir or c.out) / "checkpoints", ignore_errors=True)
            barrier(ranks)  # no process reads a checkpoint that --restart is about to remove
            m = train(c.data, c.split, c.out, cfg, c.epochs, c.batch_size, lr, c.weight_decay, c.warmup_steps,
                      c.grad_clip, c.seed, c.log or c.out / "log.csv", progress=True, val_fraction=c.val_fraction,
                      val_every=c.val_every, augment=not c.no_augment, workers=c.workers, device=device,
                      precision=c.precision, ranks=ranks, windows_per_epoch=c.windows_per_epoch,
                      save_every=c.save_every, open_files=c.open_files, resume_dir=resume_dir, init=c.init,
                      corrections_only=c.corrections_only, steps=c.steps, stop_floor=c.stop_when_converged)
    return cfg, (m if ranks.main else None)
