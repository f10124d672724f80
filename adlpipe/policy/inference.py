"""A loaded policy's predictions and their timing on the device and precision a stage was asked for."""

from __future__ import annotations

import statistics
import time

import torch

from ..runtime import Placement, synchronize, to_device
from .models import Observation, Policy


def latency_ms(policy: Policy, obs: Observation, steps: int, method: str, repeats: int,
               placement: Placement | None = None) -> float:
    """Median milliseconds of one prediction; the device's queue is drained before each clock read."""
    placement = placement or Placement()
    gen = placement.generator(0)
    obs = to_device(obs, placement.device)
    with placement.autocast():
        for _ in range(3):  # warm-up (and, with --compile, the compilation)
            policy.predict(obs, steps, method, gen)
        times = []
        for _ in range(repeats):
            synchronize(placement.device)
            t0 = time.perf_counter()
            policy.predict(obs, steps, method, gen)
            synchronize(placement.device)
            times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times)


def predict(policy: Policy, obs: Observation, steps: int, method: str | None, gen: torch.Generator,
            placement: Placement) -> torch.Tensor:
    """Normalised samples on the CPU, computed on the placement's device and precision."""
    with placement.autocast():
        return policy.predict(to_device(obs, placement.device), steps, method, gen).cpu()
