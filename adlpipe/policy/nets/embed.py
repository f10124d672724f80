"""Sinusoidal embedding of the flow time / diffusion step (or of two times: MeanFlow's t and s - t)."""

from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalEmbedding(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        """t: (B,) -> (B, dim); (B, 2) -> (B, dim), each time embedded in half the features."""
        if t.dim() == 2:
            return torch.cat([self.embed(t[:, 0], self.dim // 2), self.embed(t[:, 1], self.dim - self.dim // 2)], -1)
        return self.embed(t, self.dim)

    @staticmethod
    def embed(t: torch.Tensor, dim: int) -> torch.Tensor:
        half = dim // 2
        freqs = torch.exp(-math.log(10000) * torch.arange(half, device=t.device, dtype=torch.float32) / (half - 1))
        args = t.float()[:, None] * freqs[None]
        return torch.cat([args.sin(), args.cos()], dim=-1)
