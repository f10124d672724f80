"""Ingest ROS bags into one HDF5 dataset (schema: adlpipe.schema, docs/hdf5_schema.md).

    python -m adlpipe.ingest data/bags/*.mcap -o data/adl.h5 [--config topics.yaml] [--waypoints 32]

Reads ROS2 MCAP (CDR) and ROS1-in-MCAP with the mcap decoders, ROS1 .bag and ROS2 folders/.db3 with rosbags,
streaming (only the first frame's images are kept). Messages are synced by header.stamp: depth, affordance and
the end-effector pose are matched to the first RGB frame within `sync_tolerance_s`. The end-effector path from the
first frame to its last pose is resampled to N waypoints evenly in time (traj3d, base frame, metres) and projected
into the stored image with the CameraInfo intrinsics (traj2d, pixels).

Re-ingesting a bag already in the file (same sha256) is a no-op. The output is written to a temp file and renamed,
so a failure or a kill leaves the old file (or none) in place.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import signal
import stat
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import h5py
import numpy as np
from tqdm import tqdm

from . import schema
from .atomic import atomic_path, check_outputs
from .bags.reader import BagSource
from .cli import Parser, int_range
from .errors import AdlError, run_cli
from .geometry import TfBuffer, matrix_to_quat, pose_matrix, project, resample, scale_intrinsics
from .images import decode_image, depth_to_metres
from .lock import exclusive
from .topics import TopicMap

IMAGE_TYPES = {"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"}
MAX_COORD_M = 1000.0  # tf translations beyond this are corrupt data, not a robot's workspace
TF_TYPES = {"tf2_msgs/msg/TFMessage", "tf/msg/tfMessage"}  # tf/tfMessage: old ROS1 bags, same layout


def sha256_of(path: Path) -> str:
    """Hash of a bag file, or of a rosbag2 folder's files (names and bytes, sorted)."""
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for p in files:
        if path.is_dir():
            h.update(p.relative_to(path).as_posix().encode())
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def stamp_s(msg: object) -> float:
    """header.stamp in seconds (ROS2 sec/nanosec, ROS1 secs/nsecs)."""
    st = msg.header.stamp
    sec = getattr(st, "sec", None)
    if sec is None:
        sec = st.secs
    nsec = getattr(st, "nanosec", None)
    if nsec is None:
        nsec = st.nsecs
    return int(sec) + int(nsec) * 1e-9


def _field(msg: object, *names: str) -> object:
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


def _check_types(bag: Path, topics: dict, tm: TopicMap) -> None:
    want = {tm.image: IMAGE_TYPES, tm.camera_info: {"sensor_msgs/msg/CameraInfo"},
            tm.tf: TF_TYPES, tm.tf_static: TF_TYPES,
            tm.depth: {"sensor_msgs/msg/Image"}, tm.affordance: {"sensor_msgs/msg/Image"},
            tm.joints: {"sensor_msgs/msg/JointState"}, tm.task: {"std_msgs/msg/String"}}
    for topic, types in want.items():
        if topic and topic in topics and topics[topic].msgtype not in types | {"?"}:
            expected = " or ".join(sorted(types))
            raise AdlError(f"{bag}: topic {topic} has type {topics[topic].msgtype}, expected {expected}")


def check_counts(bag: Path, topics: dict, read: dict[str, int]) -> None:
    """Compare messages read with the bag's own counts: a reader that silently yields nothing (e.g. a rosbag2
    QoS mismatch) must not pass as an empty topic."""
    for topic, n in read.items():
        declared = topics[topic].declared
        if declared is not None and n != declared:
            raise AdlError(f"{bag}: read {n} of the {declared} messages the bag declares on {topic}")


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


def list_topics(bag: Path) -> list[tuple[str, str, int | None, int]]:
    """(topic, type, declared count, messages actually read) for every topic: what `--list` prints."""
    src = BagSource(bag)
    topics = src.topics()
    read = dict.fromkeys(topics, 0)
    for topic, _t, decode in src.messages(list(topics)):
        decode()  # a message that does not decode is a bad bag, not a count
        read[topic] += 1
    return [(t, i.msgtype, i.declared, read[t]) for t, i in sorted(topics.items())]


