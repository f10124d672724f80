"""What the training loop updates the weights with, apart from the optimiser itself: the learning-rate schedule
and the EMA of the weights that validation, evaluation and inference use."""

from __future__ import annotations

import copy
import math

import torch

# Diffusion Policy's optimiser settings, used for every model alike (N): AdamW betas (0.95, 0.999), 500 warm-up steps,
# EMA capped at 0.9999. (It clips no gradients; train clips at norm 1 for every model: see train's --grad-clip.)
ADAMW_BETAS = (0.95, 0.999)
WARMUP_STEPS = 500


def cosine_with_warmup(opt: torch.optim.Optimizer, warmup: int, total: int) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up over `warmup` steps (at most half the run: a tiny test run still reaches its lr), then cosine
    decay to zero at `total`."""
    warmup = min(warmup, total // 2)

    def f(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        progress = (step - warmup) / max(1, total - warmup)
        return 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))

    return torch.optim.lr_scheduler.LambdaLR(opt, f)


class EMA:
    """Exponential moving average of the weights with Diffusion Policy's warm-up: decay = 1 - (1 + step/1)^-0.75,
    capped at max_decay (Diffusion Policy's 0.9999), so early averages are not dominated by the random
    initialisation."""

    def __init__(self, model: torch.nn.Module, max_decay: float = 0.9999) -> None:
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.max_decay = max_decay
        self.step = 0

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.step += 1
        decay = min(self.max_decay, max(0.0, 1 - (1 + self.step) ** -0.75))
        # e += (1 - decay) (p - e) for all tensors in one call: a quarter of a per-tensor loop's time
        torch._foreach_lerp_(list(self.model.parameters()), [p.detach() for p in model.parameters()], 1 - decay)
        for e, b in zip(self.model.buffers(), model.buffers(), strict=True):
            e.copy_(b)
