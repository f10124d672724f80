"""Training batches of a state-only closed-loop model straight from memory (the low-dimensional Push-T and Franka
Kitchen settings): no image is read, so all windows fit in a few megabytes, and a batch is one gather instead of
64 per-sample loads and a collate. The windows are WindowDataset's own, read once through its item(): the same
numbers a streamed loader would give.

Each epoch's draw (which windows, in which order) and training noise come from (seed, epoch), so a resumed run
continues exactly; under torchrun each process takes its contiguous share of every global batch.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch

from .loader import WindowDataset, pass_permutation

MAX_BYTES = 1 << 30  # more than this: stream them (train falls back to the loader)


def memory_bytes(windows: WindowDataset, values_per_window: int) -> int:
    """What holding every window as float32 takes."""
    return len(windows.items) * values_per_window * 4


class MemoryBatches:
    """Batches ((empty image, normalised state), normalised target, eps, u) of `draws` windows per epoch, drawn
    uniformly over every window (one seeded permutation per pass over all windows, continued across epochs)."""

    def __init__(self, windows: WindowDataset, batch_size: int, draws: int, seed: int, world: int = 1,
                 rank: int = 0) -> None:
        if windows.w.images:
            raise ValueError("MemoryBatches holds state-only windows")
        states, targets = [], []
        for i in range(len(windows.items)):
            (_image, state), target = windows.item(i, 0)
            states.append(state)
            targets.append(target)
        self.states, self.targets = torch.stack(states), torch.stack(targets)
        self.batch, self.draws, self.seed = batch_size, draws, seed
        self.world, self.rank, self.epoch = world, rank, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return -(-self.draws // self.batch)

    def order(self, epoch: int) -> np.ndarray:
        """The window indices epoch `epoch` draws: positions epoch * draws .. of the concatenated permutations."""
        n = len(self.states)
        pos = epoch * self.draws + np.arange(self.draws)
        out = np.empty(self.draws, int)
        for p in np.unique(pos // n):
            at = pos // n == p
            out[at] = pass_permutation(self.seed, int(p), n)[pos[at] % n]
        return out

    def __iter__(self) -> Iterator[tuple]:
        idx = torch.from_numpy(self.order(self.epoch))
        rng = np.random.default_rng([self.seed, self.epoch, 5])
        eps = torch.from_numpy(rng.standard_normal((self.draws, *self.targets.shape[1:]), dtype=np.float32))
        u = torch.from_numpy(rng.random((self.draws, 3), dtype=np.float32))
        share = self.batch // self.world
        for start in range(0, self.draws, self.batch):
            lo = start + self.rank * share
            sl = slice(lo, min(lo + share, start + self.batch, self.draws))
            b = idx[sl]
            yield (self.states.new_zeros(len(b), 0), self.states[b]), self.targets[b], eps[sl], u[sl]
