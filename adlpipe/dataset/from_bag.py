"""One bag (or one demonstration of it) read into an episode: the first frame's images, the end-effector path
resampled to waypoints and projected into every camera, the camera models, the objects' first poses; with a frame
writer, every frame streamed into the episode's group. What `adlpipe.ingest` runs per bag and what
`adlpipe.doctor --verify` runs again to compare a dataset with its bags."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np

from ..bags.episode_reader import BagReadout, check_counts, read_bag
from ..bags.images import decode_depth, decode_image
from ..bags.reader import BagSource
from ..bags.splits import recording_parts, split_note
from ..bags.topics import CameraTopics, TopicMap
from ..geometry.camera import Lens, lens_from_info, project
from ..geometry.transforms import matrix_to_quat, resample, scale_intrinsics
from ..plumbing.errors import AdlError
from . import schema
from .frames import FrameWriter

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


NON_FINITE = "non-finite values"  # what the doctor looks for in an episode's note


def non_finite_note(dropped: int, of: int, what: str, t: float, name: str) -> str:
    return f"left out {dropped} of {of} {what} with {NON_FINITE} (the first at {t:.2f} s, in {name})"


def finite_joints(r: BagReadout, tm: TopicMap, n_joints: int, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The joint states (s from the first image, positions) without those a sensor sent as NaN, which the notes
    name, as they name the state / action messages left out so, and the video packets before a first keyframe."""
    joint_t = np.asarray(r.joint_t, float) - r.t_img
    joint_pos = np.asarray(r.joint_pos, float).reshape(len(r.joint_t), n_joints)
    finite = np.isfinite(joint_pos).all(1)
    if not finite.all():
        k = int(np.flatnonzero(~finite)[0])
        notes.append(non_finite_note(int((~finite).sum()), len(finite), f"joint states on {tm.joints}",
                                     joint_t[k], r.joint_names[int(np.flatnonzero(~np.isfinite(joint_pos[k]))[0])]))
        joint_t, joint_pos = joint_t[finite], joint_pos[finite]
    for key, series in r.series.items():
        if series.non_finite:
            t, name = series.non_finite[0]
            notes.append(non_finite_note(len(series.non_finite), len(series.non_finite) + len(series.t),
                                         f"{key} messages on {getattr(tm, key)}", t - r.t_img, name))
    notes += [f"skipped {n} video packet(s) on {topic} before its first keyframe" for topic, n in
              r.video_skipped.items()]
    return joint_t, joint_pos


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
    cameras = [other_camera(r, tm, c, size, traj3d) for c in tm.extra_cameras]
    names, poses = object_poses(r, tm, camera_frame, [c.camera_frame for c in cameras])
    n_joints = len(r.joint_names) if r.joint_t else 0
    joint_t, joint_pos = finite_joints(r, tm, n_joints, notes)
    if frames is not None:
        gripper = r.joint_names.index(tm.gripper_joint) if tm.gripper_joint in r.joint_names[:n_joints] else None
        frames.finish(r.t_img, t_end, tm.sync_tolerance_s, ee_t, ee_p, joint_t, joint_pos, gripper,
                      f"{bag}: topic {tm.image}", r.series)
        if r.intervention:
            frames.intervention(r.t_img, r.intervention)
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
        topic_map=json.dumps(tm.to_dict()), window_ns=window,
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


def other_camera(r: BagReadout, tm: TopicMap, cam: CameraTopics, size: int,
                 traj3d: np.ndarray) -> schema.CameraView:
    """Another camera of the map: intrinsics at the stored size, lens, pose at the primary camera's first image
    (a wrist camera's pose is also stored per frame), and the trajectory in its pixels."""
    name = cam.name
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
