"""Record demonstrations of the 10 ADL tasks in MuJoCo as ROS bags (one episode per bag), or of Push-T.

    python -m adlpipe.record --episodes 3 --out data/bags            # 3 episodes of each task, ROS2 MCAP
    python -m adlpipe.record --format bag --image-format jpeg ...    # ROS1 .bag with CompressedImage
    python -m adlpipe.record --world pusht --episodes 100 --out ...  # Push-T (gym-pusht), seeds 0..99
    python -m adlpipe.record --world kitchen --episodes 50 --out ... # Franka Kitchen (gymnasium-robotics)

Push-T bags carry the rendered image with a top-down camera model, the agent as end effector and joint state, the
T block's pose in tf, and the state (agent x, y) and action (target x, y) topics of PUSHT_TOPICS; ingest them with
`--config pipelines/pusht/topics.yaml`. They also carry /pusht/keypoint_state (the T's 8 keypoints and the agent,
the low-dimensional observation): `--config pipelines/pusht/topics_state.yaml` makes it the state. Franka Kitchen
bags likewise carry the rendered image, the robot's joints, the end-effector site in tf, the kettle's pose, the
59-D observation as state and the 9-D joint-velocity action (KITCHEN_TOPICS, `--config pipelines/kitchen/
topics.yaml`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from tqdm import tqdm

from .bags.topics import TopicMap
from .bags.writer import FORMATS, BagWriter
from .plumbing.cli import SEED, Parser, float_range, int_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, run_cli
from .plumbing.workers import stoppable_pool
from .sim.recording import write_episode_bag

# Push-T's topics: the camera has no depth, there is no affordance map or gripper; the policy's state and action.
PUSHT_TOPICS = TopicMap(depth=None, affordance=None, gripper_joint=None, ee_frame="agent", state="/pusht/state",
                        action="/pusht/action")
KITCHEN_TOPICS = TopicMap(depth=None, affordance=None, gripper_joint="panda0_finger_joint1", ee_frame="end_effector",
                          state="/kitchen/state", action="/kitchen/action")
SEEDED_WORLDS = {"pusht": ("push_the_T", PUSHT_TOPICS), "kitchen": ("franka_kitchen", KITCHEN_TOPICS)}  # bag stem


def _bag_path(out: Path, stem: str, idx: int, fmt: str) -> Path:
    """The bag of episode `idx` named by its task or world (the job carries it: the parent removes what a stopped
    worker left under its temp name)."""
    return out / f"{stem.replace(' ', '_')}_{idx:04d}{FORMATS[fmt]}"


def _record_one(job: tuple) -> tuple[str, int, bool]:
    from .sim.episode import seeded_demo
    from .sim.tasks import TASK_NAMES

    path, task, idx, seed, fmt, image_format, depth_format, size, camera_hz, moving_person, recoveries = job
    st = seeded_demo(task, seed, idx, size, camera_hz, moving_person, recoveries)
    write_episode_bag(st, path, fmt, image_format, depth_format, episode_index=TASK_NAMES.index(task) * 10000 + idx)
    return str(path), st.attempts, st.success


def _seeded_world(name: str) -> object:
    """The module of a seeded benchmark world (make_env, record)."""
    from .envs import kitchen, pusht

    return {"pusht": pusht, "kitchen": kitchen}[name]


def _record_seeded_one(job: tuple) -> tuple[str, int, bool]:
    """Push-T or Franka Kitchen: the demonstration from initial condition `seed` (their demonstrators are
    deterministic: no retries; a demonstration that misses its goal is recorded and counted)."""
    path, world, idx, seed, fmt, image_format, size = job
    st = _seeded_world(world).record(seed + idx, size)
    write_episode_bag(st, path, fmt, image_format, "32FC1", episode_index=idx, topics=SEEDED_WORLDS[world][1])
    return str(path), 1, st.success


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from .sim.tasks import TASK_NAMES

    p = Parser("python -m adlpipe.record", __doc__)
    p.add_argument("--world", choices=["adl", "pusht", "kitchen"], default="adl",
                   help="adl: the MuJoCo ADL world (default); pusht: gym-pusht's Push-T; kitchen: gymnasium-robotics' "
                   "Franka Kitchen (both optional extras)")
    p.add_argument("--episodes", type=int_range(1, 100_000), default=3, help="episodes per task (default 3)")
    p.add_argument("--out", required=True, type=Path, help="output folder for the bags")
    p.add_argument("--tasks", nargs="+", default=TASK_NAMES, metavar="TASK",
                   help="task names (default: all 10), e.g. 'wipe the nose'")
    p.add_argument("--format", choices=sorted(FORMATS), default="mcap",
                   help="mcap: ROS2 MCAP file (default); bag: ROS1 .bag; db3: ROS2 sqlite3 bag folder")
    p.add_argument("--image-format", choices=["raw", "jpeg", "png"], default="raw",
                   help="raw: sensor_msgs/Image rgb8 (default); jpeg/png: sensor_msgs/CompressedImage")
    p.add_argument("--depth-format", choices=["32FC1", "16UC1"], default="32FC1")
    p.add_argument("--size", type=int_range(16, 2048), default=224,
                   help="camera width and height in pixels (default 224; Push-T renders at this size too)")
    p.add_argument("--camera-hz", type=float_range(0.1, 120), default=15.0)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--moving-person", action="store_true",
                   help="adl: the person moves during each episode (the head turns and nods, the forearm lifts; "
                   "adlpipe.sim.person) and the demonstrator follows them; the same seeded scenes otherwise")
    p.add_argument("--recoveries", action="store_true",
                   help="adl: demonstrations with recoveries (DART-style): the demonstrator's command is pushed 2-5 "
                   "cm off its path or held back now and then and returns over 0.8 s (adlpipe.sim.disturbances); "
                   "its undisturbed path goes on the topic map's reference topic, from which train --target "
                   "recovery makes labels that never show a disturbance. The same seeded scenes otherwise")
    p.add_argument("--workers", type=int_range(1, 256), default=2)
    p.add_force()
    args = p.parse_args(argv)
    bad = [t for t in args.tasks if t not in TASK_NAMES]
    if bad:
        raise AdlError(f"unknown task(s) {bad}; tasks are {TASK_NAMES}")
    if args.moving_person and args.world != "adl":
        raise AdlError(f"--moving-person: the {args.world} world has no person; it moves in the ADL world only")
    if args.recoveries and args.world != "adl":
        raise AdlError(f"--recoveries: the {args.world} world's demonstrator is not adlpipe's; ADL world only")
    if args.episodes < 1 or args.size < 16:
        raise AdlError("--episodes must be >= 1 and --size >= 16")
    return args


def _record_all(worker: Callable[[tuple], tuple[str, int, bool]], jobs: list[tuple], workers: int) -> int:
    """Run the jobs (in a pool of `workers` when there are several); how many demonstrations missed their goal."""
    bar = {"total": len(jobs), "desc": "record", "unit": "ep", "file": sys.stderr, "disable": None}
    if workers <= 1 or len(jobs) <= 1:
        return sum(not ok for _, _, ok in tqdm(map(worker, jobs), **bar))
    with stoppable_pool(workers) as pool:
        return sum(not ok for _, _, ok in tqdm(pool.imap(worker, jobs), **bar))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    refuse_pipeline_outputs([args.out], args.force)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.world in SEEDED_WORLDS:
        _seeded_world(args.world).make_env().close()  # the optional extra's absence is one line here, not per worker
        stem = SEEDED_WORLDS[args.world][0]
        worker, jobs = _record_seeded_one, [(_bag_path(args.out, stem, i, args.format), args.world, i, args.seed,
                                             args.format, args.image_format, args.size) for i in range(args.episodes)]
    else:
        worker = _record_one
        jobs = [(_bag_path(args.out, t, i, args.format), t, i, args.seed, args.format, args.image_format,
                 args.depth_format, args.size, args.camera_hz, args.moving_person, args.recoveries)
                for t in args.tasks for i in range(args.episodes)]
    try:
        failed = _record_all(worker, jobs, args.workers)
    except BaseException:  # a terminated worker's bag was half written under its temp name (.<bag>.tmp<pid>)
        for bag, *_ in jobs:
            for tmp in bag.parent.glob(f".{bag.name}.tmp*"):
                BagWriter.remove(tmp)
        raise
    print(f"recorded {len(jobs)} episodes to {args.out} ({failed} without a successful demo)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.record", main))
