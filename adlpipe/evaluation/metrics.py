"""Figures of a predicted trajectory against the demonstrations: waypoint error and mode commitment."""

from __future__ import annotations

import torch


def waypoint_errors(pred: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample mean per-waypoint error: (px, cm). pred/gt: (B, N, 5) unnormalised (u, v, x, y, z)."""
    px = (pred[..., :2] - gt[..., :2]).norm(dim=-1).mean(-1)
    cm = (pred[..., 2:] - gt[..., 2:]).norm(dim=-1).mean(-1) * 100.0
    return px, cm


def mode_distances(samples: torch.Tensor, modes: torch.Tensor) -> torch.Tensor:
    """Mean per-waypoint distance of each sample to mode 0, mode 1 and the modes' average.
    samples (B, N, D), modes (B, 2, N, D) -> (B, 3)."""
    refs = torch.cat([modes, modes.mean(1, keepdim=True)], dim=1)
    return (samples[:, None] - refs).norm(dim=-1).mean(-1)


def commitment(samples: torch.Tensor, modes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(committed, to mode 0), each (B,) bool: a sample is committed when it lies nearer to one of the two modes
    than to their average (on the line between the modes: within a quarter of the gap from a mode). Waypoints the
    modes share add the same distance to all three and do not change the verdict."""
    d = mode_distances(samples, modes)
    nearest = d[:, :2].min(dim=1).values
    return nearest < d[:, 2], d[:, 0] <= d[:, 1]
