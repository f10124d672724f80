"""A loaded policy's predictions and their timing on the device and precision a stage was asked for."""

from __future__ import annotations

import random
import statistics
import time
from pathlib import Path

import h5py
import numpy as np
import torch

from ..dataset import schema
from ..dataset.loader import Normalizer, observation, observation_from_arrays
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Placement, synchronize, to_device
from .checkpoint import load_policy
from .models import Observation, Policy


def phase_samples_ms(policy: Policy, obs: Observation, steps: int, method: str, repeats: int,
                     placement: Placement | None = None) -> dict[str, list[float]]:
    """Per repeat, the milliseconds of one prediction ("ms") and of its two parts: the encoder (the observation's
    features, "encoder_ms") and the sampler (its `steps` network evaluations, "sampler_ms"). The encoder's share
    is what a host changes most (an image network beside a small 1D U-Net), the sampler's count of network
    evaluations what it cannot."""
    placement = placement or Placement()
    gen = placement.generator(0)
    obs = to_device(obs, placement.device)
    out: dict[str, list[float]] = {"ms": [], "encoder_ms": [], "sampler_ms": []}
    with torch.no_grad(), placement.autocast():
        for _ in range(3):  # warm-up (and, with --compile, the compilation)
            policy.predict(obs, steps, method, gen)
        for _ in range(repeats):
            synchronize(placement.device)
            t0 = time.perf_counter()
            cond = policy.condition(obs)
            synchronize(placement.device)
            t1 = time.perf_counter()
            policy.sample(cond, steps, method, gen)
            synchronize(placement.device)
            t2 = time.perf_counter()
            for key, ms in (("ms", t2 - t0), ("encoder_ms", t1 - t0), ("sampler_ms", t2 - t1)):
                out[key].append(ms * 1000.0)
    return out


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


def steps_for(family: str, fm_steps: list[int], dp_steps: list[int]) -> list[int]:
    """The step counts a model is run at: FM and MeanFlow at fm_steps, DP at dp_steps, a regressor once."""
    return {"fm": fm_steps, "meanflow": fm_steps, "ddpm": dp_steps}.get(family, [1])


def label_of(model_dir: Path, method: str, family: str, steps: int) -> str:
    """A policy's row label: the model folder, with its sampler and step count unless it is a regressor."""
    return model_dir.name if family == "mse" else f"{model_dir.name}/{method}-{steps}"


def predict_episodes(model_dir: Path, checkpoint: str, data: Path, names: list[str], fm_steps: list[int],
                dp_steps: list[int], seed: int, placement: Placement) -> dict[str, np.ndarray]:
    """label -> predicted (u, v, x, y, z) waypoints (E, N, 5) of a model for the named episodes, for each of its
    step counts."""
    policy, ck = load_policy(model_dir / checkpoint, placement)
    norm = Normalizer(ck["stats"])
    with h5py.File(data, "r") as f:
        schema.check_horizon(model_dir, policy.cfg.horizon, f, data)
        obs = torch.stack([torch.from_numpy(observation(f[schema.EPISODES][n], policy.cfg.image_size,
                                                        policy.cfg.use_depth, policy.cfg.cameras)) for n in names])
    return predictions(model_dir, policy, norm, obs, fm_steps, dp_steps, seed, placement)


def predict_scenes(model_dir: Path, checkpoint: str, scenes: list, fm_steps: list[int], dp_steps: list[int],
                   seed: int, placement: Placement) -> dict[str, np.ndarray]:
    """predict_episodes for scenes held in memory (adlpipe.evaluation.scenes.ReplayScene: rgb, affordance, depth
    at the dataset's stored size), fed through the same observation builder as a stored episode's first frame."""
    policy, ck = load_policy(model_dir / checkpoint, placement)
    cfg = policy.cfg
    if cfg.cameras and len(cfg.cameras) > 1:
        raise AdlError(f"{model_dir}: sees cameras {', '.join(cfg.cameras)}; the ADL world's scenes have one camera")
    norm = Normalizer(ck["stats"])
    per_scene = []
    for s in scenes:  # one at a time, each from the seed: a scene's noise, and so its outcome, is the same in any
        # batch of scenes replay draws (as every closed-loop rollout's is)
        obs = torch.from_numpy(observation_from_arrays(s.rgb, s.affordance, s.depth, cfg.image_size,
                                                       cfg.use_depth))[None]
        per_scene.append(predictions(model_dir, policy, norm, obs, fm_steps, dp_steps, seed, placement))
    return {label: np.concatenate([p[label] for p in per_scene]) for label in per_scene[0]} if per_scene else {}


def predictions(model_dir: Path, policy: Policy, norm: Normalizer, obs: torch.Tensor, fm_steps: list[int],
                dp_steps: list[int], seed: int, placement: Placement) -> dict[str, np.ndarray]:
    """label -> the policy's unnormalised predictions for `obs` at each of its step counts."""
    out = {}
    for steps in steps_for(policy.family, fm_steps, dp_steps):
        pred = norm.unnormalize(predict(policy, obs, steps, None, placement.generator(seed), placement))
        out[label_of(model_dir, policy.default_method, policy.family, steps)] = pred.numpy()
    return out
