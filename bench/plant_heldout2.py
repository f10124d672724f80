"""A second held-out set of defects for the doctor (issue E3): 14 more kinds no adlpipe issue named and no earlier set
planted, each taken from a report in a public tracker (the source beside each), planted one per bag with the real
writer (bench/plant_defects.py's reader and writer). Written after the doctor's checks of this session and committed
before its one measurement (bench/doctor_vs_peers.py --set heldout2); the checks are not changed for it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from plant_defects import (
    DEPTH,
    FACTORY,
    IMAGE,
    INFO,
    JOINTS,
    TF,
    Message,
    _depth,
    _of,
    _pixels,
    _set_depth,
    _shift,
    read,
    stamp_ns,
    write,
)
from plant_heldout import EE_FRAME, _set_stamp

ACTION = "/arm/tcp_command"  # the recorder's command: tcp x, y, z and the gripper
GRIPPER = "finger_left"


def image_upside_down(messages: list[Message]) -> list[Message]:
    """realsenseai/realsense-ros#798, librealsense#13121: the camera head mounted upside down for the cables, its
    images not rotated and the extrinsics those of the upright calibration (colour and depth turned 180 degrees)."""
    for msg in _of(messages, (IMAGE,)):
        msg.data = np.ascontiguousarray(_pixels(msg)[::-1, ::-1]).ravel()
    for msg in _of(messages, (DEPTH,)):
        _set_depth(msg, _depth(msg)[::-1, ::-1])
    return messages


def depth_unregistered(messages: list[Message]) -> list[Message]:
    """ros-drivers/openni2_camera#95 ("I missed the depth registered param"): depth in the depth imager's own view,
    not registered to colour: a wider field (the image shrunk by 15 % about its middle) 4 px to the side."""
    for msg in _of(messages, (DEPTH,)):
        a = _depth(msg)
        h, w = a.shape
        yy, xx = np.mgrid[0:h, 0:w]
        sy = np.clip(np.round((yy - h / 2) / 0.85 + h / 2).astype(int), 0, h - 1)
        sx = np.clip(np.round((xx - w / 2) / 0.85 + w / 2 - 4).astype(int), 0, w - 1)
        _set_depth(msg, a[sy, sx])
    return messages


def black_frames(messages: list[Message]) -> list[Message]:
    """facebookresearch/co3d#58: pure black frames in a sequence (here five in a row, in the middle of the
    recording), the other streams as recorded."""
    frames = sorted(_of(messages, (IMAGE,)), key=stamp_ns)
    k = len(frames) // 2
    for msg in frames[k:k + 5]:
        msg.data = np.zeros_like(np.frombuffer(bytes(msg.data), np.uint8))
    return messages


def depth_in_tenth_millimetres(messages: list[Message]) -> list[Message]:
    """realsenseai/librealsense#12183, realsense-ros#277: the depth unit set to 0.1 mm on the camera and read as
    1 mm by the recorder: every depth value ten times too large (still under 20 m at a table)."""
    for msg in _of(messages, (DEPTH,)):
        _set_depth(msg, _depth(msg) * 10.0)
    return messages


def stale_joint_states(messages: list[Message]) -> list[Message]:
    """ros/ros_comm#2336: messages recorded out of order for a stretch: every other joint state carries the values of
    the one 0.5 s before it, at its own (monotonic) stamp, over the middle third of the recording."""
    joints = sorted((m for m in messages if m[0] == JOINTS), key=lambda m: stamp_ns(m[3]))
    stamps = np.array([stamp_ns(m[3]) for m in joints])
    values = [np.array(m[3].position, float) for m in joints]
    n = len(joints)
    for i in range(n // 3, 2 * n // 3, 2):
        k = max(int(np.searchsorted(stamps, stamps[i] - 500_000_000, "right")) - 1, 0)
        joints[i][3].position = values[k].copy()
    return messages


def exposure_flicker(messages: list[Message]) -> list[Message]:
    """realsenseai/librealsense#12254 (a D457's colour stream flickering, auto exposure): every other colour frame
    at 60 % of its brightness."""
    for k, msg in enumerate(sorted(_of(messages, (IMAGE,)), key=stamp_ns)):
        if k % 2:
            msg.data = np.ascontiguousarray((_pixels(msg) * 0.6).astype(np.uint8)).ravel()
    return messages


def camera_stamp_jitter(messages: list[Message]) -> list[Message]:
    """stereolabs/zed-ros-wrapper#581 (frame intervals of 18 to 47 ms at 30 fps while rosbag records on a Jetson):
    each colour image, its depth and camera_info stamped up to 40 % of the frame interval early or late."""
    rng = np.random.default_rng(29)
    frames = sorted(_of(messages, (IMAGE,)), key=stamp_ns)
    interval = int(np.median(np.diff([stamp_ns(m) for m in frames])))
    by_stamp = {}
    for msg in _of(messages, (IMAGE, DEPTH, INFO)):
        by_stamp.setdefault(stamp_ns(msg), []).append(msg)
    for t, group in by_stamp.items():
        dt = int(rng.uniform(-0.4, 0.4) * interval)
        for msg in group:
            _set_stamp(msg, t + dt)
    return messages


def image_stamps_frozen(messages: list[Message]) -> list[Message]:
    """ros-drivers/camera1394#35: the driver's image stamps stop changing: every colour image carries the first
    one's stamp (depth and camera_info as recorded)."""
    frames = list(_of(messages, (IMAGE,)))
    first = min(stamp_ns(m) for m in frames)
    for msg in frames:
        _set_stamp(msg, first)
    return messages


