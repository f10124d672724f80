"""Ingest ROS bags into one HDF5 dataset (schema: adlpipe.dataset.schema, docs/hdf5_schema.md).

    python -m adlpipe.ingest data/bags/*.mcap -o data/adl.h5 [--config topics.yaml] [--waypoints 32]

Reads ROS2 MCAP (CDR) and ROS1-in-MCAP with the mcap decoders, ROS1 .bag and ROS2 folders/.db3 with rosbags,
streaming: every camera frame is resized to --size and appended to the bag's episode file as it is read, so memory
stays flat in bag length. Messages are synced by header.stamp within `sync_tolerance_s`: depth, affordance, joint
states and the end-effector pose (interpolated in tf) to every frame (adlpipe.dataset.frames). For the seed's
first-frame setting the end-effector path from the first frame to its last pose is also resampled to N waypoints
evenly in time (traj3d, base frame, metres) and projected into the stored image (traj2d, pixels).

The output is an index (-o FILE) and a folder of episode files beside it (FILE's stem + .shards): one file per bag,
one folder per run (adlpipe.dataset.shards). Appending writes only the new bags; re-ingesting a bag already in the
dataset (same sha256) is a no-op. The index is replaced last, by a rename, so a failure or a kill leaves the old
dataset (or none) whole.

Across machines: every machine (a Slurm array task, a Ray or Dask task) runs the same command with its own
--shard I/N and takes every N-th bag of the sorted list, starting at the I-th, into its own share folder; the index
is untouched until `--gather` links every finished share into it:

    python -m adlpipe.ingest data/bags/* -o data/adl.h5 --shard 1/8     # ... through 8/8, in parallel
    python -m adlpipe.ingest --gather -o data/adl.h5                     # once all shares have finished
"""

from __future__ import annotations

import argparse
import errno
import hashlib
import multiprocessing
import os
import shutil
import signal
import stat
import sys
from collections.abc import Iterable
from pathlib import Path

import cv2
import h5py
import numpy as np
from tqdm import tqdm

from .atomic import check_outputs
from .bags.episode_reader import BagReadout, check_counts, read_bag
from .bags.images import decode_depth, decode_image
from .bags.reader import BagSource
from .bags.segments import find_segments
from .bags.splits import recording_parts, recordings, split_note
from .bags.survey import list_lines, suggest_config, survey
from .bags.topics import TopicMap
from .camera import Lens, lens_from_info, project
from .cli import Parser, int_range
from .dataset import schema, shards
from .dataset.frames import FrameWriter
from .dvc_outputs import refuse_pipeline_outputs
from .errors import AdlError, one_line, run_cli
from .geometry import matrix_to_quat, resample, scale_intrinsics
from .lock import exclusive

MAX_COORD_M = 1000.0  # tf translations beyond this are corrupt data, not a robot's workspace


def sha256_of(path: Path) -> str:
    """Hash of a bag file, of a ROS1 split recording's parts (their bytes in order), or of a rosbag2 folder's
    files (names and bytes, sorted)."""
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else recording_parts(path)
    for p in files:
        if path.is_dir():
            h.update(p.relative_to(path).as_posix().encode())
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def _field(msg: object, *names: str) -> object:
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


def recovery_note(src: BagSource, read: dict[str, int]) -> str:
    """How much of a truncated MCAP was lost, on the topics the ingest uses."""
    meta = src.declared_in_metadata()
    got = sum(read.values())
    if not meta:
        return f"recovered {got} messages from a damaged MCAP; {src.lost_note or 'its tail is lost'}; " \
               "the bag does not say how many messages it held"
    held = {t: meta[t] for t in read if t in meta}
    lost = {t: n - read[t] for t, n in held.items() if n > read[t]}
    per_topic = ", ".join(f"{t} {n}" for t, n in sorted(lost.items())) or "none"
    return (f"recovered {got} of {sum(held.values())} messages from a damaged MCAP: lost {sum(lost.values())} "
            f"({per_topic})")


