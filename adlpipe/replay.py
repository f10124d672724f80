"""Execute predicted trajectories in MuJoCo and score each task's success predicate (the paper's Table 2).

    python -m adlpipe.replay --models models/fm_cnn models/dp_cnn models/bc_transformer

Each test episode's scene is rebuilt from the initial object and manikin poses stored with it; the predicted 3D
trajectory (32 waypoints, base frame) is executed open loop over the demonstration's duration by the same arm
controller and grasp rule that recorded the demonstrations. `demo` (the recorded trajectory itself) is always
scored too, as the reference. Works on bags recorded by adlpipe.record (their frames name the world's objects).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import h5py
import numpy as np
import torch
from tqdm import tqdm

from . import schema
from .atomic import write_json_atomic, write_text_atomic
from .data import Normalizer, observation, observation_from_arrays
from .errors import AdlError, run_cli
from .policy.checkpoint import load_policy
from .split import load_split

DEFAULT_STEPS = {"fm": 1, "ddpm": 16, "mse": 1}


def _replay_one(job: tuple) -> tuple[str, str, bool]:
    from .sim.episode import replay_trajectory, spec_from_objects

    label, name, task, names, objects, traj3d, duration = job
    spec = spec_from_objects(task, names, objects)
    ok, _ = replay_trajectory(spec, traj3d, duration)
    return label, task, ok


def _closed_loop_one(job: tuple) -> tuple[str, str, bool]:
    """Closed-loop replay of one episode with one model (runs in a pool process: loads the model itself)."""
    from .sim.episode import replay_closed_loop, spec_from_objects

    label, model_dir, ep, steps, execute, seed = job
    torch.set_num_threads(1)
    policy, ck = load_policy(Path(model_dir) / "model.pt")
    norm = Normalizer(ck["stats"])
    gen = torch.Generator().manual_seed(seed)
    size = ep.rgb.shape[0]

    def plan(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        obs = observation_from_arrays(rgb, ep.affordance, depth, policy.cfg.image_size, policy.cfg.use_depth)
        pred = norm.unnormalize(policy.predict(torch.from_numpy(obs)[None], steps, None, gen))
        return pred[0, :, 2:].numpy()

    spec = spec_from_objects(ep.task, ep.object_names, ep.objects)
    ok, _ = replay_closed_loop(spec, plan, ep.duration_s, len(ep.traj3d), execute, size)
    return label, ep.task, ok


def predict_all(model_dir: Path, data: Path, names: list[str], steps: int | None, seed: int) -> tuple[str, np.ndarray]:
    """(label, predicted traj3d (E, N, 3)) of a model for the named episodes."""
    policy, ck = load_policy(model_dir / "model.pt")
    steps = steps or DEFAULT_STEPS[policy.kind]
    norm = Normalizer(ck["stats"])
    with h5py.File(data, "r") as f:
        obs = torch.stack([torch.from_numpy(observation(f[schema.EPISODES][n], policy.cfg.image_size,
                                                        policy.cfg.use_depth)) for n in names])
    gen = torch.Generator().manual_seed(seed)
    pred = norm.unnormalize(policy.predict(obs, steps, None, gen))
    label = f"{model_dir.name}/{policy.default_method}-{steps}" if policy.kind != "mse" else model_dir.name
    return label, pred[..., 2:].numpy()


def main(argv: list[str] | None = None) -> int:
    from .sim.tasks import TASKS
    from .sim.world import SCENE_OBJECTS

    p = argparse.ArgumentParser(prog="python -m adlpipe.replay", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="*", type=Path, default=[], help="model folders (holding model.pt)")
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--steps", type=int, help="sampling steps for every generative model (default: FM 1, DP 16)")
    p.add_argument("--max-episodes", type=int, help="replay at most this many test episodes")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--closed-loop", type=int, metavar="TA", default=0,
                   help="closed loop: re-plan from a new camera image every TA waypoints (0: open loop, default)")
    p.add_argument("--metrics", type=Path, default=Path("metrics/replay.json"))
    p.add_argument("--table", type=Path, default=Path("reports/table2.md"))
    args = p.parse_args(argv)
    split = load_split(args.split or args.data.with_name("split.json"))
    names = split["test"][: args.max_episodes] if args.max_episodes else split["test"]
    if not names:
        raise AdlError("the test split is empty: nothing to replay")
    with h5py.File(args.data, "r") as f:
        schema.check_file(f, str(args.data))
        eps = [schema.read_episode(f, n) for n in names]
    for ep in eps:
        if ep.task not in TASKS:
            raise AdlError(f"{ep.source_path}: task {ep.task!r} is not a task of the MuJoCo ADL world")
        unknown = set(ep.object_names) - SCENE_OBJECTS
        if unknown:
            raise AdlError(f"{ep.source_path}: frames {sorted(unknown)} are not objects of the ADL world; "
                           "replay works on bags recorded by adlpipe.record")
    if args.closed_loop:
        worker = _closed_loop_one
        jobs = []
        for d in args.models:
            kind = load_policy(d / "model.pt")[0].kind
            steps = args.steps or DEFAULT_STEPS[kind]
            label = f"{d.name}/closed-loop-{args.closed_loop}"
            jobs += [(label, str(d), ep, steps, args.closed_loop, args.seed) for ep in eps]
        if not jobs:
            raise AdlError("--closed-loop needs --models")
    else:
        worker = _replay_one
        trajs = {"demo": np.stack([ep.traj3d for ep in eps])}
        for d in args.models:
            label, pred = predict_all(d, args.data, names, args.steps, args.seed)
            trajs[label] = pred
        jobs = [(label, ep.name, ep.task, ep.object_names, ep.objects, traj[i], ep.duration_s)
                for label, traj in trajs.items() for i, ep in enumerate(eps)]
    wins: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    with ProcessPoolExecutor(max_workers=max(1, args.workers)) as pool:
        for label, task, ok in tqdm(pool.map(worker, jobs, chunksize=4), total=len(jobs), desc="replay",
                                    unit="ep", file=sys.stderr, disable=None):
            wins[label][task].append(ok)
    result = {}
    for label, per in wins.items():
        every = [o for v in per.values() for o in v]
        result[label] = {"overall": float(np.mean(every)), "n": len(every),
                         "per_task": {t: float(np.mean(v)) for t, v in sorted(per.items())}}
    write_json_atomic(args.metrics, {"episodes": len(eps), "success": result})
    tasks = sorted({ep.task for ep in eps})
    lines = ["| policy | overall | " + " | ".join(tasks) + " |", "| --- | ---: |" + " ---: |" * len(tasks)]
    for label, r in result.items():
        cells = " | ".join(f"{100 * r['per_task'].get(t, float('nan')):.0f}" for t in tasks)
        lines.append(f"| {label} | {100 * r['overall']:.0f} | {cells} |")
    mode = f"closed-loop (re-plan every {args.closed_loop} waypoints)" if args.closed_loop else "open-loop"
    title = f"# Success rate (%) of {mode} execution in MuJoCo, test split\n\n"
    write_text_atomic(args.table, title + "\n".join(lines) + "\n")
    for label, r in result.items():
        print(f"{label}: success {100 * r['overall']:.0f}% over {r['n']} episodes")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.replay", main))
