"""A held-out set of defects for the doctor: 14 kinds no adlpipe issue named, each taken from what labs reported in
public trackers (the source beside each), planted one per bag with the real writer (bench/plant_defects.py's reader
and writer). Written without the doctor's checks in view and measured once (bench/doctor_vs_peers.py --set heldout):
8 of 14. The doctor's end-effector-in-image check came after that measurement (the misses pointed at it), so for
that check this set is no longer held out (results/bench/doctor_defects.md gives both).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from plant_defects import (
    CAMERA_FRAME,
    DEPTH,
    FACTORY,
    IMAGE,
    INFO,
    JOINTS,
    TF,
    TF_STATIC,
    Message,
    _depth,
    _of,
    _pixels,
    _set_depth,
    read,
    stamp_ns,
    write,
)

EE_FRAME = "ee_link"  # the recorder's end effector on /tf


def _set_stamp(msg: object, t_ns: int) -> None:
    headers = [msg.header] if hasattr(msg, "header") else [tr.header for tr in msg.transforms]
    for h in headers:
        h.stamp.sec, h.stamp.nanosec = int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000)


def image_stamps_zero(messages: list[Message]) -> list[Message]:
    """avt_vimba_camera#69: the driver left the colour image's header stamp at 0 (depth and camera_info kept)."""
    for msg in _of(messages, (IMAGE,)):
        _set_stamp(msg, 0)
    return messages


def camera_own_clock(messages: list[Message]) -> list[Message]:
    """ApolloAuto/apollo#4187: the camera stamps with its own clock, seconds since it started, while the robot's
    streams carry the system time."""
    first = min(stamp_ns(m) for m in _of(messages, (IMAGE,)))
    for msg in _of(messages, (IMAGE, DEPTH, INFO)):
        _set_stamp(msg, stamp_ns(msg) - first + 1_000_000)
    return messages


def identity_intrinsics(messages: list[Message]) -> list[Message]:
    """ensenso/ros_driver#59: camera_info's K the identity (an uncalibrated default), the image size kept."""
    for msg in _of(messages, (INFO,)):
        msg.k = np.eye(3).ravel()
    return messages


def zero_joint_states_interleaved(messages: list[Message]) -> list[Message]:
    """automaticaddison/yahboom_rosmaster#4: a second node publishes /joint_states too, all zeros at the same stamps,
    so every other joint state reads 0."""
    out: list[Message] = []
    for topic, msgtype, t, msg in messages:
        out.append((topic, msgtype, t, msg))
        if topic == JOINTS:
            zero = FACTORY.store.deserialize_cdr(FACTORY.serialize(msg, msgtype), msgtype)
            zero.position = np.zeros_like(np.asarray(msg.position, float))
            out.append((topic, msgtype, t + 1_000, zero))
    return out


def frames_repeated(messages: list[Message]) -> list[Message]:
    """huggingface/lerobot#4099: the recorder wrote the same cached camera frame three times per real frame, each
    copy with its own new stamp (colour and depth)."""
    for topic in (IMAGE, DEPTH):
        frames = sorted(_of(messages, (topic,)), key=stamp_ns)
        for k, msg in enumerate(frames):
            msg.data = frames[k - k % 3].data.copy()
    return messages


def out_of_focus(messages: list[Message]) -> list[Message]:
    """huggingface/blog#2839 ("sharp focus"): the colour camera out of focus, a Gaussian blur of 2 px."""
    for msg in _of(messages, (IMAGE,)):
        msg.data = np.ascontiguousarray(cv2.GaussianBlur(_pixels(msg), (0, 0), 2.0)).ravel()
    return messages


def shaking_camera(messages: list[Message]) -> list[Message]:
    """huggingface/blog#2839 ("steady video capture, no shaking"): the camera shakes on its mount, each frame up to
    4 px off in x and y, colour and depth together, the extrinsics unchanged."""
    rng = np.random.default_rng(5)
    colour = sorted(_of(messages, (IMAGE,)), key=stamp_ns)
    depth = sorted(_of(messages, (DEPTH,)), key=stamp_ns)
    for c, d in zip(colour, depth, strict=False):
        dx, dy = rng.integers(-4, 5, 2)
        c.data = np.ascontiguousarray(np.roll(_pixels(c), (dy, dx), axis=(0, 1))).ravel()
        _set_depth(d, np.roll(_depth(d), (dy, dx), axis=(0, 1)))
    return messages


def _camera_transforms(messages: list[Message]) -> list:
    return [tr for msg in _of(messages, (TF_STATIC,)) for tr in msg.transforms if tr.child_frame_id == CAMERA_FRAME]


def extrinsics_quaternion_wxyz(messages: list[Message]) -> list[Message]:
    """isri-aist/RoboManipBaselines#11: the camera's rotation written in (w, x, y, z) order into the (x, y, z, w)
    fields."""
    for tr in _camera_transforms(messages):
        q = tr.transform.rotation
        q.x, q.y, q.z, q.w = q.w, q.x, q.y, q.z
    return messages