def extract_episode(bag: Path, tm: TopicMap, n_waypoints: int, size: int, task_override: str | None = None,
                    recover: bool = False, sha: str | None = None, allow_tf_gaps: bool = False,
                    window: tuple[int, int] | None = None, segment: int = -1,
                    frames: FrameWriter | None = None) -> tuple[schema.Episode, str]:
    """Read one bag (or one demonstration of it: `window`, log time ns) into an Episode; returns it with a note
    (recovery losses, bridged tf gaps). With `frames`, every frame streams into it and is synced at the end."""
    src = BagSource(bag, recover=recover)
    r = read_bag(src, tm, window, frames)
    notes = [split_note(src.parts)] if len(src.parts) > 1 else []
    if recover and src.damaged:
        notes.append(recovery_note(src, r.read))
    else:
        check_counts(bag, r.topics, r.read)
    task = task_override or r.task
    if not task:
        raise AdlError(f"{bag}: no task name (topic {tm.task} absent or empty); pass --task")
    if any(ord(c) < 32 for c in task) or len(task) > 200:
        raise AdlError(f"{bag}: task name on {tm.task} has control characters or is too long: {task[:60]!r}")
    K0, camera_frame, T_bc, lens = camera_model(r, tm)
    ee_t, ee_p, t_end, gap_note = end_effector_path(r, tm, allow_tf_gaps)
    notes += [gap_note] if gap_note else []
    traj3d = resample(ee_t, ee_p, 0.0, t_end, n_waypoints)

    # Images at the stored resolution; intrinsics follow the resize.
    h0, w0 = r.image.shape[:2]
    K = scale_intrinsics(K0, size / w0, size / h0)
    image = r.image if r.image.ndim == 3 else np.repeat(r.image[..., None], 3, 2)
    rgb = cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA).astype(np.uint8)
    depth_msg = _synced_image(r.depth, tm.depth, r, tm, "depth image")
    depth_img = None
    if depth_msg is not None:
        depth_img = cv2.resize(decode_depth(depth_msg, f"{bag}: topic {tm.depth}"), (size, size),
                               interpolation=cv2.INTER_NEAREST)
    aff_msg = _synced_image(r.affordance, tm.affordance, r, tm, "affordance map")
    aff_img = np.zeros((size, size), np.float32)
    if aff_msg is not None:
        a = decode_image(aff_msg, f"{bag}: topic {tm.affordance}").astype(np.float32)
        if a.ndim != 2:
            raise AdlError(f"{bag}: affordance map on {tm.affordance} must be single channel (32FC1)")
        aff_img = cv2.resize(np.nan_to_num(a), (size, size), interpolation=cv2.INTER_LINEAR)
    cameras = [other_camera(r, tm, c.name, size, traj3d) for c in tm.extra_cameras]
    names, poses = object_poses(r, tm, camera_frame, [c.camera_frame for c in cameras])
    n_joints = len(r.joint_names) if r.joint_t else 0
    if n_joints and not np.isfinite(np.asarray(r.joint_pos, float)).all():
        raise AdlError(f"{bag}: non-finite joint positions on {tm.joints}")
    joint_t = np.asarray(r.joint_t, float) - r.t_img
    joint_pos = np.asarray(r.joint_pos, float).reshape(len(r.joint_t), n_joints)
    if frames is not None:
        gripper = r.joint_names.index(tm.gripper_joint) if tm.gripper_joint in r.joint_names[:n_joints] else None
        frames.finish(r.t_img, t_end, tm.sync_tolerance_s, ee_t, ee_p, joint_t, joint_pos, gripper,
                      f"{bag}: topic {tm.image}", r.series)
        for c in cameras:
            cw = frames.camera(c.name)
            index = cw.finish_camera(r.t_img, t_end, tm.sync_tolerance_s, frames.kept_t,
                                     lambda t, c=c: camera_poses(r, tm, c, r.t_img + t), f"{bag}: camera {c.name}")
            if (index < 0).any():
                notes.append(f"camera {c.name} has no frame within {tm.sync_tolerance_s} s of {int((index < 0).sum())}"
                             f" of the {len(index)} frames of camera {tm.camera_name}")
        for name, w in [(None, frames), *frames.cameras.items()]:
            if w.reordered:
                notes.append(f"ordered {w.reordered} frame(s) logged out of header-stamp order"
                             + (f", dropped {w.early} stamped before the first image" if w.early else "")
                             + (f" (camera {name})" if name else ""))
    ep = schema.Episode(
        task=task, source_path=str(bag.resolve()), source_sha256=sha or sha256_of(bag), source_format=r.kind,
        duration_s=t_end, stamp0_ns=int(round(r.t_img * 1e9)), base_frame=tm.base_frame, camera_frame=camera_frame,
        rgb=rgb, affordance=aff_img, traj3d=traj3d, traj2d=project(traj3d, K, T_bc, lens, (size, size)), K=K,
        T_base_camera=T_bc,
        depth=depth_img, has_affordance=aff_msg is not None, object_names=names,
        objects=np.array(poses).reshape(-1, 7), ee_t=ee_t, ee_pos=ee_p,
        joint_t=joint_t, joint_pos=joint_pos,
        joint_names=r.joint_names if n_joints else [], note="; ".join(notes), segment=segment, lens=lens,
        camera_name=tm.camera_name, cameras=cameras,
    )
    return ep, ep.note


