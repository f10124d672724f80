"""How accurate and how fast a trained policy is on the recorded test split: per checkpoint, sampler and step count,
the per-waypoint error in pixels and centimetres (per task and overall, with intervals and the per-episode errors
for paired tests), the best-of-K error, mode commitment on the two-mode tasks, the latency, the error in every
other camera, and the blind baseline's rows."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch

from ..dataset import schema
from ..dataset.loader import Normalizer, TrajectoryDataset, check_cameras
from ..geometry.camera import project
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Placement
from ..policy.blind import BLIND, blind_predictions, task_means
from ..policy.checkpoint import load_policy
from ..policy.inference import phase_samples_ms, predict
from ..policy.models import DEFAULT_METHOD, DEFAULT_STEPS, MODELS
from .metrics import commitment, waypoint_errors
from .stats import mean_interval, median_interval, ratio_interval

DEFAULTS = {name: f"{DEFAULT_METHOD[kind]}/{DEFAULT_STEPS[kind]}" for name, (kind, _net) in MODELS.items()}
PAPER_IMAGE_PX = 224


def multimodal_tasks() -> set[str]:
    from ..sim.tasks import TASKS

    return {name for name, t in TASKS.items() if t.multimodal}


def _modes_of(job: tuple) -> np.ndarray | None:
    from ..sim.modes import mode_paths

    return mode_paths(*job)


def reference_modes(data: Path, test: list[str], workers: int) -> dict[int, torch.Tensor]:
    """Test index -> (demonstrated, other) mode paths (2, N, 3) for the scenes of two-mode tasks of the simulated
    world that the simulator rebuilds; empty for other data (real robots' tasks: the metric is left out)."""
    multimodal = multimodal_tasks()
    jobs, where = [], []
    with schema.open_dataset(data, test) as f:
        for i, name in enumerate(test):
            g = f[schema.EPISODES][name]
            task = str(g.attrs["task"])
            if task in multimodal:
                jobs.append((task, [str(n) for n in g["objects"].attrs["names"]], g["objects"][()], g["traj3d"][()]))
                where.append(i)
    if not jobs:
        return {}
    with ProcessPoolExecutor(max_workers=max(1, min(workers, len(jobs)))) as pool:
        paths = list(pool.map(_modes_of, jobs))
    return {i: torch.from_numpy(p).float() for i, p in zip(where, paths, strict=True) if p is not None}


def mode_figures(samples: list[torch.Tensor], modes: dict[int, torch.Tensor], tasks: list[str]) -> dict:
    """Commitment of every sample (K per scene) on the scenes with rebuilt modes: overall, to the demonstrated mode
    (of the committed ones), and per task. samples: K tensors (B, N, 5) unnormalised. The intervals resample scenes
    (a scene's K samples share its image, so they are not independent)."""
    if not modes:
        return {"commitment": None, "commitment_ci": None, "to_demonstrated": None, "to_demonstrated_ci": None,
                "commitment_per_task": {}}
    idx = sorted(modes)
    ref = torch.stack([modes[i] for i in idx])
    committed, to_demo = (torch.stack(v) for v in zip(*(commitment(s[idx, :, 2:], ref) for s in samples),
                                                     strict=True))
    per_task = {}
    for t in sorted({tasks[i] for i in idx}):
        cols = [k for k, i in enumerate(idx) if tasks[i] == t]
        per_task[t] = float(committed[:, cols].float().mean())
    per_scene = committed.float().sum(0).numpy()
    to_demo_per_scene = (committed & to_demo).float().sum(0).numpy()
    n_committed = int(committed.sum())
    return {"commitment": float(committed.float().mean()),
            "commitment_ci": list(mean_interval((per_scene / len(samples)).tolist())),
            "to_demonstrated": float((committed & to_demo).sum()) / n_committed if n_committed else None,
            "to_demonstrated_ci": list(ratio_interval(to_demo_per_scene, per_scene)) if n_committed else None,
            "commitment_per_task": per_task}


def error_figures(px: torch.Tensor, cm: torch.Tensor, best_px: torch.Tensor, best_cm: torch.Tensor,
                  tasks: list[str], k: int, image_px: int) -> dict:
    """A row's error figures from per-episode errors (px, cm: the first sample; best_*: the closest of K samples),
    every mean with its 95 % bootstrap interval over episodes."""
    mm = [i for i, t in enumerate(tasks) if t in multimodal_tasks()]

    def mean_ci(v: torch.Tensor) -> tuple[float, list[float]]:
        return float(v.mean()), list(mean_interval(v.tolist()))

    out = {"n": len(px), "px224": float(px.mean()) * PAPER_IMAGE_PX / image_px,
           # per test episode, in the split's order: what a paired comparison of two models needs
           "px_per_episode": [round(float(v), 4) for v in px], "cm_per_episode": [round(float(v), 4) for v in cm],
           "per_task": {}}
    for t in sorted(set(tasks)):
        idx = [i for i, x in enumerate(tasks) if x == t]
        out["per_task"][t] = {"px": float(px[idx].mean()), "cm": float(cm[idx].mean()), "n": len(idx)}
    for key, v in (("px", px), ("cm", cm), (f"best_of_{k}_px", best_px), (f"best_of_{k}_cm", best_cm)):
        out[key], out[f"{key}_ci"] = mean_ci(v)
    for key, v in (("px_multimodal", px), ("cm_multimodal", cm)):
        out[key], out[f"{key}_ci"] = mean_ci(v[mm]) if mm else (None, None)
    return out


def latency_figures(policy: object, obs: torch.Tensor, steps: int, method: str, repeats: int,
                    placement: Placement) -> dict:
    """The median ms of one prediction (batch 1) and of its encoder and sampler parts, each with the bootstrap
    interval of that median over the repeats."""
    out: dict = {}
    for key, times in phase_samples_ms(policy, obs, steps, method, repeats, placement).items():
        out[key], out[f"{key}_ci"] = float(np.median(times)), list(median_interval(times))
    return out


def evaluate_model(model_dir: Path, data: Path, test: list[str], steps_list: list[int],
                   methods_by_kind: dict[str, list[str]], k: int, repeats: int, seed: int, image_px: int,
                   checkpoint: str = "model.pt", timings: dict | None = None,
                   placement: Placement | None = None, modes: dict[int, torch.Tensor] | None = None) -> dict:
    """methods_by_kind: the samplers to evaluate for each objective family ("fm", "ddpm"); others use their
    default. image_px: the stored image size the pixel errors are in. timings: latencies already measured for the
    same network (another checkpoint), reused. modes: reference_modes of the test split."""
    placement = placement or Placement()
    policy, ck = load_policy(model_dir / checkpoint, placement)
    cfg = policy.cfg
    if cfg.closed_loop:
        raise AdlError(f"{model_dir}: a closed-loop model; evaluate measures first-frame ones (closed loop: "
                       "python -m adlpipe.replay --closed-loop, or python -m adlpipe.benchmark for Push-T)")
    with schema.open_dataset(data, test) as f:
        schema.check_horizon(model_dir, cfg.horizon, f, data)
        check_cameras(f, test, cfg.cameras, str(data))
        views = other_views(f, test)
    ds = TrajectoryDataset(str(data), test, ck["stats"], cfg.image_size, cfg.use_depth, cameras=cfg.cameras)
    norm = Normalizer(ck["stats"])
    obs = torch.stack([ds[i][0] for i in range(len(ds))])
    gt = norm.unnormalize(torch.stack([ds[i][1] for i in range(len(ds))]))
    tasks = [ds.task(i) for i in range(len(ds))]
    methods = methods_by_kind.get(policy.family) or [policy.default_method]
    if policy.family == "mse":
        steps_list = [1]
    rows = {}
    for method in methods:
        for steps in steps_list:
            gen = placement.generator(seed)
            samples = [norm.unnormalize(predict(policy, obs, steps, method, gen, placement))]
            px, cm = waypoint_errors(samples[0], gt)
            # best-of-K: the closest of K samples to the demonstration (for BC all K are the same prediction)
            best_px, best_cm = px.clone(), cm.clone()
            for _ in range(k - 1 if policy.family != "mse" else 0):
                samples.append(norm.unnormalize(predict(policy, obs, steps, method, gen, placement)))
                p2, c2 = waypoint_errors(samples[-1], gt)
                best_px, best_cm = torch.minimum(best_px, p2), torch.minimum(best_cm, c2)
            key = f"{method}/{steps}"
            timed = (timings or {}).get(key) or latency_figures(policy, obs[:1], steps, method, repeats, placement)
            rows[key] = {
                "model": cfg.model, "method": method, "steps": steps, "epoch": int(ck.get("epoch", 0)),
                "default": key == DEFAULTS.get(cfg.model),
                "evaluations": policy.objective.evaluations(steps, method), "image_px": image_px,
                "input_px": cfg.image_size, **error_figures(px, cm, best_px, best_cm, tasks, k, image_px),
                **mode_figures(samples, modes or {}, tasks),
                **{k: timed.get(k) for k in ("ms", "ms_ci", "encoder_ms", "encoder_ms_ci", "sampler_ms",
                                             "sampler_ms_ci")},
                **({"px_by_camera": camera_px(samples[0].numpy(), views, image_px)} if views else {}),
            }
    return rows


def other_views(f: object, names: list[str]) -> dict[str, list[schema.CameraView]]:
    """camera name -> its view in each named episode, for the cameras beside the first that every one has."""
    groups = [f[schema.EPISODES][n] for n in names]
    common = set.intersection(*(set(schema.camera_names(g)[1:]) for g in groups)) if groups else set()
    return {c: [schema.read_camera(g, c) for g in groups] for c in sorted(common)}


def camera_px(pred: np.ndarray, views: dict[str, list[schema.CameraView]], size: int) -> dict[str, dict]:
    """Per other camera: the predicted 3D waypoints (E, N, 5: u, v, x, y, z) seen through that camera at its
    first-frame pose against the demonstration as it saw it (its traj2d), in pixels of the stored images (size),
    the mean over episodes with its 95 % bootstrap interval. The first camera's px are the row's own px."""
    out = {}
    for name, vs in views.items():
        per = [float(np.linalg.norm(project(p[:, 2:5], v.K, v.T_base_camera, v.lens, (size, size)) - v.traj2d,
                                    axis=1).mean()) for p, v in zip(pred, vs, strict=True)]
        out[name] = {"px": float(np.mean(per)), "px_ci": list(mean_interval(per)), "n": len(per)}
    return out


def blind_rows(data: Path, split: dict, image_px: int, k: int) -> dict:
    """The blind baseline (adlpipe.policy.blind) scored as a model: each test episode's prediction is its task's
    mean training trajectory, the same for every sample, so best-of-K equals the single error."""
    test = split["test"]
    with schema.open_dataset(data, test) as f:
        eps = [f[schema.EPISODES][n] for n in test]
        tasks = [str(g.attrs["task"]) for g in eps]
        gt = torch.from_numpy(np.stack([np.concatenate([g["traj2d"][()], g["traj3d"][()]], 1) for g in eps]))
    pred = torch.from_numpy(blind_predictions(task_means(data, split["train"]), tasks))
    px, cm = waypoint_errors(pred, gt.float())
    row = {"model": BLIND, "method": "task_mean", "steps": 1, "epoch": 0, "default": True, "evaluations": 0,
           "image_px": image_px, "input_px": 0, **error_figures(px, cm, px, cm, tasks, k, image_px),
           **mode_figures([], {}, tasks), "ms": 0.0, "ms_ci": None}
    return {"task_mean/1": row}
