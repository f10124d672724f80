"""How well each round's policy plans at the states a round's rollouts reach, against the expert's label there.

    python dagger_fit.py fm_cnn --split ../../data/split.json -o metrics/dagger/fit_fm_cnn.json

For one objective, three policies (round 0 `models/M`, DAgger round 1 `models_dagger/r1/M`, the control
`models_dagger/more/M`) plan on three sets of windows, in the training windows' own format (the loader's
`WindowDataset`, target "recovery", each policy's own normalisation), with its default sampler and fixed noise:
- `demo_test`: the default split's test demonstrations (4 frames each);
- `rollouts_r1`: round 1's rollouts of the round-0 policy (what round 1 trained on);
- `rollouts_r2`: round 2's rollouts, by the round-1 policy (states round 1 reached; no policy trained on them).
Per policy and set: the plan's distance from the label (cm, mean over the 16 waypoints and over the 8 executed),
split by whether the anchor (the command) is more than 2 cm off the demonstrated path; where the plan's last
waypoint ends against the path (cm off it), its length against the label's, the share of the labels' values
outside the policy's normalisation range (what a clipping sampler cannot reach), and how far the command (the
labels' anchor) is from the measured end effector (the policy's state input). docs/science/dagger.md reads it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np
import torch

from adlpipe.dataset.loader import WindowDataset, Windows, reference_series
from adlpipe.policy.checkpoint import load_policy
from adlpipe.policy.models import ModelConfig
from adlpipe.sim.dagger import Expert
from adlpipe.training.data import collate_obs

OFF_PATH_M = 0.02
BATCH = 64


def rollout_names(data: Path, demos: set[str], exclude: set[str] = frozenset()) -> list[str]:
    with h5py.File(data) as f:
        return sorted(n for n in f["episodes"] if n not in demos and n not in exclude)


def frames_of(data: Path, names: list[str]) -> int:
    """How many training windows the episodes give (a window per frame up to the end of the demonstration)."""
    with h5py.File(data) as f:
        return sum(int(np.searchsorted(f["episodes"][n]["frames/t"][()], float(f["episodes"][n].attrs["duration_s"]),
                                       "right")) for n in names)


def windows_of(data: Path, names: list[str], stats: dict, cfg, per_episode: int) -> WindowDataset:
    w = Windows(cfg.n_obs, cfg.horizon, cfg.rate_hz, "recovery", cfg.use_image)
    return WindowDataset(data, names, stats, cfg.image_size, w, cfg.use_depth, frames_per_episode=per_episode,
                         cameras=cfg.cameras)


def path_geometry(ds: WindowDataset) -> tuple[np.ndarray, np.ndarray, list[Expert]]:
    """Per window: the anchor (the command at the frame, metres), the measured end effector there (what the
    policy's state input holds) and the scene's expert (its path)."""
    anchors, measured, experts = [], [], []
    for e, k in ds.items:
        m = ds.episode_meta(e)
        g = ds.files.group(ds.names[e])
        rt, rp = reference_series(g, ds.names[e])
        anchors.append(m["now"][k])
        measured.append(m["state"][k][:3])
        experts.append(Expert(rt, rp, ds.w.horizon, ds.w.rate_hz))
    return np.array(anchors), np.array(measured), experts


@torch.no_grad()
def plans(policy, ds: WindowDataset, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(plans, labels) in metres relative to the anchor (N, H, 3), and the share of label values outside [-1, 1]."""
    out, labels, outside = [], [], []
    gen = torch.Generator().manual_seed(seed)
    for s in range(0, len(ds), BATCH):
        items = [ds[i] for i in range(s, min(s + BATCH, len(ds)))]
        obs = collate_obs([o for o, _ in items])
        target = torch.stack([a for _, a in items])
        pred = policy.predict(obs, policy.default_steps, None, gen)
        out.append(ds.norm.unnormalize(pred)[..., 2:5].numpy())
        labels.append(ds.norm.unnormalize(target)[..., 2:5].numpy())
        outside.append((target.abs() > 1).float().mean().item())
    return np.concatenate(out), np.concatenate(labels), float(np.mean(outside))


def summary(pred: np.ndarray, label: np.ndarray, anchors: np.ndarray, measured: np.ndarray, experts: list[Expert],
            outside: float) -> dict:
    err = np.linalg.norm(pred - label, axis=-1)  # (N, H) metres
    off = np.array([x.off_path(a)[0] for x, a in zip(experts, anchors, strict=True)]) > OFF_PATH_M
    end_off = np.array([x.off_path(a + p[-1])[0] for x, a, p in zip(experts, anchors, pred, strict=True)])
    length = lambda p: np.linalg.norm(np.diff(np.concatenate([np.zeros_like(p[:, :1]), p], 1), axis=1), axis=-1).sum(1)  # noqa: E731
    ratio = length(pred) / np.maximum(length(label), 1e-4)
    cm = lambda x: round(100 * float(np.mean(x)), 2) if len(x) else None  # noqa: E731
    gap = np.linalg.norm(anchors - measured, axis=1)
    return {"windows": len(err), "off_path_share": round(float(off.mean()), 3),
            "error_cm": cm(err), "error_executed_cm": cm(err[:, :8]),
            "error_on_path_cm": cm(err[~off]), "error_off_path_cm": cm(err[off]),
            "plan_end_off_path_cm": {"on": cm(end_off[~off]), "off": cm(end_off[off])},
            "plan_over_label_length": {"on": round(float(np.median(ratio[~off])), 3) if (~off).any() else None,
                                       "off": round(float(np.median(ratio[off])), 3) if off.any() else None},
            "labels_outside_range": round(outside, 4),
            # the label is relative to the command, the policy sees the measured end effector: a gap it cannot see
            "command_from_measured_cm": {"median": round(100 * float(np.median(gap)), 2),
                                         "p90": round(100 * float(np.percentile(gap, 90)), 2)}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", help="fm_cnn, dp_cnn or bc_cnn")
    p.add_argument("--split", type=Path, required=True)
    p.add_argument("--per-episode", type=int, default=4, help="frames per episode, evenly spaced")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--out", type=Path, required=True)
    a = p.parse_args()
    torch.set_num_threads(1)
    split = json.loads(a.split.read_text())
    demos = set(split["train"]) | set(split["test"])
    r1 = Path(f"data/dagger/r1/{a.model}/adl.h5")
    r2 = Path(f"data/dagger/r2/{a.model}/adl.h5")
    r1_names = rollout_names(r1, demos)
    sets = {"demo_test": (Path("../../data/adl.h5"), sorted(split["test"])), "rollouts_r1": (r1, r1_names)}
    if r2.exists():
        sets["rollouts_r2"] = (r2, rollout_names(r2, demos, set(r1_names)))
    policies = {"round 0": Path(f"models/{a.model}/best.pt"),
                "DAgger round 1": Path(f"models_dagger/r1/{a.model}/best.pt"),
                "DAgger round 2": Path(f"models_dagger/r2/{a.model}/best.pt"),
                "control": Path(f"models_dagger/more/{a.model}/best.pt")}
    out: dict = {"model": a.model, "per_episode": a.per_episode, "sets": {k: len(v[1]) for k, v in sets.items()},
                 # round 1's training windows: the training demonstrations' against its rollouts'
                 "round1_windows": {"demonstrations": frames_of(r1, sorted(split["train"])),
                                    "rollouts": frames_of(r1, r1_names)}}
    for arm, path in policies.items():
        if not path.exists():
            continue
        policy, ck = load_policy(path)
        cfg = ModelConfig.from_dict(ck["config"])
        out[arm] = {}
        for name, (data, names) in sets.items():
            ds = windows_of(data, names, ck["stats"], cfg, a.per_episode)
            anchors, measured, experts = path_geometry(ds)
            pred, label, outside = plans(policy, ds, a.seed)
            out[arm][name] = summary(pred, label, anchors, measured, experts, outside)
            print(arm, name, json.dumps(out[arm][name]), flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
