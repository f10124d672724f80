"""Plan from one observation with the public API: a trained closed-loop model, the frames of a recorded episode as a
robot would send them, waypoints in the robot's base frame.

    python examples/03_plan_one_observation.py pipelines/closed_loop/models/fm_cnn data/adl.h5
    python examples/03_plan_one_observation.py models/fm_cnn data/adl.h5 --device cuda

A first-frame model (the default pipeline's fm_cnn) plans the whole trajectory, timed at the task's demonstrated
speed: give the planner those speeds (adlpipe.serve.task_speeds reads them from the dataset and its split).
"""

from __future__ import annotations

import argparse

import h5py
import numpy as np

from adlpipe.deploy import Observation, Planner


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="a model folder (its best.pt) or a checkpoint")
    p.add_argument("data", help="an adlpipe dataset: its first episode plays the robot's camera")
    p.add_argument("--device", default="cpu")
    p.add_argument("--frame", type=int, default=4)
    args = p.parse_args()

    speeds = None
    planner = Planner.load(args.model, device=args.device)
    if not planner.spec.rate_hz:  # a first-frame model: its plan is timed at the task's demonstrated speed
        from pathlib import Path

        from adlpipe.serve import task_speeds

        speeds = task_speeds(Path(args.data), None)
        planner = Planner.load(args.model, device=args.device, task_speeds=speeds)
    n, k = planner.spec.n_obs, args.frame
    with h5py.File(args.data) as f:
        g = f["episodes"][sorted(f["episodes"])[0]]
        fr = g["frames"]
        frames = slice(k - n + 1, k + 1)
        obs = Observation(
            rgb=fr["rgb"][frames],  # (To, H, W, 3) uint8, oldest first
            affordance=g["affordance"][()],  # (H, W) in [0, 1]
            state=np.concatenate([fr["ee_pos"][frames], fr["gripper"][frames][:, None]], 1),  # tcp x y z, gripper
            command=fr["action"][k, :3].astype(float),  # the last commanded tcp: the plan's anchor
            task=str(g.attrs["task"]))
    plan = planner.plan(obs)
    print(f"{planner.spec.model}, {planner.spec.steps} step(s): {len(plan.waypoints)} waypoints in "
          f"{plan.inference_ms:.1f} ms")
    for t, w in list(zip(plan.times, plan.waypoints, strict=True))[:4]:
        print(f"  t+{t:.2f} s  x {w[0]:+.3f}  y {w[1]:+.3f}  z {w[2]:+.3f} m")


if __name__ == "__main__":
    main()
