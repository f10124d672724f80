"""1D conditional U-Net over the waypoint sequence with FiLM conditioning (Diffusion Policy's design).

Down dims (256, 512, 1024) in the paper config, kernel 5, GroupNorm(8), Mish, sinusoidal step embedding; the
condition (step embedding + observation feature) scales and shifts every residual block's features.
"""

from __future__ import annotations

import torch
from torch import nn

from .embed import SinusoidalEmbedding


class Conv1dBlock(nn.Sequential):
    def __init__(self, cin: int, cout: int, kernel: int, groups: int = 8) -> None:
        super().__init__(nn.Conv1d(cin, cout, kernel, padding=kernel // 2), nn.GroupNorm(groups, cout), nn.Mish())


class FiLMResBlock(nn.Module):
    def __init__(self, cin: int, cout: int, cond_dim: int, kernel: int, groups: int) -> None:
        super().__init__()
        self.b1 = Conv1dBlock(cin, cout, kernel, groups)
        self.b2 = Conv1dBlock(cout, cout, kernel, groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * cout))
        self.skip = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.b1(x)
        scale, shift = self.film(cond).unsqueeze(-1).chunk(2, dim=1)
        h = scale * h + shift
        return self.b2(h) + self.skip(x)


class ConditionalUnet1D(nn.Module):
    """x: (B, T, D) noisy trajectory, t: (B,) step/time (already scaled), cond: (B, C) -> (B, T, D)."""

    def __init__(self, action_dim: int, cond_dim: int, down_dims: tuple[int, ...] = (256, 512, 1024),
                 kernel: int = 5, groups: int = 8, step_embed_dim: int = 128) -> None:
        super().__init__()
        self.step_embed = nn.Sequential(SinusoidalEmbedding(step_embed_dim),
                                        nn.Linear(step_embed_dim, 4 * step_embed_dim), nn.Mish(),
                                        nn.Linear(4 * step_embed_dim, step_embed_dim))
        c = step_embed_dim + cond_dim

        def block(a: int, b: int) -> FiLMResBlock:
            return FiLMResBlock(a, b, c, kernel, groups)

        dims = [action_dim, *down_dims]
        self.down = nn.ModuleList()
        for i, (a, b) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
            last = i == len(down_dims) - 1
            self.down.append(nn.ModuleList([block(a, b), block(b, b),
                                            nn.Conv1d(b, b, 3, 2, 1) if not last else nn.Identity()]))
        mid = down_dims[-1]
        self.mid = nn.ModuleList([block(mid, mid), block(mid, mid)])
        self.up = nn.ModuleList()
        rev = list(reversed(down_dims))
        for a, b in zip(rev[:-1], rev[1:], strict=True):  # each up level undoes one down-sampling
            self.up.append(nn.ModuleList([block(2 * a, b), block(b, b), nn.ConvTranspose1d(b, b, 4, 2, 1)]))
        self.final = nn.Sequential(Conv1dBlock(down_dims[0], down_dims[0], kernel, groups),
                                   nn.Conv1d(down_dims[0], action_dim, 1))

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        c = torch.cat([self.step_embed(t), cond], dim=-1)
        h = x.transpose(1, 2)
        skips = []
        for r1, r2, down in self.down:
            h = r2(r1(h, c), c)
            skips.append(h)
            h = down(h)
        for r in self.mid:
            h = r(h, c)
        for r1, r2, up in self.up:
            h = torch.cat([h, skips.pop()], dim=1)
            h = up(r2(r1(h, c), c))
        return self.final(h).transpose(1, 2)
