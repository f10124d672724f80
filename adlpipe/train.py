"""Train one of the policies with the one training loop.

    python -m adlpipe.train --model fm_cnn --data data/adl.h5 --split data/split.json --out models/fm_cnn

Diffusion Policy's optimiser settings for every model alike: AdamW (betas 0.95/0.999, weight decay 1e-6), cosine
schedule after 500 linear warm-up steps, EMA weights (decay capped at 0.9999; used for the losses, validation and
inference). Gradients are clipped at norm 1 for every model alike (--grad-clip 0: none, as Diffusion Policy at its lr
of 1e-4; the small preset trains at 1e-3); README measures the clip's effect on each objective.
A validation part of the train split (--val-fraction, stratified per task, seeded) is held out; every
--val-every epochs the EMA policy's val px (mean per-waypoint pixel error with the model's default sampler: FM 1
Euler step, DP 16 DDPM steps, BC direct) is measured, and the best EMA weights are kept in best.pt beside the last
ones in model.pt. A model whose best val px still fell by more than 2 % over the last fifth of training is marked
"converged": false in metrics.json. Every model trains for the same number of optimiser steps (epochs x batches).
The train loss of every epoch, and the test loss and val px of every --val-every epochs, go to a CSV that
`dvc plots` reads. A checkpoint is written atomically
after every epoch; re-running the same command resumes from it (after a kill, too), and each epoch's randomness
comes from (seed, epoch), so a resumed run ends where an uninterrupted one does. Checkpoints hold only tensors and
plain values: they load with torch.load(weights_only=True).

Training augments (a random shift of the image stack with the pixel targets moved alike, colour jitter); --no-augment
turns it off; validation and test never augment. --closed-loop trains on every frame (adlpipe.dataset.loader
.WindowDataset): To frames with the measured end effector and gripper at each in, the next Tp waypoints at a fixed
rate out: by default (--target command) of the commanded end effector (the bags' action stream), relative to the
command now, so that replay anchors each plan where the last one left the command, not at the lagging measurement.
An epoch draws as many windows as there are training episodes, uniformly over
every frame of every episode, so a closed-loop model takes the same optimiser steps as a first-frame one.
--target action learns the bags' action stream from their
state stream (val px is then the action's error in its own units); --no-image drops the image encoder, so the state
alone conditions the model (the seed's Franka Kitchen setting).
"""

from __future__ import annotations

import sys
from pathlib import Path

from .dataset.loader import OPEN_FILES
from .plumbing.cli import NON_NEGATIVE, POSITIVE, SEED, Parser, config_from, float_range, int_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import run_cli
from .plumbing.runtime import add_device_args
from .policy.models import MODELS, PRESETS
from .policy.nets.resnet import POOLS
from .policy.optim import WARMUP_STEPS
from .training.run import TrainConfig, run_training


