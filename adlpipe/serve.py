"""Serve a trained policy to robots: a websocket server that plans from each robot's observations.

    python -m adlpipe.serve models/fm_cnn                                   # ws://127.0.0.1:8765, best.pt
    python -m adlpipe.serve models/fm_cnn --data data/adl.h5               # a first-frame model: times at the
                                                                            # tasks' demonstrated speeds
    python -m adlpipe.serve models/dp_cnn --host 0.0.0.0 --token-file token.txt --device cuda --log plans.jsonl

The robot side needs no torch: adlpipe.deploy.client.PolicyClient (numpy, msgpack, websockets), or the ROS 2 node
in examples/ros2_policy_node.py. Messages are msgpack maps with numpy arrays as typed bytes, checked against the
policy's spec (shapes, dtypes, sizes, task names) and never unpickled (adlpipe.deploy.server says the protocol).
The server binds localhost unless --host says otherwise; with --token-file, a client must send that token.
Ctrl-C (or SIGTERM) stops it cleanly.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .plumbing.cli import Parser, int_range, read_token_file
from .plumbing.errors import AdlError, run_cli


def task_speeds(data: Path, split: Path | None) -> dict[str, float]:
    """The tasks' demonstrated speeds over the training split (replay's fixed speed profile)."""
    from .dataset.splits import load_split
    from .evaluation.replay import demonstrated_speeds

    split = split or data.with_name("split.json")
    names = load_split(split)["train"]
    if not names:
        raise AdlError(f"{split}: no train episodes to take the tasks' speeds from")
    return demonstrated_speeds(data, names)


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.serve", __doc__)
    p.add_argument("model", type=Path, help="a model folder (its best.pt) or a checkpoint file")
    p.add_argument("--checkpoint", choices=["best", "last"], default="best",
                   help="with a model folder: best.pt (default) or model.pt")
    p.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1: this machine only; "
                   "0.0.0.0 for a robot on the network, with --token-file)")
    p.add_argument("--port", type=int_range(0, 65535), default=8765, help="port (default 8765; 0: any free one)")
    p.add_argument("--port-file", type=Path, help="write the port here once listening (with --port 0)")
    p.add_argument("--token-file", type=Path, help="a file holding the shared token clients must send")
    p.add_argument("--steps", type=int_range(1, 1000), help="sampler steps (default: the model's own: FM 1, DP 16)")
    p.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N or auto")
    p.add_argument("--threads", type=int_range(1, 256), default=1,
                   help="torch threads for inference (default 1: the plans replay computes in-process)")
    p.add_argument("--data", type=Path, help="the training dataset: the tasks accepted and their demonstrated "
                   "speeds (needed to time a first-frame model's plans)")
    p.add_argument("--split", type=Path, help="split.json of --data (default: beside it)")
    p.add_argument("--log", type=Path, help="append one JSON line per plan: received, queue, inference, reply ms")
    p.io(inputs=["model", "data", "split", "token_file"], outputs=["log", "port_file"])
    args = p.parse_args(argv)

    import torch

    from .deploy.planner import Planner
    from .deploy.server import PolicyServer, ServeConfig

    torch.set_num_threads(args.threads)
    token = read_token_file(args.token_file) if args.token_file is not None else None
    model = args.model / ("best.pt" if args.checkpoint == "best" else "model.pt") if args.model.is_dir() else args.model
    speeds = task_speeds(args.data, args.split) if args.data else None
    planner = Planner.load(model, args.device, args.steps, speeds)
    PolicyServer(planner, ServeConfig(args.host, args.port, token, args.log, args.port_file)).serve_forever()
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.serve", main))
