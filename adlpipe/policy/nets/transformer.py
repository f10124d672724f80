"""Transformer networks over the waypoint sequence: a denoiser (for flow matching / diffusion) and a direct
regressor (for behaviour cloning). Condition tokens (observation feature, and the step embedding for the
denoiser) are prepended to the waypoint tokens of a pre-norm encoder."""

from __future__ import annotations

import torch
from torch import nn

from .embed import SinusoidalEmbedding


def _encoder(d_model: int, n_layers: int, n_heads: int, dropout: float) -> nn.TransformerEncoder:
    layer = nn.TransformerEncoderLayer(d_model, n_heads, 4 * d_model, dropout, batch_first=True, norm_first=True,
                                       activation="gelu")
    return nn.TransformerEncoder(layer, n_layers, enable_nested_tensor=False)


class TransformerDenoiser(nn.Module):
    """x: (B, T, D), t: (B,), cond: (B, C) -> (B, T, D)."""

    def __init__(self, action_dim: int, cond_dim: int, horizon: int, d_model: int = 256, n_layers: int = 6,
                 n_heads: int = 8, dropout: float = 0.0) -> None:
        super().__init__()
        self.inp = nn.Linear(action_dim, d_model)
        self.pos = nn.Parameter(torch.zeros(1, horizon + 2, d_model))
        self.step = nn.Sequential(SinusoidalEmbedding(d_model), nn.Linear(d_model, d_model), nn.Mish())
        self.cond = nn.Linear(cond_dim, d_model)
        self.encoder = _encoder(d_model, n_layers, n_heads, dropout)
        self.out = nn.Sequential(nn.LayerNorm(d_model), nn.Linear(d_model, action_dim))
        nn.init.normal_(self.pos, std=0.02)

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        tokens = torch.cat([self.step(t)[:, None], self.cond(cond)[:, None], self.inp(x)], dim=1)
        h = self.encoder(tokens + self.pos[:, : tokens.shape[1]])
        return self.out(h[:, 2:])


class TransformerRegressor(nn.Module):
    """cond: (B, C) -> (B, T, D): learned waypoint queries attend to the observation token."""

    def __init__(self, action_dim: int, cond_dim: int, horizon: int, d_model: int = 256, n_layers: int = 6,
                 n_heads: int = 8, dropout: float = 0.0) -> None:
        super().__init__()
        self.queries = nn.Parameter(torch.zeros(1, horizon, d_model))
        self.pos = nn.Parameter(torch.zeros(1, horizon + 1, d_model))
        self.cond = nn.Linear(cond_dim, d_model)
        self.encoder = _encoder(d_model, n_layers, n_heads, dropout)
        self.out = nn.Sequential(nn.LayerNorm(d_model), nn.Linear(d_model, action_dim))
        nn.init.normal_(self.queries, std=0.02)
        nn.init.normal_(self.pos, std=0.02)

    def forward(self, cond: torch.Tensor) -> torch.Tensor:
        q = self.queries.expand(cond.shape[0], -1, -1)
        tokens = torch.cat([self.cond(cond)[:, None], q], dim=1)
        return self.out(self.encoder(tokens + self.pos)[:, 1:])