class _Nearest:
    """Keeps the message whose stamp is nearest a reference time (set once the first image arrives)."""

    def __init__(self) -> None:
        self.best: tuple[float, float, object] | None = None  # (|dt|, stamp, msg)
        self.pending: list[tuple[float, object]] = []  # before the reference is known (bounded below)

    def offer(self, t: float, msg: object, ref: float | None) -> None:
        if ref is None:
            self.pending.append((t, msg))
            del self.pending[:-4]  # memory stays flat: only the latest few before the first image
            return
        for tp, mp in self.pending:
            self._consider(tp, mp, ref)
        self.pending.clear()
        self._consider(t, msg, ref)

    def _consider(self, t: float, msg: object, ref: float) -> None:
        if self.best is None or abs(t - ref) < self.best[0]:
            self.best = (abs(t - ref), t, msg)

    def finish(self, ref: float) -> tuple[float, object] | None:
        for tp, mp in self.pending:
            self._consider(tp, mp, ref)
        return (self.best[1], self.best[2]) if self.best else None


def extract_episode(bag: Path, tm: TopicMap, n_waypoints: int, size: int, task_override: str | None = None,
                    recover: bool = False, sha: str | None = None) -> tuple[schema.Episode, str]:
    """Read one bag into an Episode; returns it with a note (recovery losses, warnings)."""
    src = BagSource(bag, recover=recover)
    topics = src.topics()
    missing = [t for t in tm.required_topics() if t not in topics]
    if missing:
        have = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(topics.items())) or "no topics"
        raise AdlError(f"{bag}: missing required topic(s) {', '.join(missing)}; the bag has: {have}")
    _check_types(bag, topics, tm)
    wanted = [t for t in tm.required_topics() + tm.optional_topics() if t in topics]
    read = dict.fromkeys(wanted, 0)

    image = info = task = None
    t_img: float | None = None
    depth, aff = _Nearest(), _Nearest()
    tf = TfBuffer()
    joint_t: list[float] = []
    joint_pos: list[np.ndarray] = []
    joint_names: list[str] = []
    first_pose: dict[str, tuple[float, str, np.ndarray]] = {}
    where = lambda topic: f"{bag}: topic {topic}"  # noqa: E731

    settled: set[str] = set()  # depth/affordance topics whose stamps have passed the first image
    for topic, _log_t, decode in src.messages(wanted):
        read[topic] += 1
        if topic == tm.image:
            if image is None:
                msg = decode()
                image, t_img = decode_image(msg, where(topic)), stamp_s(msg)
                camera_frame = str(msg.header.frame_id)
        elif topic == tm.camera_info:
            if info is None:
                info = decode()
        elif topic in (tm.depth, tm.affordance):
            if topic not in settled:
                msg = decode()
                t = stamp_s(msg)
                (depth if topic == tm.depth else aff).offer(t, msg, t_img)
                if t_img is not None and t > t_img + tm.sync_tolerance_s:
                    settled.add(topic)
        elif topic in (tm.tf, tm.tf_static):
            for tr in decode().transforms:
                T = pose_matrix([tr.transform.translation.x, tr.transform.translation.y, tr.transform.translation.z],
                                [tr.transform.rotation.w, tr.transform.rotation.x, tr.transform.rotation.y,
                                 tr.transform.rotation.z])
                child, parent = str(tr.child_frame_id).lstrip("/"), str(tr.header.frame_id).lstrip("/")
                t = stamp_s(tr)
                tf.add(parent, child, t, T, static=topic == tm.tf_static)
                first_pose.setdefault(child, (t, parent, T))
        elif topic == tm.joints:
            msg = decode()
            pos = np.asarray(msg.position, float)
            if not joint_names:
                joint_names = [str(n) for n in msg.name]
            if len(pos) == len(joint_names):
                joint_t.append(stamp_s(msg))
                joint_pos.append(pos)
        elif topic == tm.task and task is None:
            task = str(decode().data)

    note = ""
    if recover and src.damaged:
        note = recovery_note(src, read)
    else:
        check_counts(bag, topics, read)
    if image is None or t_img is None:
        raise AdlError(f"{bag}: no message could be read on the image topic {tm.image}")
    if info is None:
        raise AdlError(f"{bag}: no message on the camera-info topic {tm.camera_info}")
    task = task_override or task
    if not task:
        raise AdlError(f"{bag}: no task name (topic {tm.task} absent or empty); pass --task")
    if any(ord(c) < 32 for c in task) or len(task) > 200:
        raise AdlError(f"{bag}: task name on {tm.task} has control characters or is too long: {task[:60]!r}")

    h0, w0 = image.shape[:2]
    K0 = np.asarray(_field(info, "k", "K"), float).reshape(3, 3)
    if not np.isfinite(K0).all() or int(info.width) not in (0, w0) or int(info.height) not in (0, h0) \
            or K0[0, 0] <= 0 or K0[1, 1] <= 0:
        raise AdlError(f"{bag}: camera info ({info.width}x{info.height}, fx={K0[0, 0]}) does not match the "
                       f"{w0}x{h0} image on {tm.image}")
    camera_frame = camera_frame or str(info.header.frame_id)
    T_bc = tf.lookup(tm.base_frame, camera_frame.lstrip("/"), t_img)
    if T_bc is None:
        raise AdlError(f"{bag}: no tf chain from camera frame {camera_frame!r} to base frame {tm.base_frame!r}")
    if not np.isfinite(T_bc).all() or np.abs(T_bc[:3, 3]).max() > MAX_COORD_M:
        raise AdlError(f"{bag}: camera pose from tf ({camera_frame} in {tm.base_frame}) is not finite")

    # End-effector path in the base frame, from the first image on.
    ee_times = tf.times.get(tm.ee_frame, [])
    if not ee_times:
        raise AdlError(f"{bag}: no tf for end-effector frame {tm.ee_frame!r} (frames: {sorted(tf.parent)})")
    ee_pos = []
    for t in ee_times:
        T = tf.lookup(tm.base_frame, tm.ee_frame, t)
        if T is None:
            raise AdlError(f"{bag}: no tf chain from {tm.ee_frame!r} to base frame {tm.base_frame!r}")
        ee_pos.append(T[:3, 3])
    ee_t = np.asarray(ee_times) - t_img
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
    traj3d = resample(ee_t, ee_p, 0.0, t_end, n_waypoints)

    # Images at the stored resolution; intrinsics follow the resize.
    sx, sy = size / w0, size / h0
    K = scale_intrinsics(K0, sx, sy)
    rgb = cv2.resize(image if image.ndim == 3 else np.repeat(image[..., None], 3, 2), (size, size),
                     interpolation=cv2.INTER_AREA).astype(np.uint8)
    traj2d = project(traj3d, K, T_bc)

    depth_img = None
    if tm.depth and tm.depth in topics:
        found = depth.finish(t_img)
        if found is None or abs(found[0] - t_img) > tm.sync_tolerance_s:
            raise AdlError(f"{bag}: no depth image on {tm.depth} within {tm.sync_tolerance_s} s of the first image")
        d = depth_to_metres(decode_image(found[1], where(tm.depth)), where(tm.depth))
        depth_img = cv2.resize(d, (size, size), interpolation=cv2.INTER_NEAREST)
    has_aff = False
    aff_img = np.zeros((size, size), np.float32)
    if tm.affordance and tm.affordance in topics:
        found = aff.finish(t_img)
        if found is None or abs(found[0] - t_img) > tm.sync_tolerance_s:
            raise AdlError(f"{bag}: no affordance map on {tm.affordance} within {tm.sync_tolerance_s} s of the "
                           "first image")
        a = decode_image(found[1], where(tm.affordance)).astype(np.float32)
        if a.ndim != 2:
            raise AdlError(f"{bag}: affordance map on {tm.affordance} must be single channel (32FC1)")
        aff_img = cv2.resize(np.nan_to_num(a), (size, size), interpolation=cv2.INTER_LINEAR)
        has_aff = True

    # Initial poses of the other frames hanging off the base (objects, manikin), for replay.
    skip = {tm.ee_frame, camera_frame.lstrip("/")}
    names, poses = [], []
    for child, (t, parent, _T) in sorted(first_pose.items()):
        if child in skip or parent != tm.base_frame:
            continue
        T = tf.lookup(tm.base_frame, child, t)
        names.append(child)
        poses.append(np.concatenate([T[:3, 3], matrix_to_quat(T[:3, :3])]))

    ep = schema.Episode(
        task=task, source_path=str(bag.resolve()), source_sha256=sha or sha256_of(bag), source_format=src.kind,
        duration_s=t_end, stamp0_ns=int(round(t_img * 1e9)), base_frame=tm.base_frame, camera_frame=camera_frame,
        rgb=rgb, affordance=aff_img, traj3d=traj3d, traj2d=traj2d, K=K, T_base_camera=T_bc, depth=depth_img,
        has_affordance=has_aff, object_names=names, objects=np.array(poses).reshape(-1, 7),
        ee_t=ee_t, ee_pos=ee_p,
        joint_t=np.asarray(joint_t) - t_img, joint_pos=np.asarray(joint_pos).reshape(len(joint_t), -1),
        joint_names=joint_names, note=note,
    )
    return ep, note


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


