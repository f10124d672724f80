"""What a training step of the state Push-T U-Net costs here at adlpipe's small widths and at Diffusion Policy's
(issue L2: can the wider U-Net be trained to convergence across sessions?).

    OMP_NUM_THREADS=1 python bench/unet_step_cost.py [--steps 5]

One optimiser step (AdamW) of the conditional 1D U-Net as the Push-T runs train it: batch 64, Tp 16 actions of 2,
To 2 frames of the 20-D state as the condition, one thread. Prints parameters and ms per step for each width.
"""

from __future__ import annotations

import argparse
import time

import torch

from adlpipe.policy.nets.unet1d import ConditionalUnet1D

WIDTHS = {"small (adlpipe)": (32, 64, 128), "Diffusion Policy": (256, 512, 1024)}


def step_ms(dims: tuple[int, ...], steps: int) -> tuple[float, float]:
    net = ConditionalUnet1D(2, 2 * 20, dims)
    opt = torch.optim.AdamW(net.parameters(), 1e-3)
    x, t, cond = torch.randn(64, 16, 2), torch.rand(64) * 100, torch.randn(64, 40)

    def step() -> None:
        loss = net(x, t, cond).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    step()  # the first step allocates
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return sum(p.numel() for p in net.parameters()) / 1e6, (time.perf_counter() - t0) / steps * 1000


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=5)
    a = p.parse_args()
    torch.set_num_threads(1)
    for name, dims in WIDTHS.items():
        params, ms = step_ms(dims, a.steps)
        print(f"{name} {dims}: {params:.1f} M parameters, {ms:.0f} ms per step")


if __name__ == "__main__":
    main()
