"""Inference latency vs sampling steps for flow matching and diffusion, in one run.

    python bench/infer.py [--config small|paper] [--threads N] [--repeats 30] [--models models/fm_cnn models/dp_cnn]
                          [--device auto|cpu|cuda[:N]] [--precision fp32|bf16] [--compile]

Batch 1, encoder included, the device synchronised before each clock read; every series (model, sampler, steps)
is timed once per round in a shuffled order and the median over --repeats rounds is printed, so no series pays for
running last. Without --models, fresh networks of the preset are timed (latency does not depend on the weights).
Prints a table and the ratios DP-16 / FM-1 for DDPM (DP's default sampler, README's DP-16) and DDIM.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from adlpipe.plumbing.cli import Parser
from adlpipe.plumbing.runtime import Placement, add_device_args
from adlpipe.policy.checkpoint import load_policy
from adlpipe.policy.inference import interleaved_latency_ms
from adlpipe.policy.models import Policy, preset

STEPS = [1, 2, 4, 8, 16]


def main() -> None:
    p = Parser("python bench/infer.py", __doc__)
    p.add_argument("--config", default="small", choices=["small", "paper"])
    p.add_argument("--models", nargs="*", type=Path, help="trained model folders instead of fresh networks")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--threads", type=int, default=0)
    add_device_args(p, compile_option=True)
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    placement = Placement.from_args(args)
    torch.manual_seed(0)
    if args.models:
        policies = {d.name: load_policy(d / "model.pt", placement)[0] for d in args.models}
    else:
        policies = {m: Policy(preset(args.config, m)).to(placement.device).eval()
                    for m in ("fm_cnn", "dp_cnn", "fm_transformer")}
        if placement.compile:
            policies = {m: pol.compile_for_inference() for m, pol in policies.items()}
    calls = {}
    for name, pol in policies.items():
        obs = torch.randn(1, pol.cfg.in_channels, pol.cfg.image_size, pol.cfg.image_size)
        methods = ["euler"] if pol.kind == "fm" else ["ddpm", "ddim"] if pol.kind == "ddpm" else ["direct"]
        calls.update({(f"{name}/{method}", k): (pol, obs, k, method) for method in methods for k in STEPS})
    ms = interleaved_latency_ms(calls, args.repeats, placement)  # every series in every round: no order bias
    rows: dict[str, dict[int, float]] = {}
    for (series, k), v in ms.items():
        rows.setdefault(series, {})[k] = v
    print(f"config {args.config}, threads {torch.get_num_threads()}, device {placement.device}, "
          f"{placement.precision}{', compiled' if placement.compile else ''}, batch 1, median ms of "
          f"{args.repeats} interleaved rounds")
    print("series".ljust(24) + "".join(f"{k:>9d}" for k in STEPS))
    for name, r in rows.items():
        print(name.ljust(24) + "".join(f"{r[k]:9.2f}" for k in STEPS))
    fm = next(r for n, r in rows.items() if n.endswith("/euler") and n.startswith("fm_cnn"))
    ratios = {f"{n.split('/')[1].upper()}-16 / FM-1": r[16] / fm[1] for n, r in rows.items() if n.startswith("dp_")}
    for label, ratio in ratios.items():
        print(f"DP {label} = {ratio:.1f}x")
    print(json.dumps({"config": args.config, "device": str(placement.device), "precision": placement.precision,
                      "compiled": placement.compile, "ms": rows, "dp16_over_fm1": ratios}))

if __name__ == "__main__":
    main()
