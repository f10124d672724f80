"""Load and inspect an adlpipe dataset: its episodes per task, one episode's camera, trajectory and streams.

    python examples/01_inspect_a_dataset.py data/adl.h5
    python examples/01_inspect_a_dataset.py data/adl.h5 --episode <name>

The dataset is what `adlpipe ingest` writes (docs/reference/hdf5_schema.md): an index file and one file per episode
beside it, read an episode at a time. `adlpipe inspect` shows the same in Rerun.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np

from adlpipe.dataset import schema


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path)
    p.add_argument("--episode", help="the episode to show (default: the first)")
    args = p.parse_args()

    with schema.open_dataset(args.data) as f:
        names = schema.episode_names(f)
        tasks = Counter(str(f[schema.EPISODES][n].attrs["task"]) for n in names)
        print(f"{args.data}: {len(names)} episodes, {len(tasks)} tasks")
        for task, n in sorted(tasks.items()):
            print(f"  {task}: {n}")
        ep = schema.read_episode(f, args.episode or names[0])
        frames = f[schema.EPISODES][args.episode or names[0]]["frames"]
        n_frames, rate = len(frames["t"]), 1 / float(np.median(np.diff(frames["t"][()])))

    print(f"\nepisode {args.episode or names[0]} ({ep.task}, from {Path(ep.source_path).name}):")
    print(f"  {ep.duration_s:.1f} s, {n_frames} camera frames at {rate:.1f} Hz, first frame {ep.rgb.shape} "
          f"{'with' if ep.depth is not None else 'without'} depth, affordance map max {ep.affordance.max():.2f}")
    print(f"  camera K: fx {ep.K[0, 0]:.1f} fy {ep.K[1, 1]:.1f} px; camera at {np.round(ep.T_base_camera[:3, 3], 3)} m "
          f"in {ep.base_frame}")
    print(f"  trajectory: {len(ep.traj3d)} waypoints from {np.round(ep.traj3d[0], 3)} to {np.round(ep.traj3d[-1], 3)} "
          f"m; in the first image from {np.round(ep.traj2d[0], 1)} to {np.round(ep.traj2d[-1], 1)} px")
    print(f"  end effector: {len(ep.ee_t)} samples; joints: {len(ep.joint_names)} ({', '.join(ep.joint_names[:3])}"
          f"{', ...' if len(ep.joint_names) > 3 else ''})")


if __name__ == "__main__":
    main()