def camera_model(r: BagReadout, tm: TopicMap) -> tuple[np.ndarray, str, np.ndarray, Lens]:
    """(intrinsics of the recorded image, camera frame, camera pose in the base frame, lens distortion). The lens's
    coefficients act on normalised coordinates: they hold for the resized image too."""
    K0, camera_frame, lens = _intrinsics(r, r.info, r.image.shape, r.camera_frame, tm.camera_info, tm.image)
    return K0, camera_frame, _camera_pose(r, tm, camera_frame, r.t_img, ""), lens


def _intrinsics(r: BagReadout, info: object, shape: tuple[int, ...], frame: str, info_topic: str,
                image_topic: str) -> tuple[np.ndarray, str, Lens]:
    """(K of the recorded image, camera frame, lens) from a camera's CameraInfo, checked against its image."""
    h0, w0 = shape[:2]
    try:
        K0 = np.asarray(_field(info, "k", "K"), float).reshape(3, 3)
        width, height = int(info.width), int(info.height)
        camera_frame = frame or str(info.header.frame_id)
        lens = lens_from_info(getattr(info, "distortion_model", ""), getattr(info, "d", getattr(info, "D", None)),
                              f"{r.bag}: topic {info_topic}")
    except (AttributeError, TypeError, ValueError) as exc:
        raise AdlError(f"{r.bag}: topic {info_topic}: CameraInfo lacks field {exc} (k, width, height, "
                       "header)") from None
    if not np.isfinite(K0).all() or width not in (0, w0) or height not in (0, h0) or K0[0, 0] <= 0 or K0[1, 1] <= 0:
        raise AdlError(f"{r.bag}: camera info ({width}x{height}, fx={K0[0, 0]}) does not match the "
                       f"{w0}x{h0} image on {image_topic}")
    return K0, camera_frame, lens


def _camera_pose(r: BagReadout, tm: TopicMap, camera_frame: str, t: float, which: str) -> np.ndarray:
    """A camera's pose in the base frame at t (absolute s), between its tf samples (a wrist camera moves with the
    arm, and its frames fall between the arm's tf messages)."""
    T_bc = r.tf.lookup(tm.base_frame, camera_frame.lstrip("/"), t, interpolate=True)
    if T_bc is None:
        raise AdlError(f"{r.bag}: no tf chain from {which}camera frame {camera_frame!r} to base frame "
                       f"{tm.base_frame!r}")
    if not np.isfinite(T_bc).all() or np.abs(T_bc[:3, 3]).max() > MAX_COORD_M:
        raise AdlError(f"{r.bag}: {which}camera pose from tf ({camera_frame} in {tm.base_frame}) is not finite")
    return T_bc