def gripper_in_percent(messages: list[Message]) -> list[Message]:
    """Kinovarobotics/ros2_kortex#59 (the gripper position divided by 100 where it is 0.81 at full stroke): the
    gripper joint's reading in percent of its stroke instead of its own unit."""
    for msg in _of(messages, (JOINTS,)):
        if GRIPPER in list(msg.name):
            k = list(msg.name).index(GRIPPER)
            pos = np.array(msg.position, float)
            pos[k] = pos[k] * 100.0
            msg.position = pos
    return messages


def gripper_command_out_of_range(messages: list[Message]) -> list[Message]:
    """OpenHelix-Team/RoboMemArena#19 (gripper actions of 2.0 in one task where every other lies in [-1, 1]): the
    command's gripper value doubled over the middle third of the recording."""
    acts = sorted((m for m in messages if m[0] == ACTION), key=lambda m: stamp_ns(m[3]))
    n = len(acts)
    for m in acts[n // 3:2 * n // 3]:
        pos = np.array(m[3].position, float)
        pos[-1] = 2.0 * pos[-1]
        m[3].position = pos
    return messages


def intrinsics_of_infrared(messages: list[Message]) -> list[Message]:
    """realsenseai/librealsense#11212 (the depth imager's intrinsics used for the colour stream): camera_info's focal
    lengths those of a wider imager, 0.8 of the colour camera's, the principal point kept."""
    for msg in _of(messages, (INFO,)):
        k = np.array(msg.k, float).reshape(3, 3)
        k[0, 0] *= 0.8
        k[1, 1] *= 0.8
        msg.k = k.ravel()
    return messages


def two_rollouts_in_one(messages: list[Message], donor: list[Message]) -> list[Message]:
    """strands-labs/robots#666 (no episode boundary between rollouts: twenty rollouts saved as one episode): another
    rollout of the task recorded straight after this one, in the same episode (its messages shifted to start 0.5 s
    after this one's last; its task and static transforms not repeated)."""
    end = max(m[2] for m in messages)
    start = min(m[2] for m in donor)
    dt = end - start + 500_000_000
    once = {m[0] for m in messages if m[0] not in (IMAGE, DEPTH, INFO, TF, JOINTS, ACTION)}
    out = list(messages)
    for topic, msgtype, t, msg in donor:
        if topic in once:
            continue
        copy = FACTORY.store.deserialize_cdr(FACTORY.serialize(msg, msgtype), msgtype)
        _shift(copy, dt)
        out.append((topic, msgtype, t + dt, copy))
    return out


def starts_at_previous_pose(messages: list[Message], donor: list[Message]) -> list[Message]:
    """strands-labs/robots#2334 (rollouts recorded without a reset: each begins at the previous one's terminal pose):
    for this episode's first second the end effector and the joints read another episode's last pose, then its
    own (the arm reset while the recorder already ran)."""
    def last(ms: list[Message], topic: str) -> Message:
        return max((m for m in ms if m[0] == topic), key=lambda m: stamp_ns(m[3]))

    t0 = min(stamp_ns(m[3]) for m in messages if m[0] in (TF, JOINTS))
    end_tf = [tr for tr in last(donor, TF)[3].transforms if tr.child_frame_id == EE_FRAME]
    end_joints = np.array(last(donor, JOINTS)[3].position, float)
    for topic, _, _, msg in messages:
        if topic not in (TF, JOINTS) or stamp_ns(msg) > t0 + 1_000_000_000:
            continue
        if topic == JOINTS and len(msg.position) == len(end_joints):
            msg.position = end_joints.copy()
        for tr in getattr(msg, "transforms", []):
            if tr.child_frame_id == EE_FRAME and end_tf:
                tr.transform.translation = end_tf[0].transform.translation
                tr.transform.rotation = end_tf[0].transform.rotation
    return messages


def first_frame_of_previous(messages: list[Message], donor: list[Message]) -> list[Message]:
    """isaac-sim/IsaacLab-Arena#382: the camera buffer still held the previous episode's last rendered frame when the
    new episode's first observation was saved: this episode's first colour frame is another episode's last."""
    first = min(_of(messages, (IMAGE,)), key=stamp_ns)
    first.data = max(_of(donor, (IMAGE,)), key=stamp_ns).data
    return messages


Edit = Callable[[list[Message]], list[Message]]
DonorEdit = Callable[[list[Message], list[Message]], list[Message]]
DEFECTS_HELDOUT2: dict[str, tuple[Edit | DonorEdit, str]] = {  # defect -> (edit, "*": any finding)
    "image upside down": (image_upside_down, "*"),
    "depth not registered": (depth_unregistered, "*"),
    "five black frames": (black_frames, "*"),
    "depth in 0.1 mm": (depth_in_tenth_millimetres, "*"),
    "stale joint states interleaved": (stale_joint_states, "*"),
    "exposure flicker": (exposure_flicker, "*"),
    "camera stamp jitter": (camera_stamp_jitter, "*"),
    "image stamps frozen": (image_stamps_frozen, "*"),
    "gripper in percent": (gripper_in_percent, "*"),
    "gripper command out of range": (gripper_command_out_of_range, "*"),
    "K of the infrared imager": (intrinsics_of_infrared, "*"),
    "two rollouts in one episode": (two_rollouts_in_one, "*"),  # these three with a donor episode of the same task
    "starts at the previous pose": (starts_at_previous_pose, "*"),
    "first frame of the previous episode": (first_frame_of_previous, "*"),
}
NEEDS_DONOR2 = ("two rollouts in one episode", "starts at the previous pose", "first frame of the previous episode")


def plant_heldout2(src: Path, dst: Path, defect: str, donor: Path | None = None) -> None:
    edit = DEFECTS_HELDOUT2[defect][0]
    messages = list(read(src))
    if defect in NEEDS_DONOR2:
        if donor is None:
            raise ValueError(f"{defect}: needs a donor bag")
        write(dst, edit(messages, list(read(donor))))  # type: ignore[call-arg]
    else:
        write(dst, edit(messages))  # type: ignore[call-arg]
