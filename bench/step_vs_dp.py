"""One training step of adlpipe's conditional U-Net against Diffusion Policy's own, each with its own optimiser and
EMA code: samples per second, interleaved rounds.

    python bench/step_vs_dp.py --dp-git /path/to/diffusion_policy/.git   (or --dp-repo a checkout)

Needs a checkout (or the git folder) of real-stanford/diffusion_policy and einops (pip install einops: a bench-only
dependency, not adlpipe's). Both sides take the same step: noise a batch of (B, horizon, 5) trajectories, predict
with the U-Net conditioned on a (B, obs_dim) observation feature and the step, MSE loss, backward, AdamW step, EMA
update. adlpipe: its ConditionalUnet1D, AdamW(fused=True), its EMA (torch._foreach_lerp_). Diffusion Policy: its
ConditionalUnet1D (cond_predict_scale=True, step embedding 128 as adlpipe's), torch.optim.AdamW as its training
workspace builds it, and its EMAModel. The image encoder is left out: Diffusion Policy's is torchvision's
ResNet-18 (with its BatchNorms replaced by GroupNorm), and torchvision is not installed here (its wheel would pull
another torch); the feature it would give is drawn at random on both sides.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PRESETS = {"small": ((32, 64, 128), 64), "paper": ((256, 512, 1024), 512)}  # down_dims, obs feature size


def dp_package(args: argparse.Namespace) -> Path:
    """A folder holding the diffusion_policy package (the checkout, or extracted from the git folder)."""
    if args.dp_repo:
        return args.dp_repo
    out = Path(tempfile.mkdtemp(prefix="dp-"))
    archive = subprocess.run(["git", "--git-dir", str(args.dp_git), "archive", "HEAD", "diffusion_policy/model"],
                             check=True, capture_output=True).stdout
    with tempfile.NamedTemporaryFile(suffix=".tar") as f:
        f.write(archive)
        f.flush()
        with tarfile.open(f.name) as t:
            t.extractall(out, filter="data")
    for d in (out / "diffusion_policy", out / "diffusion_policy" / "model"):
        (d / "__init__.py").touch()
    return out


def make_step(side: str, down: tuple[int, ...], obs: int, horizon: int, dp_root: Path):
    """(step function, its parameters count) of one side."""
    if side == "adlpipe":
        from adlpipe.policy.nets.unet1d import ConditionalUnet1D
        from adlpipe.policy.optim import ADAMW_BETAS, EMA

        net = ConditionalUnet1D(5, obs, down, 5, 8)
        opt = torch.optim.AdamW(net.parameters(), lr=1e-4, betas=ADAMW_BETAS, weight_decay=1e-6, fused=True)
        ema = EMA(net)

        def update() -> None:
            ema.update(net)
    else:
        sys.path.insert(0, str(dp_root))
        from diffusion_policy.model.diffusion.conditional_unet1d import ConditionalUnet1D as DPUnet
        from diffusion_policy.model.diffusion.ema_model import EMAModel

        net = DPUnet(input_dim=5, global_cond_dim=obs, diffusion_step_embed_dim=128, down_dims=list(down),
                     kernel_size=5, n_groups=8, cond_predict_scale=True)
        opt = torch.optim.AdamW(net.parameters(), lr=1e-4, betas=(0.95, 0.999), eps=1e-8, weight_decay=1e-6)
        import copy

        ema = EMAModel(copy.deepcopy(net), power=0.75)

        def update() -> None:
            ema.step(net)

    def step(batch: int) -> None:
        x = torch.randn(batch, horizon, 5)
        cond = torch.randn(batch, obs)
        t = torch.randint(0, 100, (batch,)).float()
        loss = torch.nn.functional.mse_loss(net(x, t, cond) if side == "adlpipe" else net(x, t, global_cond=cond),
                                            x)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        update()

    return step, sum(p.numel() for p in net.parameters())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--dp-repo", type=Path, help="a checkout of real-stanford/diffusion_policy")
    src.add_argument("--dp-git", type=Path, help="its git folder (the package is extracted from HEAD)")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--steps", type=int, default=10, help="steps per side per round")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--horizon", type=int, default=32)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    root = dp_package(a)
    for preset, (down, obs) in PRESETS.items():
        for batch in (32, 64):
            torch.manual_seed(0)
            sides = {s: make_step(s, down, obs, a.horizon, root) for s in ("adlpipe", "diffusion_policy")}
            for step, _n in sides.values():  # warm up
                step(batch)
            rates: dict[str, list[float]] = {s: [] for s in sides}
            for r in range(a.rounds):
                for s in (list(sides) if r % 2 == 0 else list(reversed(sides))):  # interleaved
                    t0 = time.perf_counter()
                    for _ in range(a.steps):
                        sides[s][0](batch)
                    rates[s].append(a.steps * batch / (time.perf_counter() - t0))
            ours, theirs = statistics.median(rates["adlpipe"]), statistics.median(rates["diffusion_policy"])
            print(f"{preset} U-Net {down}, batch {batch}: adlpipe {ours:.0f} samples/s "
                  f"({sides['adlpipe'][1] / 1e6:.2f} M params), Diffusion Policy {theirs:.0f} samples/s "
                  f"({sides['diffusion_policy'][1] / 1e6:.2f} M); ratio {ours / theirs:.2f}", flush=True)


if __name__ == "__main__":
    main()
