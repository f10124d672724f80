"""A torch Dataset over the HDF5 file: image channels in, normalised trajectory out.

Inputs: RGB (3) + affordance map (1) [+ depth (1)] as channels at the model's image size, in [-1, 1].
Target: N waypoints x 5 = (u, v) pixels at the stored size and (x, y, z) metres, each dimension scaled to [-1, 1]
with min/max statistics of the train split only.
"""

from __future__ import annotations

import os

import cv2
import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from . import schema

DEPTH_SCALE_M = 2.0  # depth / 2 m - 1 keeps the table-top range inside [-1, 1]
ACTION_DIM = 5  # u, v, x, y, z


def raw_target(g: h5py.Group) -> np.ndarray:
    return np.concatenate([g["traj2d"][()], g["traj3d"][()]], axis=1).astype(np.float32)


def compute_stats(path: str, names: list[str]) -> dict[str, list[float]]:
    """Per-dimension min/max of the targets over `names` (the train split)."""
    with h5py.File(path, "r") as f:
        allv = np.concatenate([raw_target(f[schema.EPISODES][n]) for n in names])
    lo, hi = allv.min(0), allv.max(0)
    pad = np.maximum((hi - lo) * 0.05, 1e-3)  # a margin so test trajectories rarely leave [-1, 1]
    return {"min": (lo - pad).tolist(), "max": (hi + pad).tolist()}


class Normalizer:
    def __init__(self, stats: dict[str, list[float]]) -> None:
        self.lo = torch.tensor(stats["min"], dtype=torch.float32)
        self.hi = torch.tensor(stats["max"], dtype=torch.float32)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return 2 * (x - self.lo.to(x)) / (self.hi - self.lo).to(x) - 1

    def unnormalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x + 1) / 2 * (self.hi - self.lo).to(x) + self.lo.to(x)


def observation(g: h5py.Group, image_size: int, use_depth: bool) -> np.ndarray:
    """(C, S, S) float32 in [-1, 1] of a stored episode: RGB, affordance, optional depth."""
    depth = (g["depth"][()] if "depth" in g else None) if use_depth else None
    return observation_from_arrays(g["rgb"][()], g["affordance"][()], depth, image_size, use_depth)


def observation_from_arrays(rgb: np.ndarray, affordance: np.ndarray, depth: np.ndarray | None, image_size: int,
                            use_depth: bool) -> np.ndarray:
    """The network input from images (also a live camera's, in closed-loop replay)."""
    rgb = cv2.resize(rgb, (image_size, image_size), interpolation=cv2.INTER_AREA)
    aff = cv2.resize(affordance, (image_size, image_size), interpolation=cv2.INTER_AREA)
    chans = [rgb.transpose(2, 0, 1).astype(np.float32) / 127.5 - 1.0, aff[None] * 2.0 - 1.0]
    if use_depth:
        d = depth if depth is not None else np.full(rgb.shape[:2], np.nan, np.float32)
        d = cv2.resize(np.nan_to_num(d, nan=0.0), (image_size, image_size), interpolation=cv2.INTER_NEAREST)
        chans.append(np.clip(d / DEPTH_SCALE_M - 1.0, -1, 1)[None])
    return np.concatenate(chans).astype(np.float32)


class TrajectoryDataset(Dataset):
    """Lazy: the HDF5 file is opened once per worker process on first access; items are cached per worker."""

    def __init__(self, path: str, names: list[str], stats: dict, image_size: int, use_depth: bool = False,
                 cache: bool = True) -> None:
        self.path, self.names = str(path), list(names)
        self.norm = Normalizer(stats)
        self.image_size, self.use_depth, self.cache = image_size, use_depth, cache
        self._file: h5py.File | None = None
        self._pid = -1
        self._items: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def __len__(self) -> int:
        return len(self.names)

    def _handle(self) -> h5py.File:
        if self._file is None or self._pid != os.getpid():  # a forked worker must not share the parent's handle
            self._file = h5py.File(self.path, "r")
            self._pid = os.getpid()
            self._items = {}
        return self._file

    def task(self, i: int) -> str:
        return str(self._handle()[schema.EPISODES][self.names[i]].attrs["task"])

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        if i in self._items:
            return self._items[i]
        g = self._handle()[schema.EPISODES][self.names[i]]
        obs = torch.from_numpy(observation(g, self.image_size, self.use_depth))
        act = self.norm.normalize(torch.from_numpy(raw_target(g)))
        if self.cache:
            self._items[i] = (obs, act)
        return obs, act

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_file"], state["_items"] = None, {}
        return state