def _ignore_sigint() -> None:
    """Pool workers leave Ctrl-C to the parent, which stops them; a worker dying mid-result would hang the pool."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _worker(job: tuple) -> tuple[str, schema.Episode | None, str, str | None]:
    """(bag, episode or None if already ingested, note, error line or None). Runs in a pool process."""
    bag, tm, n, size, task, recover, known = job
    try:
        check_bag_path(Path(bag))
        sha = sha256_of(Path(bag)) if Path(bag).exists() else None
        if sha is not None and sha in known:
            return bag, None, "already ingested", None
        ep, note = extract_episode(Path(bag), tm, n, size, task, recover, sha)
        return bag, ep, note, None
    except AdlError as exc:
        return bag, None, "", str(exc)
    except MemoryError:
        return bag, None, "", f"{bag}: out of memory while reading the bag"
    except Exception as exc:  # noqa: BLE001 - one bag's unforeseen failure must not take the batch down
        return bag, None, "", f"{bag}: cannot ingest ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = Parser("python -m adlpipe.ingest", __doc__)
    p.add_argument("bags", nargs="+", type=Path, help=".mcap / .bag files, rosbag2 folders or .db3 files")
    p.add_argument("-o", "--output", type=Path, help="HDF5 file to create or extend (required unless --list)")
    p.add_argument("--list", action="store_true",
                   help="print each bag's topics, types, declared and read message counts; write nothing")
    p.add_argument("--config", type=Path, help="topic map YAML (keys of adlpipe.topics.TopicMap)")
    p.add_argument("--waypoints", type=int_range(2, 4096), default=32, help="waypoints per trajectory (default 32)")
    p.add_argument("--size", type=int_range(8, 4096), default=224, help="stored image width and height (default 224)")
    p.add_argument("--task", help="task name for bags without a task topic")
    p.add_argument("--workers", type=int_range(1, 256), default=min(4, os.cpu_count() or 1))
    p.add_argument("--skip-bad", action="store_true",
                   help="write the good bags and report the bad ones (exit 1) instead of writing nothing")
    p.add_argument("--recover", action="store_true",
                   help="read what is complete in a truncated MCAP and report what was lost")
    args = p.parse_args(argv)
    if not args.list and args.output is None:
        p.error("the following arguments are required: -o/--output")
    return args


def remove_stale_temps(output: Path) -> None:
    """Temp files of ingests that were killed (their process is gone): never a valid output, so remove them."""
    for tmp in output.parent.glob(f".{output.name}.tmp*"):
        try:
            pid = int(tmp.name.rsplit(".tmp", 1)[1])
            os.kill(pid, 0)
        except ValueError:
            continue  # not one of ours
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except PermissionError:
            continue  # alive, another user's


def ingest(bags: list[Path], output: Path, tm: TopicMap, n_waypoints: int = 32, size: int = 224,
           task: str | None = None, workers: int = 1, skip_bad: bool = False, recover: bool = False,
           progress: bool = False) -> dict:
    """Ingest bags into `output` atomically. Returns counts; raises AdlError (output untouched) on a bad bag."""
    known: set[str] = set()
    if output.exists():
        try:
            with h5py.File(output, "r") as f:
                schema.check_file(f, str(output), n_waypoints, size)
                known = schema.episode_shas(f)
        except OSError as exc:
            raise AdlError(f"{output}: existing output is not a readable HDF5 file ({exc})") from exc
    jobs = [(str(b), tm, n_waypoints, size, task, recover, known) for b in bags]
    results = []
    if workers > 1 and len(jobs) > 1:
        pool = ProcessPoolExecutor(max_workers=workers, initializer=_ignore_sigint)
        try:
            it = pool.map(_worker, jobs)
            results = list(tqdm(it, total=len(jobs), desc="ingest", unit="bag", file=sys.stderr,
                                disable=None if progress else True))
        except KeyboardInterrupt:
            for proc in list(getattr(pool, "_processes", {}).values()):  # stop now, not after the running bags
                proc.terminate()
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()
    else:
        bar = tqdm(jobs, desc="ingest", unit="bag", file=sys.stderr, disable=None if progress else True)
        results = [_worker(j) for j in bar]

    errors = [err for _b, _e, _n, err in results if err]
    if errors and not skip_bad:
        more = f" (and {len(errors) - 1} more bad bag(s))" if len(errors) > 1 else ""
        raise AdlError(errors[0] + more)
    new = {}
    for _bag, ep, _note, _err in results:
        if ep is not None and ep.source_sha256 not in known:
            new.setdefault(ep.source_sha256, ep)  # the same bag given twice is ingested once
    notes = [f"{b}: {n}" for b, ep, n, _ in results if n and ep is not None]
    counts = {"new": len(new), "skipped": len(results) - len(new) - len(errors), "bad": len(errors),
              "errors": errors, "notes": notes}
    if not new:
        return counts  # nothing to add: the file stays exactly as it was
    remove_stale_temps(output)
    check_free_space(output, new.values())
    with atomic_path(output) as tmp:
        if output.exists():
            shutil.copy2(output, tmp)
        with h5py.File(tmp, "a") as f:
            if schema.EPISODES not in f:
                schema.create_file(f, n_waypoints, size)
            for ep in new.values():
                schema.write_episode(f, ep)
    return counts


def check_free_space(output: Path, episodes: object) -> None:
    """Refuse to start writing into a file system that cannot hold the result (HDF5 does not fail cleanly on a full
    disk): the copy of the old file plus the new episodes uncompressed, an upper bound."""
    need = output.stat().st_size if output.exists() else 0
    for ep in episodes:  # type: ignore[attr-defined]
        need += sum(a.nbytes for a in (ep.rgb, ep.affordance, ep.traj3d, ep.traj2d, ep.ee_pos, ep.joint_pos))
        need += ep.depth.nbytes if ep.depth is not None else 0
    free = shutil.disk_usage(output.parent).free
    if free < need + (1 << 20):
        raise AdlError(f"no space left on device writing {output} (needs up to {need / 1e6:.1f} MB, "
                       f"{free / 1e6:.1f} MB free)")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.list:
        bad = 0
        for bag in args.bags:
            print(f"{bag}:")
            for topic, msgtype, declared, n in list_topics(bag):
                flag = "" if declared in (None, n) else "   <-- count mismatch"
                bad += bool(flag)
                print(f"  {topic:40s} {msgtype:40s} declared {declared!s:>6} read {n:>6}{flag}")
        return 1 if bad else 0
    tm = TopicMap.load(args.config)
    check_outputs(args.output)
    with exclusive(args.output):
        c = ingest(args.bags, args.output, tm, args.waypoints, args.size, args.task, args.workers, args.skip_bad,
                   args.recover, progress=True)
    for note in c["notes"]:
        print(f"note: {note}", file=sys.stderr)
    for err in c["errors"]:
        print(f"adlpipe.ingest: skipped bad bag: {err}", file=sys.stderr)
    print(f"{args.output}: {c['new']} episode(s) added, {c['skipped']} already present, {c['bad']} bad bag(s)")
    return 1 if c["bad"] else 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.ingest", main))
