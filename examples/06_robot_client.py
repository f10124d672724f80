"""A robot's side of `adlpipe serve`, in a few lines and without torch: numpy, msgpack and websockets.

    adlpipe serve pipelines/closed_loop/models/fm_cnn --host 0.0.0.0 --token-file token.txt   # on the GPU box
    python examples/06_robot_client.py ws://gpu-box:8765 --token-file token.txt                  # on the robot

The loop a closed-loop policy runs: observe, plan, execute the first Ta waypoints, observe again. `Robot` below is
where a lab's own drivers go; here it only makes up frames so that the example runs anywhere.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from adlpipe.deploy.client import PolicyClient


class Robot:
    """Stand-in for a lab's drivers: the camera's last frames, the arm's state, the last command sent."""

    def __init__(self) -> None:
        self.command = np.array([0.0, 0.3, 0.3])

    def observe(self, n_frames: int) -> dict:
        rng = np.random.default_rng()
        return {"rgb": rng.integers(0, 255, (n_frames, 128, 128, 3), dtype=np.uint8),
                "affordance": np.zeros((128, 128), np.float32),
                "state": np.tile(np.append(self.command, 0.04), (n_frames, 1)),
                "command": self.command}

    def execute(self, waypoints: np.ndarray, times: np.ndarray) -> None:
        self.command = waypoints[-1]  # a real arm tracks each waypoint at its time


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("url")
    p.add_argument("--token-file", type=Path)
    p.add_argument("--task", default="wipe the nose")
    p.add_argument("--execute", type=int, default=8, help="Ta: waypoints executed per plan")
    p.add_argument("--plans", type=int, default=5)
    args = p.parse_args()
    token = args.token_file.read_text().strip() if args.token_file else None
    robot = Robot()
    with PolicyClient(args.url, token=token) as client:
        spec = client.policy
        print(f"serving {spec['model']} ({spec['steps']} step(s)): {spec['n_obs']} frame(s) in, "
              f"{spec['horizon']} waypoints out at {spec['rate_hz']} Hz")
        for _ in range(args.plans):
            plan = client.plan(task=args.task, **robot.observe(spec["n_obs"]))
            robot.execute(plan["waypoints"][:args.execute], plan["times"][:args.execute])
            print(f"plan: {plan['timing']['inference_ms']:.1f} ms inference, next waypoint "
                  f"{np.round(plan['waypoints'][0], 3)} m")


if __name__ == "__main__":
    main()
