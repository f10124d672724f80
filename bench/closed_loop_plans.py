"""How good is one closed-loop plan on the demonstrations' own frames? (teacher forcing: no compounding)

    python bench/closed_loop_plans.py [--data data/adl.h5] [--split data/split.json] [--models models/closed_loop/*]

For every test episode, 12 evenly spaced frames: the policy's plan from the recorded frames and state, against the
demonstrated command. Prints, per model, how far the plan moves in Ta = 8 waypoints (0.8 s at 10 Hz) over how far
the command moved, and the error of that waypoint. Compared with closed-loop rollouts (replay's path ratio), it
tells a plan that is already wrong on the demonstrations' states from errors that compound off them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from adlpipe.dataset.loader import Normalizer, WindowDataset, Windows
from adlpipe.policy.checkpoint import load_policy


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, default=Path("data/split.json"))
    p.add_argument("--models", type=Path, nargs="+", default=sorted(Path("models/closed_loop").glob("*")))
    p.add_argument("--ta", type=int, default=8)
    a = p.parse_args()
    torch.set_num_threads(1)
    names = json.loads(a.split.read_text())["test"]
    for model in a.models:
        policy, ck = load_policy(model / "best.pt")
        cfg = policy.cfg
        ds = WindowDataset(a.data, names, ck["stats"], cfg.image_size,
                           Windows(cfg.n_obs, cfg.horizon, cfg.rate_hz, cfg.target), frames_per_episode=12)
        norm = Normalizer(ck["stats"])
        planned, shown, err = [], [], []
        for i in range(0, len(ds), 64):
            items = [ds[j] for j in range(i, min(i + 64, len(ds)))]
            obs = (torch.stack([o[0] for o, _ in items]), torch.stack([o[1] for o, _ in items]))
            target = norm.unnormalize(torch.stack([t for _, t in items]))[:, a.ta - 1, 2:]
            pred = norm.unnormalize(policy.predict(obs, policy.default_steps, None,
                                                   torch.Generator().manual_seed(0)))[:, a.ta - 1, 2:]
            planned.append(pred.norm(dim=-1))
            shown.append(target.norm(dim=-1))
            err.append((pred - target).norm(dim=-1))
        pl, sh, er = torch.cat(planned), torch.cat(shown), torch.cat(err)
        print(f"{model}: {len(sh)} windows; planned / demonstrated displacement over {a.ta} waypoints "
              f"{float(pl.mean() / sh.mean()):.2f}; error of waypoint {a.ta} {100 * float(er.mean()):.1f} cm against "
              f"a displacement of {100 * float(sh.mean()):.1f} cm")


if __name__ == "__main__":
    main()