def extrinsics_in_millimetres(messages: list[Message]) -> list[Message]:
    """DurrLab/C3VD#6: the camera's pose translation in millimetres."""
    for tr in _camera_transforms(messages):
        t = tr.transform.translation
        t.x, t.y, t.z = 1000 * t.x, 1000 * t.y, 1000 * t.z
    return messages


def _rotate(q: object, v: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat([q.x, q.y, q.z, q.w]).apply(v)


def tcp_of_another_frame(messages: list[Message]) -> list[Message]:
    """XenseRobotics-AI/xense-taccap-lerobot#8: the end effector's pose is another frame's (a tracker mounted on the
    tool), a fixed 15 cm along the tool's z axis from the real one."""
    for msg in _of(messages, (TF,)):
        for tr in msg.transforms:
            if tr.child_frame_id == EE_FRAME:
                t = tr.transform.translation
                t.x, t.y, t.z = np.array([t.x, t.y, t.z]) + _rotate(tr.transform.rotation, np.array([0, 0, 0.15]))
    return messages


def depth_holes(messages: list[Message]) -> list[Message]:
    """realsenseai/librealsense#2880 and #4320: depth reads 0 over a reflective region (here the middle 40 % x 40 % of
    every depth image)."""
    for msg in _of(messages, (DEPTH,)):
        a = _depth(msg)
        h, w = a.shape
        a[int(0.3 * h):int(0.7 * h), int(0.3 * w):int(0.7 * w)] = 0.0
        _set_depth(msg, a)
    return messages


def tf_static_missing(messages: list[Message]) -> list[Message]:
    """ros2/rosbag2#1302: /tf_static not recorded (a recorder started paused misses the latched message): no camera
    extrinsics in the bag."""
    return [m for m in messages if m[0] != TF_STATIC]


def stamped_faster_than_recorded(messages: list[Message]) -> list[Message]:
    """huggingface/lerobot#2786: the loop ran at half the rate it stamps, so the recording's clock runs twice as fast
    as the world's: every stamp and log time halved from the start."""
    t0 = min(m[2] for m in messages)
    s0 = min(stamp_ns(m[3]) for m in messages if m[0] in (IMAGE, TF, JOINTS))
    out = []
    for topic, msgtype, t, msg in messages:
        if hasattr(msg, "header") or getattr(msg, "transforms", None):
            _set_stamp(msg, s0 + (stamp_ns(msg) - s0) // 2 if stamp_ns(msg) >= s0 else stamp_ns(msg))
        out.append((topic, msgtype, t0 + (t - t0) // 2, msg))
    return out


def tcp_of_another_episode(messages: list[Message], donor: list[Message]) -> list[Message]:
    """vikashplus/robohive#71: the end effector's pose is the same in every episode of a session: this episode's
    /tf carries another episode's path (resampled to its length), its images and joints its own."""
    def ee(ms: list[Message]) -> list:
        return [tr for msg in _of(ms, (TF,)) for tr in msg.transforms if tr.child_frame_id == EE_FRAME]

    mine, theirs = ee(messages), ee(donor)
    idx = np.linspace(0, len(theirs) - 1, len(mine)).round().astype(int)
    for tr, k in zip(mine, idx, strict=True):
        tr.transform.translation, tr.transform.rotation = theirs[k].transform.translation, theirs[k].transform.rotation
    return messages


Edit = Callable[[list[Message]], list[Message]]
DEFECTS_HELDOUT: dict[str, tuple[Edit, str]] = {  # defect -> (edit, "*": any finding no clean episode has)
    "image stamps 0": (image_stamps_zero, "*"),
    "camera's own clock": (camera_own_clock, "*"),
    "K identity": (identity_intrinsics, "*"),
    "zero joint states interleaved": (zero_joint_states_interleaved, "*"),
    "each frame written 3 times": (frames_repeated, "*"),
    "out of focus": (out_of_focus, "*"),
    "shaking camera": (shaking_camera, "*"),
    "extrinsics quaternion wxyz": (extrinsics_quaternion_wxyz, "*"),
    "extrinsics in mm": (extrinsics_in_millimetres, "*"),
    "tcp of another frame (15 cm)": (tcp_of_another_frame, "*"),
    "tcp of another episode": (tcp_of_another_episode, "*"),  # planted with a donor episode of the same task
    "depth holes": (depth_holes, "*"),
    "tf_static missing": (tf_static_missing, "*"),
    "stamped 2x faster than recorded": (stamped_faster_than_recorded, "*"),
}
NEEDS_DONOR = ("tcp of another episode",)


def plant_heldout(src: Path, dst: Path, defect: str, donor: Path | None = None) -> None:
    edit = DEFECTS_HELDOUT[defect][0]
    messages = list(read(src))
    if defect in NEEDS_DONOR:
        if donor is None:
            raise ValueError(f"{defect}: needs a donor bag")
        write(dst, tcp_of_another_episode(messages, list(read(donor))))
    else:
        write(dst, edit(messages))
