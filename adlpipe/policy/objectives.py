"""Training objectives and samplers, independent of the network that is trained with them.

Flow matching: x_t = t*x1 + (1-t)*x0 with x0 ~ N(0, I) at train AND test time; sampled by integrating
dx/dt = v from t=0 to 1 with Euler, midpoint or RK4 in 1..16 steps. Two parameterisations of v:
  - "x1" (default): the network predicts the clean trajectory x1_hat, trained with MSE to x1, and
    v = (x1_hat - x_t) / (1 - t), 1 - t clamped at T_EPS (Li & He 2025, "x-prediction"). One Euler step returns
    x1_hat exactly, so the network never has to cancel its input noise through GroupNorm/Mish layers.
  - "velocity" (the paper's): the network predicts v directly, trained with MSE to x1 - x0.
The flow time is fed to the sinusoidal embedding scaled by TIME_SCALE (t*100), the range of the diffusion steps.
DDPM: 100 training steps, squaredcos_cap_v2 betas; the network predicts the clean sample ("sample", Diffusion
Policy's `prediction_type: sample`, the like-for-like partner of FM's "x1") or the noise ("epsilon", its default
and the paper's); sampled by DDPM (ancestral) or DDIM (eta=0).
Timestep spacing "leading" (diffusers' default, what Diffusion Policy uses: 16 steps = 90, 84, ..., 0) or
"trailing" (16 steps = 99, 93, ..., 5; the first step starts from pure noise, which few-step sampling needs).
MeanFlow (Geng et al. 2025): the network gives the average velocity u(x_t, t, s) over [t, s], trained with the
MeanFlow identity u = v + (s - t) du/dt (the total derivative along the flow, one forward-mode JVP); one step from
t = 0 to s = 1 jumps straight to a sample. Clean-trajectory output as FM's "x1": u = (x1_hat - x_t) / (1 - t).
MSE: behaviour cloning by direct regression of the trajectory.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel

Denoiser = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]  # (x, t, cond) -> same shape as x


T_EPS = 0.05  # the smallest 1 - t that x-prediction divides by


@dataclass(frozen=True)
class Noise:
    """A batch's training randomness: eps (B, N, D) standard normal (FM's x0, DDPM's noise) and u (B, 3) uniform in
    [0, 1) (the flow time or diffusion step; MeanFlow's second time and its choice of s = t). Drawn per sample
    from (seed, epoch, index) by adlpipe.dataset.sampling, the same on 1 or N processes."""

    eps: torch.Tensor
    u: torch.Tensor


def draw_noise(shape: tuple[int, ...], gen: torch.Generator | None = None,
               device: torch.device | str | None = None) -> Noise:
    """A batch's noise from one generator (tests, benches)."""
    eps = torch.randn(shape, generator=gen, device=device)
    u = torch.rand(shape[0], 2, generator=gen, device=device)  # FM's and DDPM's stream as before the third one
    return Noise(eps, torch.cat([u, torch.rand(shape[0], 1, generator=gen, device=device)], dim=1))


def interpolate(x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The flow-matching path x_t = t*x1 + (1-t)*x0; t has one entry per batch element."""
    t = t.reshape(-1, *([1] * (x1.dim() - 1)))
    return t * x1 + (1 - t) * x0


def velocity_from_x1(x1_hat: torch.Tensor, xt: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """The velocity that carries x_t to the predicted clean sample x1_hat by t = 1: (x1_hat - x_t) / (1 - t)."""
    if isinstance(t, torch.Tensor):
        t = t.reshape(-1, *([1] * (xt.dim() - 1)))
        return (x1_hat - xt) / (1 - t).clamp(min=T_EPS)
    return (x1_hat - xt) / max(1.0 - t, T_EPS)


class FlowMatching:
    TIME_SCALE = 100.0
    methods = ("euler", "midpoint", "rk4")
    predictions = ("x1", "velocity")

    def __init__(self, prediction: str = "x1", clip_sample: bool = False) -> None:
        if prediction not in self.predictions:
            raise ValueError(f"unknown flow-matching prediction {prediction!r}; use one of {self.predictions}")
        self.prediction = prediction
        # Diffusion Policy's clip_sample, FM's equivalent (x1 output only): the clean-trajectory estimate held in
        # the normalised range [-1, 1] at every step. Off by default (the paper's FM has none); DDPM's is on.
        self.clip = clip_sample
        # The source's noise scale at test time (a sampling temperature; 1: the N(0, I) it was trained from).
        self.noise_scale = 1.0

    def loss(self, net: Denoiser, x1: torch.Tensor, cond: torch.Tensor, noise: Noise) -> torch.Tensor:
        x0, t = noise.eps, noise.u[:, 0]
        out = net(interpolate(x0, x1, t), t * self.TIME_SCALE, cond)
        return F.mse_loss(out, x1 if self.prediction == "x1" else x1 - x0)

    @torch.no_grad()
    def sample(self, net: Denoiser, cond: torch.Tensor, shape: tuple[int, ...], steps: int, method: str = "euler",
               gen: torch.Generator | None = None) -> torch.Tensor:
        if method not in self.methods:
            raise ValueError(f"unknown flow-matching sampler {method!r}; use one of {self.methods}")
        x = self.noise_scale * torch.randn(shape, generator=gen, device=cond.device)
        dt = 1.0 / steps
        b = shape[0]

        def v(x: torch.Tensor, t: float) -> torch.Tensor:
            out = net(x, torch.full((b,), t * self.TIME_SCALE, device=x.device), cond)
            if self.prediction != "x1":
                return out
            return velocity_from_x1(out.clamp(-1, 1) if self.clip else out, x, t)

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


class MeanFlow:
    """One-step generation that commits to a mode: x_s = x_t + (s - t) u(x_t, t, s). The network sees both times,
    (t, s - t) scaled by TIME_SCALE, one half of the sinusoidal time embedding each."""

    TIME_SCALE = 100.0
    methods = ("euler",)
    EQUAL_TIMES = 0.75  # the share of samples trained with s = t (plain flow matching, u = v); see README
    ADAPTIVE_C = 1e-3  # adaptive loss weight 1 / (error + c) (the paper's p = 1): large errors do not dominate

    def average_velocity(self, net: Denoiser, x: torch.Tensor, t: torch.Tensor, s: torch.Tensor,
                         cond: torch.Tensor) -> torch.Tensor:
        times = torch.stack([t, s - t], dim=1) * self.TIME_SCALE
        return velocity_from_x1(net(x, times, cond), x, t)

    def times(self, noise: Noise) -> tuple[torch.Tensor, torch.Tensor]:
        """(t, s): two uniform times in order; s = t for a share EQUAL_TIMES of the batch."""
        a, b = noise.u[:, 0], noise.u[:, 1]
        t, s = torch.minimum(a, b), torch.maximum(a, b)
        return t, torch.where(noise.u[:, 2] < self.EQUAL_TIMES, t, s)

    def loss(self, net: Denoiser, x1: torch.Tensor, cond: torch.Tensor, noise: Noise) -> torch.Tensor:
        x0 = noise.eps
        t, s = self.times(noise)
        xt, v = interpolate(x0, x1, t), x1 - x0
        # du/dt along the flow: tangent v for x_t and 1 for t, with s held (forward mode, one extra pass). The
        # fused attention kernels have no forward-mode derivative: attention runs the plain math kernel here.
        with sdpa_kernel(SDPBackend.MATH):
            u, du_dt = torch.func.jvp(lambda x, tt: self.average_velocity(net, x, tt, s, cond), (xt, t),
                                      (v, torch.ones_like(t)))[:2]
        target = (v + (s - t).reshape(-1, 1, 1) * du_dt).detach()
        err = (u - target).pow(2).mean(dim=(1, 2))
        return (err / (err.detach() + self.ADAPTIVE_C)).mean()

    @torch.no_grad()
    def sample(self, net: Denoiser, cond: torch.Tensor, shape: tuple[int, ...], steps: int, method: str = "euler",
               gen: torch.Generator | None = None) -> torch.Tensor:
        if method not in self.methods:
            raise ValueError(f"unknown MeanFlow sampler {method!r}; use one of {self.methods}")
        x = torch.randn(shape, generator=gen, device=cond.device)
        for i in range(steps):
            t, s = (torch.full((shape[0],), k / steps, device=x.device) for k in (i, i + 1))
            x = x + (1.0 / steps) * self.average_velocity(net, x, t, s, cond)
        return x

    @staticmethod
    def evaluations(steps: int, method: str) -> int:
        return steps


def squaredcos_cap_v2(n: int, max_beta: float = 0.999) -> torch.Tensor:
    """Betas of the cosine schedule (Nichol & Dhariwal), as diffusers' squaredcos_cap_v2."""
    abar = lambda t: math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    return torch.tensor([min(1 - abar((i + 1) / n) / abar(i / n), max_beta) for i in range(n)], dtype=torch.float64)


class DDPM:
    methods = ("ddpm", "ddim", "ddpm_trailing", "ddim_trailing")  # the suffix overrides the spacing
    spacings = ("leading", "trailing")
    predictions = ("sample", "epsilon")

    def __init__(self, train_steps: int = 100, clip_sample: bool = True, spacing: str = "leading",
                 prediction: str = "sample") -> None:
        if spacing not in self.spacings:
            raise ValueError(f"unknown timestep spacing {spacing!r}; use one of {self.spacings}")
        if prediction not in self.predictions:
            raise ValueError(f"unknown diffusion prediction {prediction!r}; use one of {self.predictions}")
        self.spacing, self.prediction = spacing, prediction
        self.noise_scale = 1.0  # the starting and the ancestral noise's scale at test time (a sampling temperature)
        self.n = train_steps
        self.betas = squaredcos_cap_v2(train_steps)
        self.abar = torch.cumprod(1 - self.betas, 0)
        self.clip = clip_sample

    def loss(self, net: Denoiser, x1: torch.Tensor, cond: torch.Tensor, noise: Noise) -> torch.Tensor:
        k = (noise.u[:, 0] * self.n).long().clamp(max=self.n - 1)  # a uniform diffusion step in 0..n-1
        a = self.abar.to(x1.device, torch.float32)[k][:, None, None]
        xk = a.sqrt() * x1 + (1 - a).sqrt() * noise.eps
        return F.mse_loss(net(xk, k.float(), cond), x1 if self.prediction == "sample" else noise.eps)

    def timesteps(self, steps: int, spacing: str | None = None) -> list[int]:
        """'leading' (diffusers' default): steps=16 -> [90, 84, ..., 0], steps=1 -> [0];
        'trailing': steps=1 -> [99]; steps=16 -> [99, 93, ..., 5]."""
        if not 1 <= steps <= self.n:
            raise ValueError(f"steps must be in 1..{self.n}")
        if (spacing or self.spacing) == "leading":
            ratio = self.n // steps
            return [i * ratio for i in reversed(range(steps))]
        return [int(round(self.n - i * self.n / steps)) - 1 for i in range(steps)]

    @torch.no_grad()
    def sample(self, net: Denoiser, cond: torch.Tensor, shape: tuple[int, ...], steps: int, method: str = "ddpm",
               gen: torch.Generator | None = None) -> torch.Tensor:
        if method not in self.methods:
            raise ValueError(f"unknown diffusion sampler {method!r}; use one of {self.methods}")
        method, _, spacing = method.partition("_")
        x = self.noise_scale * torch.randn(shape, generator=gen, device=cond.device)
        ts = self.timesteps(steps, spacing or None)
        abar = self.abar.tolist()
        for i, t in enumerate(ts):
            prev = ts[i + 1] if i + 1 < len(ts) else -1
            a_t, a_prev = abar[t], (abar[prev] if prev >= 0 else 1.0)
            out = net(x, torch.full((shape[0],), float(t), device=x.device), cond)
            # epsilon: the clean-sample estimate divides the noise error by sqrt(abar_t) (5e-4 at t = 99)
            x0 = out if self.prediction == "sample" else (x - math.sqrt(1 - a_t) * out) / math.sqrt(a_t)
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
                    x = x + self.noise_scale * math.sqrt(var) * torch.randn(shape, generator=gen, device=x.device)
        return x

    @staticmethod
    def evaluations(steps: int, method: str) -> int:
        return steps


class MSERegression:
    """Behaviour cloning: the network maps the observation straight to the trajectory."""

    methods = ("direct",)

    def loss(self, net: Callable, x1: torch.Tensor, cond: torch.Tensor, noise: Noise | None = None) -> torch.Tensor:
        return F.mse_loss(net(cond), x1)

    @torch.no_grad()
    def sample(self, net: Callable, cond: torch.Tensor, shape: tuple[int, ...], steps: int = 1, method: str = "direct",
               gen: torch.Generator | None = None) -> torch.Tensor:
        return net(cond)

    @staticmethod
    def evaluations(steps: int, method: str) -> int:
        return 1
