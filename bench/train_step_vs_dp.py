"""A whole training step, image encoder included: adlpipe's FM-CNN and DP-CNN against Diffusion Policy's own
(issue V.4), side by side in one run: samples per second, ours over theirs.

    python -m venv /tmp/dpvenv && /tmp/dpvenv/bin/pip install torch==2.14.1 torchvision==0.29.1 einops numpy
    /tmp/dpvenv/bin/python bench/train_step_vs_dp.py --dp-git /path/to/diffusion_policy/.git

Run it in its own venv: Diffusion Policy's encoder is torchvision's ResNet-18, and torchvision does not install
beside adlpipe's torch (env notes). Only torch-only parts of adlpipe are imported (its networks, objectives and
optimiser helpers). The observation is one 96 px RGB frame (Push-T's image size), the action 16 waypoints of 5.
- adlpipe: ResNet18GN (width 64: the standard ResNet-18 with GroupNorm) -> its ConditionalUnet1D (the paper
  preset's dims) under its FlowMatching (x1 output) or DDPM (clean-sample output) loss; AdamW(fused=True); its
  EMA (torch._foreach_lerp_).
- Diffusion Policy: torchvision's resnet18 with every BatchNorm replaced by GroupNorm(C // 16, C) and its fc
  removed, as its image encoder builds it (written from that description: its obs encoder needs robomimic);
  its ConditionalUnet1D (cond_predict_scale=True, step embedding 128 as adlpipe's); its DDPM epsilon loss (noise
  added from the same squared-cosine schedule); torch.optim.AdamW; its EMAModel.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))


def adlpipe_step(kind: str, down: tuple[int, ...], obs: int, horizon: int):
    from adlpipe.policy.nets.resnet import ResNet18GN
    from adlpipe.policy.nets.unet1d import ConditionalUnet1D
    from adlpipe.policy.objectives import DDPM, FlowMatching, draw_noise
    from adlpipe.policy.optim import ADAMW_BETAS, EMA

    enc, net = ResNet18GN(3, obs, 64), ConditionalUnet1D(5, obs, down, 5, 8)
    model = torch.nn.ModuleList([enc, net])
    objective = FlowMatching() if kind == "fm" else DDPM()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, betas=ADAMW_BETAS, weight_decay=1e-6, fused=True)
    ema = EMA(model)

    def step(image: torch.Tensor, action: torch.Tensor) -> None:
        loss = objective.loss(net, action, enc(image), draw_noise(tuple(action.shape)))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        ema.update(model)

    return step, sum(p.numel() for p in model.parameters())


def dp_step(down: tuple[int, ...], horizon: int):
    import torchvision
    from diffusion_policy.model.diffusion.conditional_unet1d import ConditionalUnet1D as DPUnet
    from diffusion_policy.model.diffusion.ema_model import EMAModel

    enc = torchvision.models.resnet18(weights=None)
    enc.fc = torch.nn.Identity()
    _groupnorm(enc)
    net = DPUnet(input_dim=5, global_cond_dim=512, diffusion_step_embed_dim=128, down_dims=list(down), kernel_size=5,
                 n_groups=8, cond_predict_scale=True)
    model = torch.nn.ModuleList([enc, net])
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, betas=(0.95, 0.999), eps=1e-8, weight_decay=1e-6)
    ema = EMAModel(copy.deepcopy(model), power=0.75)
    steps = 100
    alpha_bar = torch.cos((torch.arange(steps + 1) / steps + 0.008) / 1.008 * torch.pi / 2) ** 2
    alpha_bar = (alpha_bar / alpha_bar[0])[1:]

    def step(image: torch.Tensor, action: torch.Tensor) -> None:
        feat = enc(image)
        eps = torch.randn_like(action)
        k = torch.randint(0, steps, (action.shape[0],))
        a = alpha_bar[k][:, None, None]
        noisy = a.sqrt() * action + (1 - a).sqrt() * eps
        loss = F.mse_loss(net(noisy, k, global_cond=feat), eps)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        ema.step(model)

    return step, sum(p.numel() for p in model.parameters())


def _groupnorm(module: torch.nn.Module) -> None:
    for name, child in module.named_children():
        if isinstance(child, torch.nn.BatchNorm2d):
            setattr(module, name, torch.nn.GroupNorm(child.num_features // 16, child.num_features))
        else:
            _groupnorm(child)


def main() -> None:
    from step_vs_dp import dp_package

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--dp-repo", type=Path)
    src.add_argument("--dp-git", type=Path)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--steps", type=int, default=3, help="steps per side per round")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--image", type=int, default=96)
    p.add_argument("--horizon", type=int, default=16)
    p.add_argument("--batches", type=int, nargs="+", default=[32, 64])
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    sys.path.insert(0, str(dp_package(a)))
    down = (256, 512, 1024)
    print(f"torch {torch.__version__}, {a.threads} thread(s), {a.image} px RGB, horizon {a.horizon}, U-Net {down}")
    for batch in a.batches:
        torch.manual_seed(0)
        sides = {"adlpipe FM-CNN": adlpipe_step("fm", down, 512, a.horizon),
                 "adlpipe DP-CNN": adlpipe_step("ddpm", down, 512, a.horizon),
                 "Diffusion Policy": dp_step(down, a.horizon)}
        image, action = torch.randn(batch, 3, a.image, a.image), torch.randn(batch, a.horizon, 5)
        for step, _n in sides.values():
            step(image, action)  # warm-up
        rates: dict[str, list[float]] = {s: [] for s in sides}
        for r in range(a.rounds):
            for s in (list(sides) if r % 2 == 0 else list(reversed(sides))):
                t0 = time.perf_counter()
                for _ in range(a.steps):
                    sides[s][0](image, action)
                rates[s].append(a.steps * batch / (time.perf_counter() - t0))
        theirs = statistics.median(rates["Diffusion Policy"])
        for s, (_step, n) in sides.items():
            mine = statistics.median(rates[s])
            print(f"batch {batch}: {s}: {mine:.2f} samples/s ({n / 1e6:.1f} M parameters), "
                  f"{mine / theirs:.2f}x Diffusion Policy's", flush=True)


if __name__ == "__main__":
    main()
