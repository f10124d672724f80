"""Write a Rerun recording of a policy's predictions on episodes of the dataset, or of the dataset itself.

    python -m adlpipe.inspect --model models/fm_cnn --episodes 0 1 2 -o preds.rrd     (indices into the test split)
    python -m adlpipe.inspect --dataset --data data/adl.h5 [--episodes NAME|INDEX ...] -o data.rrd
    python -m adlpipe.inspect --dataset --data data/adl.h5 --episodes NAME --bag BAG -o side.rrd
    rerun preds.rrd

--dataset: every frame of every episode (or of those named; indices count all episodes in catalog order), one
after another on the `dataset_time` timeline: the camera image with the affordance overlay and the projected end
effector, the end-effector path and the camera frustum in 3D, the joints and gripper as time series
(adlpipe/interchange/viewer.py). With --bag, one episode beside the bag it came from, on one timeline: the bag's
images as recorded, its joint states and its tf end-effector path next to what ingest stored.

Per episode (timeline `episode`): the RGB image with the affordance map as a colour-mapped overlay, the ground-truth
and predicted 2D trajectories as line strips on the image, the 3D trajectories in the base frame and the camera
(Transform3D + Pinhole) in a 3D view; a blueprint lays out the image and the 3D view side by side.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch

from .dataset import schema
from .dataset.loader import Normalizer, observation
from .dataset.splits import load_split
from .evaluation.outcomes import outcome_text
from .interchange import viewer
from .interchange.viewer import (
    affordance_overlay,
    close_recording,
    write_bag_beside_episode,
    write_dataset_recording,
)
from .plumbing.atomic import atomic_path, check_outputs
from .plumbing.cli import SEED, Parser, int_range
from .plumbing.errors import AdlError, read_json_object, run_cli
from .plumbing.runtime import Placement, add_device_args
from .policy.checkpoint import CHECKPOINTS, load_policy
from .policy.inference import predict

GT_COLOR = [40, 200, 40]
PRED_COLOR = [230, 60, 40]


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial2DView(origin="world/camera/image", name="image + 2D trajectories"),
        rrb.Spatial3DView(origin="world", name="3D trajectories"),
    ), collapse_panels=True)


def write_recording(out: Path, episodes: list[schema.Episode], preds: list[np.ndarray], model: str,
                    outcomes: list[str] | None = None) -> None:
    """preds[i]: (K, N, 5) samples (u, v, x, y, z) for episodes[i]; outcomes[i]: replay's verdicts on it (logged as
    world/replay when not empty). Written to a temp file, then renamed."""
    viewer.check_recording_space(out, sum(ep.rgb.nbytes * 3 + p.nbytes for ep, p in zip(episodes, preds,
                                                                                       strict=True)))
    with atomic_path(out) as tmp:
        _record(tmp, out, episodes, preds, model, outcomes or [""] * len(episodes))


def _record(path: Path, out: Path, episodes: list[schema.Episode], preds: list[np.ndarray], model: str,
            outcomes: list[str]) -> None:
    rec = rr.RecordingStream("adlpipe_inspect")
    rec.save(path, default_blueprint=blueprint())
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for i, (ep, pred, outcome) in enumerate(zip(episodes, preds, outcomes, strict=True)):
        rec.set_time("episode", sequence=i)
        h, w = ep.rgb.shape[:2]
        T = ep.T_base_camera
        rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        rec.log("world/camera/image", rr.Pinhole(image_from_camera=ep.K, resolution=[w, h]))
        rec.log("world/camera/image/rgb", rr.Image(ep.rgb))
        rec.log("world/camera/image/affordance", rr.Image(affordance_overlay(ep.affordance)))
        rec.log("world/camera/image/gt", rr.LineStrips2D([ep.traj2d], colors=[GT_COLOR], radii=0.5,
                                                         labels=[f"{ep.task} (demo)"]))
        rec.log("world/camera/image/pred", rr.LineStrips2D(list(pred[:, :, :2]), colors=[PRED_COLOR], radii=0.5,
                                                           labels=[model] * len(pred)))
        rec.log("world/gt", rr.LineStrips3D([ep.traj3d], colors=[GT_COLOR], radii=0.003))
        rec.log("world/pred", rr.LineStrips3D(list(pred[:, :, 2:]), colors=[PRED_COLOR], radii=0.003))
        rec.log("world/task", rr.TextDocument(f"{ep.task}\n{ep.source_path}"))
        if outcome:
            rec.log("world/replay", rr.TextDocument(outcome))
    close_recording(rec, path, out)


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.inspect", __doc__)
    p.add_argument("--model", type=Path, help="model folder (holding model.pt); or --dataset")
    p.add_argument("--dataset", action="store_true", help="record the dataset's frames instead of predictions")
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--episodes", nargs="+",
                   help="episode names, or indices: with --model, positions in the test split (default: the first "
                   "test episode); with --dataset, positions in the dataset's catalog, the order ingest added them "
                   "(default: every episode)")
    p.add_argument("--samples", type=int_range(1, 1000), default=4, help="predicted samples drawn per episode")
    p.add_argument("--steps", type=int_range(1, 100), default=4)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--checkpoint", choices=sorted(CHECKPOINTS), default="best",
                   help="best: the lowest validation px (best.pt, default); last: model.pt")
    p.add_argument("--replay", type=Path, metavar="DETAILS",
                   help="replay's details (metrics/replay_details.json): log each episode's replay outcome for this "
                   "model (success, or the parts of the predicate that failed, and the peak force on the person)")
    p.add_argument("--bag", type=Path, help="with --dataset and one episode: show the bag it was ingested from beside "
                   "it")
    p.add_argument("--config", type=Path, action="append",
                   help="with --bag: the topic map (default: the one the episode was ingested with)")
    p.add_argument("-o", "--output", type=Path, default=Path("preds.rrd"))
    add_device_args(p, compile_option=True)
    p.io(inputs=["model", "data", "split", "replay", "bag", "config"], outputs=["output"])
    args = p.parse_args(argv)
    if args.dataset == (args.model is not None):
        p.error("give either --model (predictions) or --dataset (the dataset's frames)")
    if args.bag and not args.dataset:
        p.error("--bag goes with --dataset")
    check_outputs(args.output)
    if args.dataset:
        return record_dataset(args)
    placement = Placement.from_args(args)
    policy, ck = load_policy(args.model / CHECKPOINTS[args.checkpoint], placement)
    if policy.cfg.closed_loop:
        raise AdlError(f"{args.model}: a closed-loop model; inspect shows first-frame predictions (the dataset "
                       "itself: --dataset)")
    norm = Normalizer(ck["stats"])
    with schema.open_dataset(args.data) as f:
        schema.check_horizon(args.model, policy.cfg.horizon, f, args.data)
        all_names = schema.episode_names(f)
        test = load_split(args.split or args.data.with_name("split.json"))["test"] or all_names
        names = pick_episodes(args.episodes or ["0"], test, "the test split", all_names, args.data)
        eps = [schema.read_episode(f, n) for n in names]
        obs = torch.stack([torch.from_numpy(observation(f[schema.EPISODES][n], policy.cfg.image_size,
                                                        policy.cfg.use_depth, policy.cfg.cameras)) for n in names])
    gen = placement.generator(args.seed)
    k = 1 if policy.family == "mse" else args.samples
    samples = torch.stack([norm.unnormalize(predict(policy, obs, args.steps, None, gen, placement))
                           for _ in range(k)], dim=1)
    outcomes = None
    if args.replay is not None:
        details = read_json_object(args.replay, "replay details")
        outcomes = [outcome_text(details, args.model.name, n) for n in names]
    write_recording(args.output, eps, list(samples.numpy()), policy.cfg.model, outcomes)
    print(f"{args.output}: {len(eps)} episode(s), {k} sample(s) each from {args.model}")
    return 0


def pick_episodes(wanted: list[str], indexed: list[str], indexed_what: str, all_names: list[str],
                  data: Path) -> list[str]:
    """Episode names for --episodes: an episode's name, or an index into `indexed` (a digit string that is not
    itself an episode's name)."""
    names = []
    for e in wanted:
        if e.isascii() and e.isdigit() and e not in all_names:
            if int(e) >= len(indexed):
                raise AdlError(f"episode index {e} out of range: {indexed_what} has {len(indexed)} episodes")
            if indexed[int(e)] not in all_names:  # a split naming an episode the dataset lacks
                raise AdlError(f"{indexed_what} names episode {indexed[int(e)]!r}, which {data} does not hold")
            names.append(indexed[int(e)])
        elif e in all_names:
            names.append(e)
        else:
            raise AdlError(f"no episode {e!r} in {data}")
    return names


def record_dataset(args: object) -> int:
    with schema.open_dataset(args.data) as f:
        catalog = [r["name"] for r in schema.read_catalog(f)] or schema.episode_names(f)  # ingest order
    names = pick_episodes(args.episodes or [], catalog, f"{args.data}'s catalog", catalog, args.data) or catalog
    if not names:
        raise AdlError(f"{args.data}: no episodes to record")
    if args.bag:
        if len(names) != 1:
            raise AdlError("--bag shows one episode beside its bag: name it with --episodes NAME")
        images = write_bag_beside_episode(args.output, args.data, names[0], args.bag, args.config)
        print(f"{args.output}: episode {names[0]} of {args.data} beside {args.bag} ({images} bag images)")
        return 0
    frames = write_dataset_recording(args.output, args.data, names)
    print(f"{args.output}: {len(names)} episode(s), {frames} frames of {args.data}")
    return 0


if __name__ == "__main__":
    code = run_cli("adlpipe.inspect", main)
    if viewer.writer_stuck():  # Rerun's writer stopped on a full disk and would hold the exit forever
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)
