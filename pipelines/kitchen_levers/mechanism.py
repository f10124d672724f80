"""Why flow matching trails Diffusion Policy on Franka Kitchen (issue L3, item 1): the two trained networks measured
on the held-out test episodes' windows (the demonstrator's own states, teacher-forced), in the format the policies
are trained and run in (the 2-frame 59-D state, the normalised 16-step joint-velocity chunk).

1. The fit by noise level. Both networks predict the clean chunk x1 from a noised one; FM's x_t = t*x1 + (1-t)*x0
   and DDPM's x_k = sqrt(a_k)*x1 + sqrt(1-a_k)*eps hold the same information where t = sqrt(a)/(sqrt(a)+sqrt(1-a))
   (x_t is x_k scaled by 1/(sqrt(a)+sqrt(1-a))). At DDPM steps k and their matched t, the same x1 and the same
   noise: each network's squared error of x1 (its training loss there, and its one-step error: one Euler step from
   t, or one DDIM step to k = 0, lands on it), and the share of each objective's training draws in each band.
2. The plans (teacher-forced): S samples per window at 2 and 16 steps; against the demonstrator's chunk, over the
   Ta = 8 executed actions: the error of a sample, the error of the samples' mean (bias), their spread around
   it, and the share of values outside [-1, 1] (the range DDPM's sampler clips to, FM's does not); per sub-task
   phase (the first of the demonstrator's order not yet done at that frame) and over all. Also each with the other's
   clipping (FM with its x1 estimate clipped, DP without) and each with its noise at half scale (a temperature).

    python pipelines/kitchen_levers/mechanism.py models/fm_cnn_e30 models/dp_cnn_e30 \
        --data data/kitchen.h5 --split data/split.json --out results/mechanism_e30.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch
from gymnasium_robotics.envs.franka_kitchen.kitchen_env import BONUS_THRESH, OBS_ELEMENT_GOALS, OBS_ELEMENT_INDICES
from phases import ORDER  # the demonstrator's order of the sub-tasks (this folder's phases.py)

from adlpipe.dataset.loader import WindowDataset, Windows
from adlpipe.policy.checkpoint import load_policy
from adlpipe.policy.models import ModelConfig, Policy
from adlpipe.training.data import collate_obs

QPOS_IN_OBS = 9  # the 59-D observation is robot qpos (9), qvel (9), object qpos, qvel: qpos index i is at i + 9
DDPM_STEPS = (0, 5, 10, 20, 30, 40, 50, 60, 70, 80, 90, 99)
EXECUTED = 8  # Ta


def done_at(states: np.ndarray) -> dict[str, int]:
    """Per sub-task, the first frame of an episode's 59-D states where the environment's own test holds (within
    BONUS_THRESH of its goal); a task done stays done (as the environment counts it: the microwave door swings back
    a little after it was opened). len(states) if never (the recording ends on the step that completes the last)."""
    out = {}
    for task in ORDER:
        d = np.linalg.norm(states[:, OBS_ELEMENT_INDICES[task] + QPOS_IN_OBS] - OBS_ELEMENT_GOALS[task], axis=1)
        hit = np.flatnonzero(d < BONUS_THRESH)
        out[task] = int(hit[0]) if len(hit) else len(states)
    return out


def phase(done: dict[str, int], k: int) -> str:
    """The first sub-task of the demonstrator's order not yet done at frame k."""
    return next((task for task in ORDER if done[task] > k), "all done")


def test_windows(data: Path, names: list[str], stats: dict, cfg: ModelConfig,
                 per_episode: int) -> tuple[tuple, torch.Tensor, list]:
    """(observation, normalised demonstrated chunk (N, horizon, action_dim), phase per window) of `per_episode`
    evenly spaced frames of each test episode, windowed as the model was trained (its config)."""
    windows = Windows(cfg.n_obs, cfg.horizon, cfg.rate_hz, cfg.target, cfg.use_image)
    ds = WindowDataset(data, names, stats, cfg.image_size, windows, frames_per_episode=per_episode)
    items = [ds[i] for i in range(len(ds))]
    done = {e: done_at(ds.episode_meta(e)["state"]) for e in {e for e, _ in ds.items}}
    phases = [phase(done[e], k) for e, k in ds.items]
    return collate_obs([o for o, _ in items]), torch.stack([a for _, a in items]), phases


