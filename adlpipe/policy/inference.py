"""A loaded policy's predictions and their timing on the device and precision a stage was asked for."""

from __future__ import annotations

import random
import statistics
import time

import torch

from ..runtime import Placement, synchronize, to_device
from .models import Observation, Policy


def latency_ms(policy: Policy, obs: Observation, steps: int, method: str, repeats: int,
               placement: Placement | None = None) -> float:
    """Median milliseconds of one prediction; the device's queue is drained before each clock read."""
    return statistics.median(latency_samples_ms(policy, obs, steps, method, repeats, placement))


def latency_samples_ms(policy: Policy, obs: Observation, steps: int, method: str, repeats: int,
                       placement: Placement | None = None) -> list[float]:
    """Milliseconds of each of `repeats` predictions after a warm-up (for a median and its interval)."""
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
    return times


def interleaved_latency_ms(calls: dict[object, tuple[Policy, Observation, int, str]], rounds: int,
                           placement: Placement | None = None, seed: int = 0) -> dict[object, float]:
    """Median milliseconds of each call (policy, obs, steps, method), timed in rounds: every round times every
    call once, in a fresh random order, so a drift of the machine (another job, the clock) falls on every series
    alike instead of on whichever ran last."""
    placement = placement or Placement()
    gen = placement.generator(0)
    calls = {k: (pol, to_device(obs, placement.device), steps, method)
             for k, (pol, obs, steps, method) in calls.items()}
    times: dict[object, list[float]] = {k: [] for k in calls}
    order = list(calls)
    rng = random.Random(seed)
    with placement.autocast():
        for pol, obs, steps, method in calls.values():
            for _ in range(3):  # warm-up (and, with --compile, the compilation)
                pol.predict(obs, steps, method, gen)
        for _ in range(rounds):
            rng.shuffle(order)
            for k in order:
                pol, obs, steps, method = calls[k]
                synchronize(placement.device)
                t0 = time.perf_counter()
                pol.predict(obs, steps, method, gen)
                synchronize(placement.device)
                times[k].append((time.perf_counter() - t0) * 1000.0)
    return {k: statistics.median(v) for k, v in times.items()}


def predict(policy: Policy, obs: Observation, steps: int, method: str | None, gen: torch.Generator,
            placement: Placement) -> torch.Tensor:
    """Normalised samples on the CPU, computed on the placement's device and precision."""
    with placement.autocast():
        return policy.predict(to_device(obs, placement.device), steps, method, gen).cpu()