def other_camera(r: BagReadout, tm: TopicMap, name: str, size: int, traj3d: np.ndarray) -> schema.CameraView:
    """Another camera of the map: intrinsics at the stored size, lens, pose at the primary camera's first image
    (a wrist camera's pose is also stored per frame), and the trajectory in its pixels."""
    cam = next(c for c in tm.extra_cameras if c.name == name)
    seen = r.cameras[name]
    K0, frame, lens = _intrinsics(r, seen.info, seen.shape, seen.frame, cam.camera_info, cam.image)
    K = scale_intrinsics(K0, size / seen.shape[1], size / seen.shape[0])
    T_bc = _camera_pose(r, tm, frame, r.t_img, f"camera {name}'s ")
    return schema.CameraView(name=name, camera_frame=frame, K=K, T_base_camera=T_bc,
                             traj2d=project(traj3d, K, T_bc, lens, (size, size)), lens=lens)


def camera_poses(r: BagReadout, tm: TopicMap, cam: schema.CameraView, t: np.ndarray) -> np.ndarray:
    """A camera's pose in the base frame at each absolute stamp in t (s)."""
    return np.stack([_camera_pose(r, tm, cam.camera_frame, float(s), f"camera {cam.name}'s ") for s in t]) \
        if len(t) else np.zeros((0, 4, 4))


def end_effector_path(r: BagReadout, tm: TopicMap, allow_gaps: bool) -> tuple[np.ndarray, np.ndarray, float, str]:
    """(times from the first image, positions in the base frame, end time, note) of the end-effector frame. A frame
    on /tf_static (a tool frame off a moving link) follows its nearest moving ancestor, at that frame's times."""
    bag = r.bag
    moving = r.tf.motion_times(tm.ee_frame, tm.base_frame)
    if moving is None:
        known = sorted(set(r.tf.parent) | set(r.tf.parent.values()))
        why = "it does not move" if tm.ee_frame in r.tf.parent else "no tf for it"
        raise AdlError(f"{bag}: end-effector frame {tm.ee_frame!r}: {why} relative to {tm.base_frame!r} "
                       f"(frames: {known})")
    mover, ee_times = moving
    ee_pos = []
    for t in ee_times:
        T = r.tf.lookup(tm.base_frame, tm.ee_frame, t)
        if T is None:
            raise AdlError(f"{bag}: no tf chain from {tm.ee_frame!r} to base frame {tm.base_frame!r}")
        ee_pos.append(T[:3, 3])
    ee_t = np.asarray(ee_times) - r.t_img
    ee_p = np.asarray(ee_pos)
    if ee_t[0] > tm.sync_tolerance_s:
        raise AdlError(f"{bag}: first end-effector pose is {ee_t[0]:.3f} s after the first image "
                       f"(tolerance {tm.sync_tolerance_s} s)")
    t_end = float(ee_t[-1]) if tm.trajectory_end_s is None else min(float(ee_t[-1]), tm.trajectory_end_s)
    if t_end <= 0:
        raise AdlError(f"{bag}: the end-effector path ends before the first image")
    if not (np.isfinite(ee_p).all() and np.abs(ee_p).max() < MAX_COORD_M):
        raise AdlError(f"{bag}: end-effector poses from tf ({tm.ee_frame} in {tm.base_frame}) are not finite "
                       f"or exceed {MAX_COORD_M} m")
    if not np.all(np.diff(ee_t) >= 0):
        raise AdlError(f"{bag}: end-effector tf stamps go backwards")
    inside = ee_t[(ee_t >= -tm.sync_tolerance_s) & (ee_t <= t_end)]
    gaps = np.diff(inside) if len(inside) > 1 else np.zeros(1)
    note = ""
    if gaps.max() > tm.max_tf_gap_s:
        k = int(gaps.argmax())
        where = f"{gaps[k]:.2f} s gap in the tf of {mover!r} at {inside[k]:.2f} s after the first image"
        if not allow_gaps:
            raise AdlError(f"{bag}: {where} (max_tf_gap_s {tm.max_tf_gap_s}); the path across it would be a guess; "
                           "pass --allow-tf-gaps to keep the bag with a note")
        note = f"bridged a {where}"
    return ee_t, ee_p, t_end, note