def matched_t(k: int, abar: torch.Tensor) -> float:
    a = float(abar[k])
    return math.sqrt(a) / (math.sqrt(a) + math.sqrt(1 - a))


@torch.no_grad()
def fit_by_noise(fm: Policy, dp: Policy, obs: tuple, x1: torch.Tensor, seed: int) -> list[dict]:
    """Per DDPM step k and its matched flow time: each network's mean squared error of x1 (normalised units) on the
    same windows and noise; the executed part apart."""
    abar = dp.objective.abar.float()
    eps = torch.randn(x1.shape, generator=torch.Generator().manual_seed(seed))
    cf, cd = fm.condition(obs), dp.condition(obs)
    rows = []
    for k in DDPM_STEPS:
        a, t = float(abar[k]), matched_t(k, abar)
        xk = math.sqrt(a) * x1 + math.sqrt(1 - a) * eps
        xt = xk / (math.sqrt(a) + math.sqrt(1 - a))  # = t*x1 + (1-t)*eps exactly
        n = len(x1)
        out_dp = dp.net(xk, torch.full((n,), float(k)), cd)
        out_fm = fm.net(xt, torch.full((n,), t * fm.objective.TIME_SCALE), cf)
        err = {name: (out - x1).pow(2) for name, out in (("fm", out_fm), ("dp", out_dp))}
        rows.append({"k": k, "t": round(t, 4), "log_snr": round(math.log(a / (1 - a)), 3),
                     **{f"{m}_mse": float(e.mean()) for m, e in err.items()},
                     **{f"{m}_mse_executed": float(e[:, :EXECUTED].mean()) for m, e in err.items()}})
    return rows


def training_share(abar: torch.Tensor, edges: list[float]) -> list[dict]:
    """The share of each objective's training draws whose (matched) flow time falls in each band: FM draws t
    uniformly, DDPM its step k uniformly in 0..99."""
    ts = np.array([matched_t(k, abar) for k in range(len(abar))])
    return [{"t_from": lo, "t_to": hi, "fm": hi - lo, "dp": float(np.mean((ts >= lo) & (ts < hi)))}
            for lo, hi in zip(edges[:-1], edges[1:], strict=True)]


@torch.no_grad()
def plans(policy: Policy, obs: tuple, x1: torch.Tensor, steps: int, samples: int, seed: int,
          clip: bool, noise_scale: float = 1.0) -> dict[str, torch.Tensor]:
    """Per window: sample error, bias, spread (RMS over the executed actions, normalised units) and the share of
    values outside [-1, 1], of `samples` plans at `steps` with the sampler's clipping set to `clip` and its noise
    scaled by `noise_scale`."""
    was = policy.objective.clip, policy.objective.noise_scale
    policy.objective.clip, policy.objective.noise_scale = clip, noise_scale
    try:
        cond = policy.condition(obs)
        gen = torch.Generator().manual_seed(seed)
        draws = torch.stack([policy.sample(cond, steps, None, gen)[:, :EXECUTED] for _ in range(samples)])
    finally:
        policy.objective.clip, policy.objective.noise_scale = was
    demo = x1[:, :EXECUTED]
    mean = draws.mean(0)
    return {"error": (draws - demo).pow(2).mean(dim=(2, 3)).mean(0).sqrt(),
            "bias": (mean - demo).pow(2).mean(dim=(1, 2)).sqrt(),
            "spread": (draws - mean).pow(2).mean(dim=(0, 2, 3)).sqrt(),
            "outside": (draws.abs() > 1).float().mean(dim=(0, 2, 3))}


def summarise(per_window: dict[str, torch.Tensor], phases: list[str]) -> dict[str, dict[str, float]]:
    out = {}
    for name in (*ORDER, "all done", "all"):
        mask = torch.tensor([name == "all" or p == name for p in phases])
        if mask.any():
            out[name] = {m: float(v[mask].mean()) for m, v in per_window.items()} | {"windows": int(mask.sum())}
    return out


