"""Why closed loop stalls, measured on recorded test windows: how far a closed-loop model's plan moves the arm
against how far the demonstration moves it from the same frame, with the model's true observation history and with
a history that shows the arm standing still (the older frame replaced by the newest, image and state alike).

A policy whose plans shrink when the history shows no motion copies the motion it sees (the "copycat" problem of
behaviour cloning from observation histories, Wen et al., NeurIPS 2020): in the demonstrations the arm's recent
motion predicts its next motion, and the model leans on it. Closed loop then compounds: a plan that moves the arm a
little too little shows a slower arm in the next frames, whose plan is slower again, until the arm creeps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..dataset.loader import Normalizer, WindowDataset, Windows
from ..plumbing.runtime import Placement
from ..policy.checkpoint import load_policy
from ..policy.inference import predict

MOVING_M = 0.01  # a window whose demonstrated plan moves the arm less than this (over Ta waypoints) is a dwell


def plan_lengths(model_dir: Path, checkpoint: str, data: Path, names: list[str], execute: int, steps: int,
                 frames_per_episode: int = 12, seed: int = 0) -> dict[str, np.ndarray]:
    """Per window: "demo" the demonstration's path over the first `execute` waypoints of the plan (metres), "true"
    the model's with its true history, "frozen" the model's with a history showing the arm standing still, "error"
    how far the model's waypoint `execute` (true history) lies from the demonstration's (metres), "first" 1 for an
    episode's first frame (the arm at home: the plan that has to find the object or the person)."""
    placement = Placement()
    policy, ck = load_policy(model_dir / checkpoint, placement)
    cfg = policy.cfg
    norm = Normalizer(ck["stats"])
    ds = WindowDataset(data, names, ck["stats"], cfg.image_size,
                       Windows(cfg.n_obs, cfg.horizon, cfg.rate_hz, cfg.target), cfg.use_depth,
                       frames_per_episode=frames_per_episode)
    per_frame = cfg.in_channels // cfg.n_obs
    out: dict[str, list[float]] = {"demo": [], "true": [], "frozen": [], "error": [], "first": []}
    gen = placement.generator(seed)
    for i in range(len(ds)):
        e, k = ds.window(i)
        obs, state, target = ds.raw(e, k)
        frozen_obs = np.concatenate([obs[-per_frame:]] * cfg.n_obs)
        frozen_state = np.repeat(state[-1:], cfg.n_obs, axis=0)
        out["demo"].append(_length(target[:execute, 2:]))
        out["first"].append(float(k == 0))
        for key, (o, s) in (("true", (obs, state)), ("frozen", (frozen_obs, frozen_state))):
            x = (torch.from_numpy(o.astype(np.float32))[None], ds.normalize_state(s)[None])
            plan = norm.unnormalize(predict(policy, x, steps, None, gen, placement))[0, :execute, 2:].numpy()
            out[key].append(_length(plan))
            if key == "true":
                out["error"].append(float(np.linalg.norm(plan[-1] - target[execute - 1, 2:])))
    return {k: np.array(v) for k, v in out.items()}


def _length(offsets: np.ndarray) -> float:
    """Path length of waypoints given as offsets from the anchor (the anchor itself first)."""
    pts = np.vstack([np.zeros(3), offsets])
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
