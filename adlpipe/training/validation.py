"""What a training run measures of its EMA model: the test loss, the val px that selects checkpoints, and whether
the run converged (metrics.json)."""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from ..dataset.loader import Normalizer
from ..evaluation.stats import mean_interval
from ..evaluation.training_log import converged
from ..plumbing.runtime import Ranks, autocast, generator, to_device
from ..policy.models import ModelConfig, Observation, Policy
from ..policy.objectives import Noise
from .data import collate_obs


@torch.no_grad()
def evaluate_loss(policy: Policy, loader: DataLoader, device: torch.device, precision: str) -> float:
    """Mean loss over the loader (its samples carry fixed noise: comparable test losses from epoch to epoch)."""
    total, n = 0.0, 0
    for obs, act, eps, u in loader:
        obs, act, eps, u = to_device((obs, act, eps, u), device)
        with autocast(device, precision):
            total += float(policy.loss(obs, act, Noise(eps, u))) * len(act)
        n += len(act)
    return total / max(n, 1)


def val_dims(cfg: ModelConfig) -> int:
    """How many target dimensions the validation error measures: the waypoints' pixels (u, v), or the whole
    recorded action (Push-T's is a pixel position; Franka Kitchen's, joint velocities)."""
    return cfg.action_dim if cfg.target == "action" else 2


def validation_px(policy: Policy, obs: Observation, target_px: torch.Tensor, norm: Normalizer, seed: int,
                  precision: str = "fp32") -> list[float]:
    """Per validation episode, the mean per-waypoint error (L2, the target's units: pixels, or the action's) of the
    default sampler (same noise every time); their mean is the val px that selects checkpoints."""
    device = target_px.device
    with autocast(device, precision):
        pred = policy.predict(obs, policy.default_steps, None, generator(device, seed))
    err = (norm.unnormalize(pred)[..., :target_px.shape[-1]] - target_px).norm(dim=-1)
    return err.flatten(1).mean(1).tolist()


def validation_set(val_ds: Dataset | None, norm: Normalizer, cfg: ModelConfig,
                   device: torch.device) -> tuple[Observation | None, torch.Tensor | None]:
    """The validation episodes' observations and their targets in the target's units, on the device, once."""
    if val_ds is None:
        return None, None
    items = [val_ds[i] for i in range(len(val_ds))]
    obs = to_device(collate_obs([o for o, _ in items]), device)
    return obs, norm.unnormalize(torch.stack([a for _, a in items]))[..., :val_dims(cfg)].to(device)


@torch.no_grad()
def measure(model: Policy, test_loader: DataLoader, val_obs: Observation | None, val_target: torch.Tensor | None,
            norm: Normalizer, seed: int, device: torch.device,
            precision: str) -> tuple[float, float | None, list[float] | None]:
    """(test loss, val px, its interval) of the EMA model; no val px without a validation part."""
    test_loss = evaluate_loss(model, test_loader, device, precision)
    if val_obs is None:
        return test_loss, None, None
    per_episode = validation_px(model, val_obs, val_target, norm, seed, precision)
    return test_loss, float(np.mean(per_episode)), list(mean_interval(per_episode))


def final_metrics(history: list[dict], cfg: ModelConfig, epochs: int, steps_per_epoch: int, n_train: int, n_val: int,
                  ranks: Ranks, device: torch.device, precision: str) -> dict:
    """metrics.json: the run's losses, its best and last val px with their intervals, and whether it converged."""
    vals = [r for r in history if r.get("val_px") is not None]
    best = min(vals, key=lambda r: r["val_px"]) if vals else None
    final = {"model": cfg.model, "epochs": epochs, "optimizer_steps": epochs * steps_per_epoch,
             "train_episodes": n_train, "val_episodes": n_val,
             "train_loss": history[-1]["train_loss"], "test_loss": history[-1]["test_loss"],
             "val_px_last": vals[-1]["val_px"] if vals else None, "val_px_best": best["val_px"] if best else None,
             "val_px_last_ci": vals[-1].get("val_px_ci") if vals else None,
             "val_px_best_ci": best.get("val_px_ci") if best else None,
             "best_epoch": best["epoch"] if best else epochs, "converged": converged(history),
             "val_history": [[r["epoch"], r["val_px"]] for r in vals], "processes": ranks.world,
             "device": device.type, "precision": precision,
             "seconds": sum(r["seconds"] for r in history)}
    return final