def markdown(r: dict) -> str:
    """The two tables of a result, for docs/science/kitchen.md."""
    lines = [f"FM {r['fm']} against DP {r['dp']}: {r['windows']} windows of {r['episodes']} test episodes "
             f"(phases: {', '.join(f'{k} {v}' for k, v in r['phases'].items())}); normalised units ([-1, 1]).", "",
             "| DDPM step k | matched t | log SNR | FM mse of x1 | DP mse of x1 | FM / DP | executed 8: FM / DP |",
             "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    lines += [f"| {f['k']} | {f['t']:.3f} | {f['log_snr']:+.2f} | {f['fm_mse']:.4f} | {f['dp_mse']:.4f} | "
              f"{f['fm_mse'] / f['dp_mse']:.2f} | {f['fm_mse_executed']:.4f} / {f['dp_mse_executed']:.4f} |"
              for f in r["fit"]]
    lines += ["", "| matched t | FM's training draws | DP's |", "| --- | ---: | ---: |"]
    lines += [f"| {b['t_from']:.1f}-{b['t_to']:.1f} | {b['fm']:.0%} | {b['dp']:.0%} |" for b in r["training_share"]]
    lines += ["", "| plans | steps | error, all | bias | spread | outside [-1, 1] | error, kettle phase | "
              "bias, kettle |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for row in r["plans"]:
        a, k = row["by_phase"]["all"], row["by_phase"].get("kettle", {})
        lines.append(f"| {row['model']} | {row['steps']} | {a['error']:.4f} | {a['bias']:.4f} | {a['spread']:.4f} | "
                     f"{a['outside']:.2%} | {k.get('error', float('nan')):.4f} | {k.get('bias', float('nan')):.4f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("fm", type=Path, help="the FM model's folder (its model.pt), or a checkpoint file")
    p.add_argument("dp", type=Path, help="the DP model's, trained with the same budget")
    p.add_argument("--data", type=Path, default=Path("data/kitchen.h5"))
    p.add_argument("--split", type=Path, default=Path("data/split.json"))
    p.add_argument("--frames", type=int, default=40, help="evenly spaced windows per test episode")
    p.add_argument("--samples", type=int, default=4, help="plans per window")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True, help="JSON of every figure")
    p.add_argument("--table", type=Path, help="also the tables as markdown")
    a = p.parse_args()
    torch.set_num_threads(1)
    fm, ck = load_policy(a.fm / "model.pt" if a.fm.is_dir() else a.fm)
    dp, _ = load_policy(a.dp / "model.pt" if a.dp.is_dir() else a.dp)
    if fm.family != "fm" or dp.family != "ddpm" or dp.objective.prediction != "sample":
        raise SystemExit("mechanism.py: needs an FM model (x1 output) and a clean-sample DP model")
    names = json.loads(a.split.read_text())["test"]
    if fm.cfg.to_dict() | {"model": ""} != dp.cfg.to_dict() | {"model": ""}:
        raise SystemExit("mechanism.py: the two models differ in more than their objective (config)")
    obs, x1, phases = test_windows(a.data, names, ck["stats"], fm.cfg, a.frames)
    result = {"fm": str(a.fm), "dp": str(a.dp), "windows": len(x1), "episodes": len(names),
              "samples": a.samples, "phases": {q: phases.count(q) for q in (*ORDER, "all done")},
              "fit": fit_by_noise(fm, dp, obs, x1, a.seed),
              "training_share": training_share(dp.objective.abar.float(), [0, .1, .3, .5, .7, .9, 1.0]),
              "plans": []}
    for steps in (2, 16):
        for name, pol, clip, scale in (("FM", fm, False, 1.0), ("FM clipped", fm, True, 1.0), ("DP", dp, True, 1.0),
                                       ("DP unclipped", dp, False, 1.0), ("FM noise 0.5", fm, False, 0.5),
                                       ("DP noise 0.5", dp, True, 0.5)):
            per = plans(pol, obs, x1, steps, a.samples, a.seed, clip, scale)
            result["plans"].append({"model": name, "steps": steps, "by_phase": summarise(per, phases)})
            print(f"{name:>13} {steps:>2}: " + "  ".join(f"{m} {v:.4f}" for m, v in
                                                          result["plans"][-1]["by_phase"]["all"].items()), flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1) + "\n")
    if a.table:
        a.table.write_text(markdown(result))


if __name__ == "__main__":
    main()