def _synced_image(found: tuple[float, object] | None, topic: str | None, r: BagReadout, tm: TopicMap,
                  what: str) -> object | None:
    """The message of an optional image topic nearest the first frame; None if the map or the bag has no such
    topic; an error if the topic is there but nothing lies within the sync tolerance."""
    if not topic or topic not in r.topics:
        return None
    if found is None or abs(found[0] - r.t_img) > tm.sync_tolerance_s:
        raise AdlError(f"{r.bag}: no {what} on {topic} within {tm.sync_tolerance_s} s of the first image")
    return found[1]


def object_poses(r: BagReadout, tm: TopicMap, camera_frame: str,
                 other_frames: list[str] = ()) -> tuple[list[str], list[np.ndarray]]:
    """Initial poses of the other frames hanging off the base (objects, manikin), for replay."""
    skip = {tm.ee_frame, camera_frame.lstrip("/"), *(f.lstrip("/") for f in other_frames)}
    names, poses = [], []
    for child, (t, parent, _T) in sorted(r.first_pose.items()):
        if child in skip or parent != tm.base_frame:
            continue
        T = r.tf.lookup(tm.base_frame, child, t)
        if not np.isfinite(T).all() or np.abs(T[:3, 3]).max() > MAX_COORD_M:
            raise AdlError(f"{r.bag}: pose of frame {child!r} in {tm.base_frame!r} from tf is not finite")
        names.append(child)
        poses.append(np.concatenate([T[:3, 3], matrix_to_quat(T[:3, :3])]))
    return names, poses


def check_bag_path(bag: Path) -> None:
    """Bags are regular files or rosbag2 folders: a FIFO, a device (a link to /dev/zero) or a socket would block or
    never end."""
    try:
        mode = bag.stat().st_mode
    except FileNotFoundError:
        return  # the reader says "no such bag" with the formats it knows
    except OSError as exc:
        raise AdlError(f"{bag}: cannot read ({exc.strerror})") from None
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise AdlError(f"{bag}: not a regular file or folder (a pipe, device or socket); give a bag file")


def _pool_worker_init() -> None:
    """Pool workers leave Ctrl-C to the parent, which stops them (a worker dying mid-result would hang the pool),
    and report a full disk once."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _report_full_disk_once()


def _report_full_disk_once() -> None:
    """After the disk filled, every HDF5 object released on the way out tries its write again and fails in a
    Cython destructor, which prints the error (through sys.excepthook) and then reports it as unraisable, each
    time; the full disk is already the stage's one error line, so those two hooks pass over it."""
    def full_disk(exc: BaseException | None) -> bool:
        return isinstance(exc, OSError) and exc.errno == errno.ENOSPC

    def unraisable(u: sys.UnraisableHookArgs) -> None:
        if not full_disk(u.exc_value):
            sys.__unraisablehook__(u)

    def excepthook(kind: type[BaseException], exc: BaseException, tb: object) -> None:
        if not full_disk(exc):
            sys.__excepthook__(kind, exc, tb)

    sys.unraisablehook, sys.excepthook = unraisable, excepthook


