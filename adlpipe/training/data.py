"""What a training run reads: its train and validation episodes, the datasets of the model's kind (first frames or
windows of every frame) and the batches an epoch draws from them."""

from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset

from ..dataset import schema
from ..dataset.loader import (
    OPEN_FILES,
    Augment,
    TrajectoryDataset,
    WindowDataset,
    Windows,
    any_reference,
    check_cameras,
    compute_action_stats,
    compute_stats,
    compute_window_stats,
)
from ..dataset.memory_windows import MAX_BYTES, MemoryBatches, memory_bytes
from ..dataset.sampling import EpochSampler, TrainingSamples
from ..dataset.splits import make_split, recording_keys
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Ranks
from ..policy.models import ModelConfig, Observation


def collate_obs(items: list) -> Observation:
    """Stack observations: image tensors, or (image, state) pairs of closed-loop windows."""
    if isinstance(items[0], tuple | list):
        return tuple(torch.stack(parts) for parts in zip(*items, strict=True))
    return torch.stack(items)


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


def training_episodes(data: Path, split: dict, cfg: ModelConfig, val_fraction: float,
                      seed: int) -> tuple[list[str], list[str], int, list[str]]:
    """(train, validation) episodes of the split's train part, the dataset's stored image size, and the train
    part's recording keys (the bags' file names: the same when another host re-records the same scenes, where the
    episode names are not); the data must hold the model's cameras and (first-frame models) its horizon."""
    with schema.open_dataset(data, split["train"] + split["test"]) as f:
        horizon, stored_size = int(f.attrs["n_waypoints"]), int(f.attrs["image_size"])
        tasks = {n: str(f[schema.EPISODES][n].attrs["task"]) for n in split["train"]}
        keys = recording_keys(f, split["train"])
        check_cameras(f, split["train"] + split["test"], cfg.cameras, str(data))
    if horizon != cfg.horizon and not cfg.closed_loop:
        raise AdlError(f"{data}: trajectories of {horizon} waypoints, the model is configured for {cfg.horizon}")
    return (*split_validation(tasks, val_fraction, seed, keys), stored_size, sorted(keys.values()))


def datasets(data: Path, cfg: ModelConfig, split: dict, train_names: list[str], val_names: list[str],
             aug: Augment | None, seed: int, windows_per_epoch: str = "episodes", open_files: int = OPEN_FILES,
             corrections_only: bool = False, stats: dict | None = None
             ) -> tuple[dict, Dataset, Dataset, Dataset | None]:
    """(stats, train, test, val) datasets of the model's kind: windows of every frame (closed loop) or first frames.
    aug: the training augmentation (validation and test never augment). windows_per_epoch (closed loop): an epoch
    draws as many windows as there are training episodes ("episodes") or every window once ("all").
    corrections_only (closed loop, HG-DAgger): an episode with an operator's flag gives training windows only where
    the operator drove. stats: the normalisation to keep (a warm start's), else computed
    from the training episodes."""
    if cfg.closed_loop:
        w = Windows(cfg.n_obs, cfg.horizon, cfg.rate_hz, cfg.target, cfg.use_image)
        if cfg.target == "recovery" and not any_reference(data, train_names):
            raise AdlError(f"{data}: --target recovery, but no training episode has a reference stream "
                           "(frames/reference_stream: bags recorded with record --recoveries); use --target command")
        stats = stats or (compute_action_stats(data, train_names) if cfg.target == "action"
                          else compute_window_stats(data, train_names, w))

        def windows(names: list[str], **kw: object) -> WindowDataset:
            return WindowDataset(data, names, stats, cfg.image_size, w, cfg.use_depth, seed=seed, cameras=cfg.cameras,
                                 **kw)

        train_w = replace(w, corrections_only=corrections_only)
        train_ds = WindowDataset(data, train_names, stats, cfg.image_size, train_w, cfg.use_depth, augment=aug,
                                 draws_per_epoch=len(train_names), seed=seed, cameras=cfg.cameras,
                                 open_files=open_files)
        if windows_per_epoch == "all":
            train_ds.draws = len(train_ds.items)
        return (stats, train_ds,
                windows(split["test"] or train_names, frames_per_episode=2),
                windows(val_names, frames_per_episode=4) if val_names else None)
    stats = stats or compute_stats(str(data), train_names)

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