def parse_args(argv: list[str] | None) -> TrainConfig:
    """The options as the run's configuration, its outputs checked (not a DVC stage's unless --force)."""
    p = Parser("python -m adlpipe.train", __doc__)
    p.add_argument("--model", required=True, choices=sorted(MODELS))
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--out", type=Path, help="output folder (default: models/<model>)")
    p.add_argument("--config", choices=sorted(PRESETS), default="small",
                   help="small: trains on 2 CPU cores in minutes (default); paper: 224x224, full-size networks")
    p.add_argument("--image-size", type=int_range(16, 1024), help="override the preset's input size")
    p.add_argument("--depth", action="store_true", help="add the depth image as an input channel")
    p.add_argument("--epochs", type=POSITIVE, default=100)
    p.add_argument("--batch-size", type=POSITIVE, default=32)
    p.add_argument("--lr", type=float_range(0, 1, lo_open=True),
                   help="AdamW learning rate (default: the preset's, small 1e-3, paper 1e-4)")
    p.add_argument("--weight-decay", type=float_range(0, 1), default=1e-6)
    p.add_argument("--warmup-steps", type=NON_NEGATIVE, default=WARMUP_STEPS,
                   help=f"linear learning-rate warm-up (default {WARMUP_STEPS}, Diffusion Policy's)")
    p.add_argument("--grad-clip", type=float_range(0, 1e6), default=1.0,
                   help="clip the gradient norm at this (default 1; 0: no clipping, as Diffusion Policy at lr 1e-4)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--threads", type=NON_NEGATIVE, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--log", type=Path, help="per-epoch CSV for dvc plots (default: <out>/log.csv)")
    p.add_argument("--val-fraction", type=float_range(0, 0.9), default=0.1,
                   help="part of the train split held out for validation and checkpoint selection (0: none)")
    p.add_argument("--val-every", type=POSITIVE, default=5, help="measure val px every N epochs (and at the last)")
    p.add_argument("--workers", type=int_range(0, 64), default=0,
                   help="DataLoader worker processes (per training process) that load and augment batches beside "
                   "training; they persist for the whole run (default 0: the training process loads)")
    p.add_argument("--open-files", type=int_range(1, 100_000), default=OPEN_FILES,
                   help=f"closed loop: episode files each loader process keeps open (default {OPEN_FILES}; about "
                   "0.6 MB each: as many as the training episodes makes random windows about 1.6x cheaper)")
    p.add_argument("--windows-per-epoch", choices=["episodes", "all"], default="episodes",
                   help="closed loop: an epoch draws as many windows as there are training episodes (default: as "
                   "many optimiser steps as a first-frame model) or every window once (all)")
    p.add_argument("--save-every", type=NON_NEGATIVE, default=0,
                   help="keep the EMA weights of every N epochs in <out>/checkpoints/ for learning curves "
                   "(benchmark --curve; default 0: none)")
    p.add_argument("--resume-dir", type=Path,
                   help="keep the checkpoints of the run in progress here (default: in --out); a finished run "
                        "moves best.pt into --out and removes it. For DVC stages, whose outputs DVC deletes "
                        "before it runs a stage again: a killed `dvc repro` then resumes where it stopped")
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint and train from scratch")
    p.add_argument("--no-augment", action="store_true",
                   help="train without random shifts and colour jitter (on by default; never at evaluation)")
    p.add_argument("--closed-loop", action="store_true",
                   help="train on every frame: --obs-frames frames in, the next --action-steps waypoints at "
                   "--rate-hz out (for replay --closed-loop); default: the first frame -> the whole trajectory")
    p.add_argument("--obs-frames", type=int_range(1, 16), default=2, help="closed loop: To (default 2)")
    p.add_argument("--action-steps", type=int_range(4, 256), default=16,
                   help="closed loop: Tp, a multiple of 4 (default 16)")
    p.add_argument("--rate-hz", type=float_range(0.1, 1000), default=10.0,
                   help="closed loop: waypoint rate (default 10 Hz)")
    p.add_argument("--no-image", action="store_true",
                   help="closed loop: a state-only model (no image encoder; the state stream alone conditions it, "
                   "as the seed's Franka Kitchen policies)")
    p.add_argument("--cameras", nargs="+", metavar="NAME",
                   help="the cameras the model sees, in order (names of the topic map's cameras list), each through "
                   "one shared image encoder; default: the first camera alone")
    p.add_argument("--pool", choices=POOLS, default="avg",
                   help="the image encoder's pooling: avg (global average; default) or spatial_softmax (32 "
                   "keypoints, as Diffusion Policy, robomimic and LeRobot)")
    p.add_argument("--crop", type=NON_NEGATIVE, default=0,
                   help="the encoder sees a crop x crop window of the input: a random one in training, the centre "
                   "at test (Diffusion Policy's Push-T: 84 of 96); replaces the random shift; default 0: none")
    p.add_argument("--per-frame", action="store_true",
                   help="each observation frame through the shared image encoder, features concatenated (Diffusion "
                   "Policy); default: the frames stacked as channels into one encoder pass")
    p.add_argument("--target", choices=["command", "recovery", "ee", "action"], default="command",
                   help="closed loop: command (the commanded end effector's waypoints relative to the command now: "
                   "the action stream's x, y, z; default), recovery (the same anchor; where a demonstrator was "
                   "disturbed (record --recoveries), the plan it follows back onto its reference path: the "
                   "topic map's reference stream), ee (the measured end effector's, relative to where it "
                   "is: for bags without a command topic) or action (the bags' action stream per frame, absolute, "
                   "with their state stream as the state input: Push-T, joint-space policies)")
    p.add_argument("--init", type=Path, default=None, metavar="CHECKPOINT",
                   help="start from a trained model's weights and normalisation (its model.pt or best.pt), with a "
                   "fresh optimiser and schedule over --epochs: a DAgger round goes on from the previous round's "
                   "policy (docs/science/dagger.md)")
    p.add_argument("--steps", type=int_range(1), default=None,
                   help="train for this many optimiser steps in all instead of --epochs (as many epochs as that "
                   "takes): one budget for runs on different numbers of episodes (DAgger rounds)")
    p.add_argument("--stop-when-converged", type=int_range(1), default=None, metavar="FLOOR",
                   help="stop at the first validation from epoch FLOOR on at which the run has converged by the "
                   "2 %% rule (its best val px no more than 2 %% below the best of its first four fifths); the "
                   "learning-rate schedule stays --epochs', so the run is the capped run's first epochs exactly")
    p.add_argument("--corrections-only", action="store_true",
                   help="closed loop (HG-DAgger): an episode whose bag carried an operator's intervention flag gives "
                   "training windows only where the operator drove; the demonstrations give every frame")
    add_device_args(p)
    p.add_force()
    p.io(inputs=["data", "split"], outputs=["out", "log"],
         implied=lambda a: [a.data.with_name("split.json")] if a.split is None else [])
    args = p.parse_args(argv)
    c = config_from(args, TrainConfig, split=args.split or args.data.with_name("split.json"),
                    out=args.out or Path("models") / args.model)
    refuse_pipeline_outputs([c.out, c.log], args.force)
    return c


def main(argv: list[str] | None = None) -> int:
    c = parse_args(argv)
    cfg, m = run_training(c)
    if m is None:  # not rank 0: it wrote nothing
        return 0
    val = (f", val px best {m['val_px_best']:.2f} (epoch {m['best_epoch']}) last {m['val_px_last']:.2f}"
           f"{'' if m['converged'] else ', NOT CONVERGED'}" if m["val_px_best"] is not None else "")
    stopped = f" (converged: stopped at {m['epochs']} of {c.epochs})" if "stopped_converged_at" in m else ""
    print(f"{c.out}: {cfg.model} trained {m['epochs']} epochs{stopped} ({m['optimizer_steps']} steps) in "
          f"{m['seconds']:.0f} s, "
          f"train loss {m['train_loss']:.4f}, test loss {m['test_loss']:.4f}{val}")
    return 0

if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.train", main))