def _worker(job: tuple) -> tuple[str, list[dict[str, str]], str, str | None]:
    """(bag, catalog rows of its episodes (none if already ingested), note, error line or None). Runs in a pool
    process: it streams the bag's episodes into their own file, `out`, and removes it on failure."""
    bag, tm, n, size, task, recover, known_shas, allow_gaps, segments_file, out = job
    try:
        check_bag_path(Path(bag))
        sha = sha256_of(Path(bag)) if Path(bag).exists() else None
        if sha is not None and sha in known_shas:
            return bag, [], "already ingested", None
        windows = find_segments(Path(bag), tm, segments_file) if not recover else None
        rows, notes = [], []
        with h5py.File(out, "w") as f:
            for k, w in enumerate(windows or [None]):
                g = f.create_group("pending")
                ep, note = extract_episode(Path(bag), tm, n, size, task, recover, sha, allow_gaps, w,
                                           k if windows else -1, FrameWriter(g, size))
                schema.write_episode(g, ep)
                f.move("pending", f"{schema.EPISODES}/{ep.name}")
                rows.append({"name": ep.name, "key": ep.key, "task": ep.task, "file": Path(out).name})
                notes += [f"segment {k}: {note}" if windows else note] if note else []
        if windows is None:
            return bag, rows, "; ".join(notes), None
        return bag, rows, f"{len(rows)} demonstrations" + (f" ({'; '.join(notes)})" if notes else ""), None
    except AdlError as exc:
        error = str(exc)
    except MemoryError:
        error = f"{bag}: out of memory while reading the bag"
    except Exception as exc:  # noqa: BLE001 - one bag's unforeseen failure must not take the batch down
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:  # the disk filled while writing: no bag's
            Path(out).unlink(missing_ok=True)  # fault, and no later bag fares better; the run stops
            raise
        error = f"{bag}: cannot ingest ({type(exc).__name__}: {one_line(exc, 200)})"
    Path(out).unlink(missing_ok=True)
    return bag, [], "", error


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = Parser("python -m adlpipe.ingest", __doc__)
    p.add_argument("bags", nargs="*", type=Path, help=".mcap / .bag files, rosbag2 folders or .db3 files")
    p.add_argument("-o", "--output", type=Path, help="HDF5 file to create or extend (required unless --list)")
    p.add_argument("--list", action="store_true",
                   help="print each bag's topics: type, declared and read counts, rate, largest gap between "
                   "messages and the offset of header.stamp from log time; write nothing")
    p.add_argument("--suggest-config", action="store_true",
                   help="print a topic-map YAML guessed from the (first) bag, with comments; write nothing")
    p.add_argument("--config", type=Path, action="append",
                   help="topic map YAML (keys of adlpipe.bags.topics.TopicMap); repeat it to combine, later ones "
                   "override: --config pipelines/presets/azure_kinect.yaml --config pipelines/presets/kinova_gen3.yaml")
    p.add_argument("--waypoints", type=int_range(2, 4096), default=32, help="waypoints per trajectory (default 32)")
    p.add_argument("--size", type=int_range(16, 4096), default=224, help="stored image width and height (default 224)")
    p.add_argument("--task", help="task name for bags without a task topic")
    p.add_argument("--workers", type=int_range(1, 256), default=min(4, os.cpu_count() or 1))
    p.add_argument("--skip-bad", action="store_true",
                   help="write the good bags and report the bad ones (exit 1) instead of writing nothing")
    p.add_argument("--allow-tf-gaps", action="store_true",
                   help="keep a bag whose end-effector tf has a gap over max_tf_gap_s, with a note, instead of "
                   "refusing it")
    p.add_argument("--segments", type=Path,
                   help="segments YAML for a bag holding several demonstrations (default: <bag>.segments.yaml "
                   "beside it, if there)")
    p.add_argument("--recover", action="store_true",
                   help="read what is complete in a truncated MCAP and report what was lost")
    p.add_argument("--shard", type=share_arg, metavar="I/N",
                   help="take the I-th of N disjoint shares of the bags (every N-th of the sorted list) into a share "
                   "folder of the dataset, leaving the index to --gather (one share per machine or task)")
    p.add_argument("--gather", action="store_true",
                   help="link every finished share (--shard) into the index; give no bags")
    p.add_force()
    args = p.parse_args(argv)
    if not (args.list or args.suggest_config) and args.output is None:
        p.error("the following arguments are required: -o/--output")
    if args.gather and (args.bags or args.shard):
        p.error("--gather takes no bags and no --shard: it links the shares already written")
    if not args.gather and not args.bags:
        p.error("the following arguments are required: bags")
    return args


def share_arg(text: str) -> tuple[int, int]:
    """'I/N' -> (I, N), 1 <= I <= N."""
    i, sep, n = text.partition("/")
    if not (sep and i.strip().isdigit() and n.strip().isdigit()) or not 1 <= int(i) <= int(n):
        raise argparse.ArgumentTypeError(f"{text!r} is not a share I/N with 1 <= I <= N (e.g. 3/8)")
    return int(i), int(n)


