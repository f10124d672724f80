"""Which samples a training process loads, and the randomness each carries.

One DataLoader serves the whole run (its worker processes persist), so the epoch travels with every index: the
sampler yields (epoch, index) keys, and the dataset derives the sample's window, augmentation and training noise
from (seed, epoch, index). Under torchrun each process takes a disjoint share of every epoch's permutation
(torch's DistributedSampler); the shares of one global batch are exactly the samples a single process would put in
it, with the same noise, so N processes train as one does, up to the order of floating-point sums.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Protocol

import numpy as np
import torch
from torch.utils.data import Dataset, DistributedSampler, Sampler


def sample_noise(shape: tuple[int, ...], key: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """One sample's training noise (adlpipe.policy.objectives.Noise): eps of the target's shape, standard normal,
    and three uniforms in [0, 1), from a generator seeded by key (seed, epoch, index). (The first two are what
    two were before MeanFlow's third: FM and DP train on the same noise as they did.)"""
    rng = np.random.default_rng([*key, 2])
    return (torch.from_numpy(rng.standard_normal(shape, dtype=np.float32)),
            torch.from_numpy(rng.random(3, dtype=np.float32)))


class EpochItems(Protocol):
    def __len__(self) -> int: ...

    def item(self, i: int, epoch: int) -> tuple: ...


class EpochSampler(Sampler[tuple[int, int]]):
    """(epoch, index) keys of this process's share of a seeded permutation (shuffle) or of the items in order.
    set_epoch before each epoch, as with DistributedSampler, which draws the permutation."""

    def __init__(self, n: int, world: int = 1, rank: int = 0, seed: int = 0, shuffle: bool = True) -> None:
        self.inner = DistributedSampler(range(n), num_replicas=world, rank=rank, shuffle=shuffle, seed=seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch
        self.inner.set_epoch(epoch)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        return ((self.epoch, i) for i in self.inner)

    def __len__(self) -> int:
        return len(self.inner)


class TrainingSamples(Dataset):
    """(observation, target, eps, u) for an (epoch, index) key: the item with its per-sample training noise."""

    def __init__(self, items: EpochItems, seed: int) -> None:
        self.items, self.seed = items, seed

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, key: tuple[int, int]) -> tuple:
        epoch, i = key
        obs, target = self.items.item(i, epoch)
        eps, u = sample_noise(tuple(target.shape), [self.seed, epoch, i])
        return obs, target, eps, u
