"""Training objectives and samplers, independent of the network that is trained with them.

Flow matching: x_t = t*x1 + (1-t)*x0 with x0 ~ N(0, I) at train AND test time, target velocity x1 - x0 (MSE);
sampled by integrating dx/dt = v from t=0 to 1 with Euler, midpoint or RK4 in 1..16 steps. The flow time is fed
to the sinusoidal embedding scaled by TIME_SCALE (t*100), so it spans the same range as the diffusion steps.
DDPM: 100 training steps, squaredcos_cap_v2 betas, epsilon prediction; sampled by DDPM (ancestral) or DDIM
(eta=0) on 1..16 'trailing' timesteps (the first step starts at t=99, i.e. from pure noise).
MSE: behaviour cloning by direct regression of the trajectory.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F

Denoiser = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]  # (x, t, cond) -> same shape as x


class FlowMatching:
    TIME_SCALE = 100.0
    methods = ("euler", "midpoint", "rk4")

    def loss(self, net: Denoiser, x1: torch.Tensor, cond: torch.Tensor,
             gen: torch.Generator | None = None) -> torch.Tensor:
        x0 = torch.randn(x1.shape, generator=gen, device=x1.device)
        t = torch.rand(x1.shape[0], generator=gen, device=x1.device)
        xt = t[:, None, None] * x1 + (1 - t[:, None, None]) * x0
        return F.mse_loss(net(xt, t * self.TIME_SCALE, cond), x1 - x0)

    @torch.no_grad()
    def sample(self, net: Denoiser, cond: torch.Tensor, shape: tuple[int, ...], steps: int, method: str = "euler",
               gen: torch.Generator | None = None) -> torch.Tensor:
        if method not in self.methods:
            raise ValueError(f"unknown flow-matching sampler {method!r}; use one of {self.methods}")
        x = torch.randn(shape, generator=gen, device=cond.device)
        dt = 1.0 / steps
        b = shape[0]

        def v(x: torch.Tensor, t: float) -> torch.Tensor:
            return net(x, torch.full((b,), t * self.TIME_SCALE, device=x.device), cond)

        for i in range(steps):
            t = i * dt
            if method == "euler":
                x = x + dt * v(x, t)
            elif method == "midpoint":
                x = x + dt * v(x + 0.5 * dt * v(x, t), t + 0.5 * dt)
            else:
                k1 = v(x, t)
                k2 = v(x + 0.5 * dt * k1, t + 0.5 * dt)
                k3 = v(x + 0.5 * dt * k2, t + 0.5 * dt)
                k4 = v(x + dt * k3, t + dt)
                x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return x

    @staticmethod
    def evaluations(steps: int, method: str) -> int:
        """Network evaluations per sample."""
        return steps * {"euler": 1, "midpoint": 2, "rk4": 4}[method]


def squaredcos_cap_v2(n: int, max_beta: float = 0.999) -> torch.Tensor:
    """Betas of the cosine schedule (Nichol & Dhariwal), as diffusers' squaredcos_cap_v2."""
    abar = lambda t: math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    return torch.tensor([min(1 - abar((i + 1) / n) / abar(i / n), max_beta) for i in range(n)], dtype=torch.float64)


class DDPM:
    methods = ("ddpm", "ddim")

    def __init__(self, train_steps: int = 100, clip_sample: bool = True) -> None:
        self.n = train_steps
        self.betas = squaredcos_cap_v2(train_steps)
        self.abar = torch.cumprod(1 - self.betas, 0)
        self.clip = clip_sample

    def loss(self, net: Denoiser, x1: torch.Tensor, cond: torch.Tensor,
             gen: torch.Generator | None = None) -> torch.Tensor:
        noise = torch.randn(x1.shape, generator=gen, device=x1.device)
        k = torch.randint(0, self.n, (x1.shape[0],), generator=gen, device=x1.device)
        a = self.abar.to(x1.device, torch.float32)[k][:, None, None]
        xk = a.sqrt() * x1 + (1 - a).sqrt() * noise
        return F.mse_loss(net(xk, k.float(), cond), noise)

    def timesteps(self, steps: int) -> list[int]:
        """'trailing' spacing: steps=1 -> [99]; steps=16 -> [99, 93, ..., 5]."""
        if not 1 <= steps <= self.n:
            raise ValueError(f"steps must be in 1..{self.n}")
        return [int(round(self.n - i * self.n / steps)) - 1 for i in range(steps)]

    @torch.no_grad()
    def sample(self, net: Denoiser, cond: torch.Tensor, shape: tuple[int, ...], steps: int, method: str = "ddpm",
               gen: torch.Generator | None = None) -> torch.Tensor:
        if method not in self.methods:
            raise ValueError(f"unknown diffusion sampler {method!r}; use one of {self.methods}")
        x = torch.randn(shape, generator=gen, device=cond.device)
        ts = self.timesteps(steps)
        abar = self.abar.tolist()
        for i, t in enumerate(ts):
            prev = ts[i + 1] if i + 1 < len(ts) else -1
            a_t, a_prev = abar[t], (abar[prev] if prev >= 0 else 1.0)
            eps = net(x, torch.full((shape[0],), float(t), device=x.device), cond)
            x0 = (x - math.sqrt(1 - a_t) * eps) / math.sqrt(a_t)
            if self.clip:
                x0 = x0.clamp(-1, 1)
            if method == "ddim":
                eps = (x - math.sqrt(a_t) * x0) / math.sqrt(1 - a_t)
                x = math.sqrt(a_prev) * x0 + math.sqrt(1 - a_prev) * eps
            else:
                alpha = a_t / a_prev
                beta = 1 - alpha
                mean = (math.sqrt(a_prev) * beta / (1 - a_t)) * x0 + (math.sqrt(alpha) * (1 - a_prev) / (1 - a_t)) * x
                x = mean
                if prev >= 0:
                    var = max((1 - a_prev) / (1 - a_t) * beta, 1e-20)
                    x = x + math.sqrt(var) * torch.randn(shape, generator=gen, device=x.device)
        return x

    @staticmethod
    def evaluations(steps: int, method: str) -> int:
        return steps


class MSERegression:
    """Behaviour cloning: the network maps the observation straight to the trajectory."""

    methods = ("direct",)

    def loss(self, net: Callable, x1: torch.Tensor, cond: torch.Tensor,
             gen: torch.Generator | None = None) -> torch.Tensor:
        return F.mse_loss(net(cond), x1)

    @torch.no_grad()
    def sample(self, net: Callable, cond: torch.Tensor, shape: tuple[int, ...], steps: int = 1, method: str = "direct",
               gen: torch.Generator | None = None) -> torch.Tensor:
        return net(cond)

    @staticmethod
    def evaluations(steps: int, method: str) -> int:
        return 1