def share_of(bags: list[Path], share: tuple[int, int]) -> list[Path]:
    """The I-th of N disjoint shares: every N-th bag of the sorted list from the I-th on. Every machine that is given
    the same bags (in any order) takes the same share."""
    i, n = share
    return sorted(bags, key=lambda b: str(b))[i - 1::n]


def ingest(bags: list[Path], output: Path, tm: TopicMap, n_waypoints: int = 32, size: int = 224,
           task: str | None = None, workers: int = 1, skip_bad: bool = False, recover: bool = False,
           progress: bool = False, allow_tf_gaps: bool = False, segments: Path | None = None,
           share: tuple[int, int] | None = None) -> dict:
    """Ingest bags into the dataset `output` (an index; episode files in adl.shards beside it). Each bag streams
    into its own file as it is read; the index is replaced only when every bag is in. Returns counts; raises
    AdlError (dataset untouched) on a bad bag. share (I, N): only that share of the bags, committed as a share
    folder for shards.gather, the index untouched."""
    bags = recordings(bags)
    if share:
        bags = share_of(bags, share)
    known: set[str] = set()
    if output.exists():
        try:
            with h5py.File(output, "r") as f:
                schema.check_file(f, str(output), n_waypoints, size)
                known = schema.episode_keys(f)
        except OSError as exc:
            raise AdlError(f"{output}: existing output is not a readable HDF5 file ({exc})") from exc
        try:  # every episode it holds readable: an append never builds on a damaged dataset
            with schema.open_dataset(output):
                pass
        except AdlError as exc:
            raise AdlError(f"cannot append to a damaged dataset: {exc}") from None
    known_shas = {k.split("#")[0] for k in known}  # a bag whose sha is in the file is skipped whole
    output.parent.mkdir(parents=True, exist_ok=True)
    if not share:  # a share never cleans up: other shares write beside it, on other machines
        shards.remove_unreferenced(output)
    check_free_space(output, bags)
    root_existed = share is not None or shards.shards_dir(output).exists()
    run, tmp_dir = shards.new_run(output, share)
    try:
        jobs = [(str(b), tm, n_waypoints, size, task, recover, known_shas, allow_tf_gaps, segments,
                 str(tmp_dir / f"{i:06d}.h5")) for i, b in enumerate(bags)]
        try:
            results = _run_jobs(jobs, workers, progress)
        except OSError as exc:
            if exc.errno == errno.ENOSPC:  # name the dataset, not a temp file of the run (removed below)
                raise OSError(errno.ENOSPC, "No space left on device", str(output)) from None
            raise
        errors = [err for _b, _r, _n, err in results if err]
        if errors and not skip_bad:
            more = f" (and {len(errors) - 1} more bad bag(s))" if len(errors) > 1 else ""
            raise AdlError(errors[0] + more)
        new: dict[str, dict[str, str]] = {}
        for _bag, rows, _note, _err in results:
            if rows and all(r["key"] in known or r["key"] in new for r in rows):
                (tmp_dir / rows[0]["file"]).unlink()  # the same bag given twice is ingested once
                continue
            new.update((r["key"], r) for r in rows)
        notes = [f"{b}: {n}" for b, rows, n, _ in results if n and rows]
        skipped = sum(1 for _b, rows, _n, err in results if not rows and not err)
        counts = {"new": len(new), "skipped": skipped, "bad": len(errors), "errors": errors, "notes": notes}
        if new and share:
            shards.commit_share(output, run, tmp_dir, list(new.values()), n_waypoints, size)
        elif new:
            shards.commit(output, run, tmp_dir, list(new.values()), n_waypoints, size)
        return counts
    finally:
        if tmp_dir.exists():  # not committed: nothing of this run may stay
            shutil.rmtree(tmp_dir, ignore_errors=True)
            if not root_existed:
                shutil.rmtree(shards.shards_dir(output), ignore_errors=True)


def _run_jobs(jobs: list[tuple], workers: int, progress: bool) -> list[tuple]:
    """_worker over the jobs, in a process pool when there are several. Results are a few strings per bag."""
    bar = {"desc": "ingest", "unit": "bag", "file": sys.stderr, "disable": None if progress else True,
           "total": len(jobs)}
    if workers <= 1 or len(jobs) <= 1:
        return [_worker(j) for j in tqdm(jobs, **bar)]
    # multiprocessing's Pool, not concurrent.futures: its workers can be stopped at once on Ctrl-C, where an
    # executor's management thread trips over the futures it cancelled (InvalidStateError, a hang). Ctrl-C is
    # held back while the workers fork, so it never meets a half-built pool.
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        pool = multiprocessing.get_context("fork").Pool(workers, initializer=_pool_worker_init)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
    try:
        results = list(tqdm(pool.imap(_worker, jobs), **bar))
        pool.close()
        return results
    except BaseException:
        pool.terminate()  # the workers ignore SIGINT, so none dies holding the task queue's lock
        raise
    finally:
        pool.join()


def check_free_space(output: Path, bags: Iterable[Path]) -> None:
    """Refuse to start writing into a file system that cannot hold the result (HDF5 does not fail cleanly on a full
    disk). A bag's episode file holds its frames compressed at the stored size: less than the bag, except for a
    bag of small compressed images stored larger, so the bound is the bags' size plus 10 MB."""
    need = 10 << 20
    for b in bags:
        try:
            files = b.rglob("*") if b.is_dir() else recording_parts(b)
            need += sum(p.stat().st_size for p in files if p.is_file())
        except OSError:
            continue  # the worker reports the bag
    free = shutil.disk_usage(output.parent).free
    if free < need:
        raise AdlError(f"no space left on device writing {output} (needs up to {need / 1e6:.1f} MB, "
                       f"{free / 1e6:.1f} MB free)")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _report_full_disk_once()
    args.bags = recordings(args.bags)  # a folder of ROS1 bags: its bags; a split recording's parts: one recording
    if args.suggest_config:
        print(suggest_config(survey(args.bags[0])), end="")
        return 0
    if args.list:
        bad = 0
        for bag in args.bags:
            s = survey(bag)
            print("\n".join(list_lines(s)))
            bad += sum(t.declared not in (None, t.read) for t in s.topics.values())
        return 1 if bad else 0
    check_outputs(args.output)
    refuse_pipeline_outputs([args.output], args.force)
    if args.gather:
        with exclusive(args.output):
            g = shards.gather(args.output)
        for name in g["unfinished"]:
            print(f"note: {shards.shards_dir(args.output) / name}: a share still being written (or written on "
                  "another machine); left alone: gather again when it has finished, or remove it if it was "
                  "stopped", file=sys.stderr)
        print(f"{args.output}: {g['new']} episode(s) linked from {g['shares']} share(s), {g['episodes']} in all")
        return 0
    tm = TopicMap.load(args.config)
    lock = args.output.with_name(f"{args.output.name}.share-{args.shard[0]}-of-{args.shard[1]}") if args.shard \
        else args.output  # shares run side by side; each excludes only a second run of itself
    with exclusive(lock):
        c = ingest(args.bags, args.output, tm, args.waypoints, args.size, args.task, args.workers, args.skip_bad,
                   args.recover, progress=True, allow_tf_gaps=args.allow_tf_gaps, segments=args.segments,
                   share=args.shard)
    for note in c["notes"]:
        print(f"note: {note}", file=sys.stderr)
    for err in c["errors"]:
        print(f"adlpipe.ingest: skipped bad bag: {err}", file=sys.stderr)
    where = f" into share {args.shard[0]}/{args.shard[1]} (link it with --gather)" if args.shard else ""
    print(f"{args.output}: {c['new']} episode(s) added{where}, {c['skipped']} already present, {c['bad']} bad "
          "bag(s)")
    return 1 if c["bad"] else 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.ingest", main))
