"""Defects planted in recorded bags, one per bag, rewritten message by message with the real writer (issue E.3).

Each defect reads a clean MCAP (mcap's reader, rosbags' CDR decoder), changes what a faulty sensor or driver would
(a frozen or dropped camera, a tf or joint sample off, a NaN, an idle start, the same demonstration saved twice) and
writes a new bag with adlpipe's BagWriter (mcap's writer), so the defect is in the bytes a lab would record.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from adlpipe.bags.messages import MessageFactory
from adlpipe.bags.writer import BagWriter

IMAGE = "/camera/color/image_raw"  # the recorder's topics
INFO = "/camera/color/camera_info"
DEPTH = "/camera/depth/image_raw"
TF = "/tf"
TF_STATIC = "/tf_static"
JOINTS = "/joint_states"
TASK = "/adl/task"
AFFORDANCE = "/adl/affordance"
CAMERA_FRAME = "camera_color_optical_frame"
GRIPPER = "finger_left"
SPIKE_RAD = 1.0  # a joint sample this far off (an encoder glitch)
GLITCH_M = 0.3  # a tf sample this far off (a bad transform)
WINDOW_S = 1.0  # frozen and dropped camera stretches
IDLE_S = 2.0  # still time put before the demonstration
COPY_SHIFT_S = 3600.0  # the same demonstration saved again an hour later

FACTORY = MessageFactory(2)

Message = tuple[str, str, int, object]  # topic, type, log time (ns), decoded message
Edit = Callable[[list[Message]], list[Message]]


def read(bag: Path) -> Iterator[Message]:
    with open(bag, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            yield channel.topic, schema.name, message.log_time, FACTORY.store.deserialize_cdr(message.data, schema.name)


def write(bag: Path, messages: list[Message]) -> None:
    w = BagWriter(bag, "mcap")
    for topic, msgtype, t_ns, msg in sorted(messages, key=lambda m: m[2]):
        w.write(topic, msgtype, t_ns, msg)
    w.close()


def stamp_ns(msg: object) -> int:
    header = msg.header if hasattr(msg, "header") else msg.transforms[0].header
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _shift(msg: object, dt_ns: int) -> None:
    headers = [msg.header] if hasattr(msg, "header") else [tr.header for tr in getattr(msg, "transforms", [])]
    for h in headers:
        t = h.stamp.sec * 1_000_000_000 + h.stamp.nanosec + dt_ns
        h.stamp.sec, h.stamp.nanosec = t // 1_000_000_000, t % 1_000_000_000


def _middle(messages: list[Message], topic: str, key: Callable[[int], float] = lambda t: 0.0) -> int:
    """The index of the topic's message in the middle third of the recording that minimises key(its stamp), among
    the messages of the topic's most frequent kind (on /tf: the arm's)."""
    kinds = Counter(_kind(m[0], m[3]) for m in messages if m[0] == topic)
    arm = kinds.most_common(1)[0][0]
    idx = [i for i, m in enumerate(messages) if m[0] == topic and _kind(m[0], m[3]) == arm]
    mid = idx[len(idx) // 3: 2 * len(idx) // 3]
    return min(mid, key=lambda i: key(stamp_ns(messages[i][3])))


def _image_stamps(messages: list[Message]) -> np.ndarray:
    return np.array(sorted(stamp_ns(m[3]) for m in messages if m[0] == IMAGE))


def _image_window(messages: list[Message]) -> tuple[int, int]:
    stamps = _image_stamps(messages)
    t0 = int(stamps[len(stamps) // 3])
    return t0, t0 + int(WINDOW_S * 1e9)


def frozen_camera(messages: list[Message]) -> list[Message]:
    t0, t1 = _image_window(messages)
    held = None
    for _, _, _, msg in (m for m in messages if m[0] == IMAGE and t0 <= stamp_ns(m[3]) <= t1):
        held = msg.data if held is None else held
        msg.data = held.copy()
    return messages


def camera_dropout(messages: list[Message]) -> list[Message]:
    t0, t1 = _image_window(messages)
    return [m for m in messages if not (m[0] == IMAGE and t0 < stamp_ns(m[3]) < t1)]


def _tf_glitch(messages: list[Message], on_frame: bool) -> list[Message]:
    stamps = _image_stamps(messages)

    def to_frame(t: int) -> float:  # on a frame: the nearest; between frames: the farthest from any
        gap = float(np.abs(stamps - t).min())
        return gap if on_frame else -gap

    msg = messages[_middle(messages, TF, to_frame)][3]
    for tr in msg.transforms:
        tr.transform.translation.z += GLITCH_M
    return messages


def tf_glitch_between_frames(messages: list[Message]) -> list[Message]:
    return _tf_glitch(messages, on_frame=False)


def tf_glitch_on_frame(messages: list[Message]) -> list[Message]:
    return _tf_glitch(messages, on_frame=True)


def joint_spike(messages: list[Message]) -> list[Message]:
    msg = messages[_middle(messages, JOINTS)][3]
    msg.position = msg.position.copy()
    msg.position[1] += SPIKE_RAD
    return messages


def joint_nan(messages: list[Message]) -> list[Message]:
    msg = messages[_middle(messages, JOINTS)][3]
    msg.position = msg.position.copy()
    msg.position[1] = np.nan
    return messages


def _kind(topic: str, msg: object) -> tuple:
    """A topic's messages of one kind: tf messages by the frames they carry (the arm's at its rate, others at
    theirs)."""
    return (topic, *(tr.child_frame_id for tr in getattr(msg, "transforms", [])))


def idle_start(messages: list[Message]) -> list[Message]:
    """IDLE_S of a still arm before the demonstration: the first message of every periodic kind repeated at its
    rate (camera images with a sensor's noise of +-2 grey levels) and the rest of it later by IDLE_S; what is sent
    once (the task, the affordance map, the static transforms) stays at the start."""
    rng = np.random.default_rng(0)
    dt = int(IDLE_S * 1e9)
    times: dict[tuple, list[int]] = defaultdict(list)
    for topic, _, t, msg in messages:
        times[_kind(topic, msg)].append(t)
    rate = {kind: int(np.median(np.diff(ts))) for kind, ts in times.items() if len(ts) > 1 and ts[-1] > ts[0]}
    out, seen = [], set()
    for topic, msgtype, t, msg in messages:
        kind = _kind(topic, msg)
        if kind in rate and kind not in seen:
            seen.add(kind)
            for k in range(dt // rate[kind]):
                copy = FACTORY.store.deserialize_cdr(FACTORY.serialize(msg, msgtype), msgtype)
                _shift(copy, k * rate[kind])
                if topic == IMAGE:
                    noise = rng.integers(-2, 3, copy.data.shape)
                    copy.data = np.clip(copy.data.astype(int) + noise, 0, 255).astype(np.uint8)
                out.append((topic, msgtype, t + k * rate[kind], copy))
        if kind not in rate:
            out.append((topic, msgtype, t, msg))
            continue
        _shift(msg, dt)
        out.append((topic, msgtype, t + dt, msg))
    return out


def saved_again(messages: list[Message]) -> list[Message]:
    dt = int(COPY_SHIFT_S * 1e9)
    for _, _, _, msg in messages:
        _shift(msg, dt)
    return [(topic, msgtype, t + dt, msg) for topic, msgtype, t, msg in messages]


DEFECTS: dict[str, tuple[Edit, str]] = {  # defect -> (edit, the doctor's flag that names it)
    "frozen camera": (frozen_camera, "frozen camera"),
    "tf glitch between frames": (tf_glitch_between_frames, "tf glitch"),
    "tf glitch on a frame": (tf_glitch_on_frame, "tf glitch"),
    "idle start": (idle_start, "idle start"),
    "camera dropout": (camera_dropout, "frame gap"),
    "joint-value spike": (joint_spike, "joint spike"),
    "joint NaN": (joint_nan, "non-finite values"),
    "near-duplicate episode": (saved_again, "near duplicate"),
}


# The second set (issue E2): what a lab gets wrong once and loses weeks to; each edit is what the faulty driver,
# calibration or script would have written.
CLOCK_S = 0.2  # the camera's clock this far behind the robot's
BUMP_M, BUMP_DEG = 0.05, 5.0  # the camera moved after calibration: its recorded pose is this far off
DARK = 0.25  # an exposure this share of the usual
NOISE_M = 2e-4  # a recording saved twice, its tf with sensor noise of this size


def _of(messages: list[Message], topics: tuple[str, ...] = (IMAGE,)) -> Iterator[object]:
    return (m[3] for m in messages if m[0] in topics)


def camera_clock_behind(messages: list[Message]) -> list[Message]:
    """The camera's stamps CLOCK_S behind the robot's (an unsynchronised camera PC): images, depth and camera_info;
    the camera started CLOCK_S after the robot's streams (its first frames stamped before them are not there)."""
    for msg in _of(messages, (IMAGE, DEPTH, INFO)):
        _shift(msg, -int(CLOCK_S * 1e9))
    first_tf = min(stamp_ns(m[3]) for m in messages if m[0] == TF)
    return [m for m in messages if m[0] not in (IMAGE, DEPTH, INFO) or stamp_ns(m[3]) >= first_tf]


def wrong_intrinsics(messages: list[Message]) -> list[Message]:
    """camera_info's K of the 640x480 calibration on the smaller stream (width and height say the stream's)."""
    for msg in _of(messages, (INFO,)):
        k = np.array(msg.k, float).reshape(3, 3)
        scale = 640.0 / msg.width
        msg.k = np.array([k[0, 0] * scale, 0, 319.5, 0, k[1, 1] * scale, 239.5, 0, 0, 1], float)
    return messages


def stale_extrinsics(messages: list[Message]) -> list[Message]:
    """The camera was bumped after calibration: the static transform says where it was (BUMP_M, BUMP_DEG off)."""
    half = np.radians(BUMP_DEG) / 2
    for msg in _of(messages, (TF_STATIC,)):
        for tr in msg.transforms:
            if tr.child_frame_id == CAMERA_FRAME:
                tr.transform.translation.x += BUMP_M
                q = tr.transform.rotation  # rotated about the world z by BUMP_DEG: q' = (cos, 0, 0, sin) * q
                c, sz = np.cos(half), np.sin(half)
                q.w, q.x, q.y, q.z = (c * q.w - sz * q.z, c * q.x - sz * q.y, c * q.y + sz * q.x, c * q.z + sz * q.w)
    return messages


def _pixels(msg: object) -> np.ndarray:
    return np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, -1)


def _depth(msg: object) -> np.ndarray:
    """A 32FC1 depth image's metres (H, W), a writable copy."""
    return np.frombuffer(bytes(msg.data), np.float32).reshape(msg.height, msg.width).copy()


def _set_depth(msg: object, a: np.ndarray) -> None:
    msg.data = np.frombuffer(np.ascontiguousarray(a, np.float32).tobytes(), np.uint8)


def bgr_as_rgb(messages: list[Message]) -> list[Message]:
    """A driver publishing BGR bytes under the rgb8 encoding."""
    for msg in _of(messages):
        msg.data = np.ascontiguousarray(_pixels(msg)[..., ::-1]).ravel()
    return messages


def dark_images(messages: list[Message]) -> list[Message]:
    """An exposure left at DARK of the usual."""
    for msg in _of(messages):
        msg.data = (_pixels(msg) * DARK).astype(np.uint8).ravel()
    return messages


def depth_in_millimetres(messages: list[Message]) -> list[Message]:
    """A 32FC1 depth topic carrying millimetres (REP 118 says metres)."""
    for msg in _of(messages, (DEPTH,)):
        d = np.frombuffer(bytes(msg.data), np.float32) * 1000.0
        msg.data = np.frombuffer(d.astype(np.float32).tobytes(), np.uint8)
    return messages


def joints_in_degrees(messages: list[Message]) -> list[Message]:
    for msg in _of(messages, (JOINTS,)):
        msg.position = np.degrees(np.asarray(msg.position, float))
    return messages


def wrong_task_label(messages: list[Message]) -> list[Message]:
    """The task string of another task (a script that kept the previous session's label)."""
    for msg in _of(messages, (TASK,)):
        msg.data = "wipe the nose" if msg.data != "wipe the nose" else "put on the hat"
    return messages


def cut_off(messages: list[Message]) -> list[Message]:
    """The recording stopped at 55 % of the demonstration, mid-motion (what is sent once is kept)."""
    stamps = _image_stamps(messages)
    end = stamps[0] + int(0.55 * (stamps[-1] - stamps[0]))
    once = {TASK, TF_STATIC, "/adl/affordance"}
    return [m for m in messages if m[0] in once or m[2] <= end]


def half_rate_camera(messages: list[Message]) -> list[Message]:
    """A camera at half its rate: every other image (with its depth and camera_info) is missing."""
    stamps = _image_stamps(messages)
    drop = set(stamps[1::2].tolist())
    return [m for m in messages if not (m[0] in (IMAGE, DEPTH, INFO) and stamp_ns(m[3]) in drop)]


def stuck_gripper(messages: list[Message]) -> list[Message]:
    """The gripper's reading stuck at its first value, with the sensor's noise on it."""
    rng = np.random.default_rng(1)
    first = None
    for msg in _of(messages, (JOINTS,)):
        names = list(msg.name)
        if GRIPPER in names:
            pos = np.asarray(msg.position, float).copy()
            k = names.index(GRIPPER)
            first = pos[k] if first is None else first
            pos[k] = first + rng.normal(0, 1e-4)
            msg.position = pos
    return messages


def time_reversed(messages: list[Message]) -> list[Message]:
    """A copy of the demonstration run backwards (a script that reversed a playback), saved an hour later."""
    times = [m[2] for m in messages]
    t0, t1 = min(times), max(times)
    dt = int(COPY_SHIFT_S * 1e9)
    once = {TASK, TF_STATIC, "/adl/affordance"}
    out = []
    for topic, msgtype, t, msg in messages:
        new = t if topic in once else t0 + (t1 - t)
        _shift(msg, new - t + dt)
        out.append((topic, msgtype, new + dt, msg))
    return out


def saved_again_with_noise(messages: list[Message]) -> list[Message]:
    """The same demonstration saved twice, its tf with NOISE_M of sensor noise (not byte-identical)."""
    rng = np.random.default_rng(2)
    for msg in _of(messages, (TF,)):
        for tr in msg.transforms:
            tr.transform.translation.x += rng.normal(0, NOISE_M)
            tr.transform.translation.y += rng.normal(0, NOISE_M)
    return saved_again(messages)


DEFECTS_E2: dict[str, tuple[Edit, str]] = {  # the second set: defect -> (edit, the doctor's flag that names it)
    "camera clock 200 ms behind": (camera_clock_behind, "camera clock"),
    "K of another resolution": (wrong_intrinsics, "camera intrinsics"),
    "stale extrinsics": (stale_extrinsics, "extrinsics"),
    "BGR as RGB": (bgr_as_rgb, "colour order"),
    "dark images": (dark_images, "dark images"),
    "depth in mm (32FC1)": (depth_in_millimetres, "depth units"),
    "joints in degrees": (joints_in_degrees, "joint units"),
    "wrong task label": (wrong_task_label, "task label"),
    "cut off mid-motion": (cut_off, "cut off"),
    "camera at half rate": (half_rate_camera, "camera rate"),
    "stuck gripper with noise": (stuck_gripper, "stuck gripper"),
    "time-reversed copy": (time_reversed, "time-reversed"),
    "near-duplicate 0.2 mm": (saved_again_with_noise, "near duplicate"),
}
def frames_swapped(messages: list[Message]) -> list[Message]:
    """Two consecutive colour frames stored in each other's place (a driver's two threads racing), halfway through
    the recording, where the arm moves: their pixels swapped, the stamps kept."""
    images = [m[3] for m in messages if m[0] == IMAGE]
    k = len(images) // 2
    images[k].data, images[k + 1].data = images[k + 1].data, images[k].data
    return messages


def nonsense_distortion(messages: list[Message]) -> list[Message]:
    """camera_info's distortion set to plumb_bob with k1 = 3.0 (a calibration file of another camera, or a typo)."""
    for msg in _of(messages, (INFO,)):
        msg.distortion_model = "plumb_bob"
        msg.d = np.array([3.0, 0.0, 0.0, 0.0, 0.0])
    return messages


ACTION = "/arm/tcp_command"  # the recorder's commanded end effector (JointState positions x, y, z, ...)
LATE_S = 0.3


def command_late(messages: list[Message]) -> list[Message]:
    """The command's values LATE_S behind the arm's (a bridge that republishes a stale buffer): each command carries
    the values of the one sent LATE_S before it (the first held), at its own stamp."""
    acts = sorted((m for m in messages if m[0] == ACTION), key=lambda m: stamp_ns(m[3]))
    stamps = np.array([stamp_ns(m[3]) for m in acts])
    values = [np.array(m[3].position, float) for m in acts]
    for m, t in zip(acts, stamps, strict=True):
        k = max(int(np.searchsorted(stamps, t - int(LATE_S * 1e9), "right")) - 1, 0)
        m[3].position = values[k].copy()
    return messages


def gripper_inverted(messages: list[Message]) -> list[Message]:
    """The gripper's reading upside down (a driver's sign or offset convention: open reads closed), its range kept."""
    values = [m[3].position[list(m[3].name).index(GRIPPER)] for m in messages
              if m[0] == JOINTS and GRIPPER in list(m[3].name)]
    lo, hi = min(values), max(values)
    for msg in _of(messages, (JOINTS,)):
        if GRIPPER in list(msg.name):
            k = list(msg.name).index(GRIPPER)
            pos = np.array(msg.position, float)
            pos[k] = lo + hi - pos[k]
            msg.position = pos
    return messages


def _shift_images(messages: list[Message], topic: str, dx: int, dtype: type) -> None:
    """Every image of `topic` moved dx pixels to the right (np.roll: what leaves one side enters the other)."""
    for msg in _of(messages, (topic,)):
        a = np.frombuffer(bytes(msg.data), dtype).reshape(msg.height, msg.width, -1)
        msg.data = np.frombuffer(np.ascontiguousarray(np.roll(a, dx, axis=1)).tobytes(), np.uint8)


def depth_misregistered(messages: list[Message]) -> list[Message]:
    """The depth image 8 px to the side of the colour image (a registration left off, or another camera's depth)."""
    _shift_images(messages, DEPTH, 8, np.float32)
    return messages


def mirrored_image(messages: list[Message]) -> list[Message]:
    """The colour image mirrored left-right (a driver's flip option), the depth image and the camera model kept."""
    for msg in _of(messages):
        msg.data = np.ascontiguousarray(_pixels(msg)[:, ::-1]).ravel()
    return messages


def camera_bumped(messages: list[Message]) -> list[Message]:
    """A camera head knocked after calibration: colour and depth move by 10 and 6 px (their lenses sit apart), the
    extrinsics unchanged."""
    _shift_images(messages, IMAGE, 10, np.uint8)
    _shift_images(messages, DEPTH, 6, np.float32)
    return messages


def joint_names_swapped(messages: list[Message]) -> list[Message]:
    """Two arm joints' names swapped in every joint state (a driver's or a URDF's order), their values kept."""
    for msg in _of(messages, (JOINTS,)):
        names = list(msg.name)
        names[1], names[2] = names[2], names[1]
        msg.name = names
    return messages


def affordance_from(donor: Path) -> Edit:
    """This episode's affordance map replaced by another task's episode's (an annotation script that picked the
    wrong episode's map), the image and everything else kept."""
    maps = [m[3] for m in read(donor) if m[0] == AFFORDANCE]

    def edit(messages: list[Message]) -> list[Message]:
        for msg in _of(messages, (AFFORDANCE,)):
            msg.data = maps[0].data
        return messages
    return edit


def _needs_donor(messages: list[Message]) -> list[Message]:
    raise ValueError("this defect is planted from a donor bag: plant(src, dst, defect, donor)")


DEFECTS_E3: dict[str, tuple[Edit, str]] = {  # the kinds no issue had named, now checked: defect -> (edit, flag)
    "two frames swapped": (frames_swapped, "frame order"),
    "distortion k1 = 3": (nonsense_distortion, "camera lens"),
    "command 300 ms late": (command_late, "command timing"),
    "gripper inverted": (gripper_inverted, "gripper inverted"),
    "depth misregistered 8 px": (depth_misregistered, "depth registration"),
    "colour image mirrored": (mirrored_image, "depth registration"),
    "camera bumped 10 / 6 px": (camera_bumped, "depth registration"),
    "joint names swapped": (joint_names_swapped, "kinematics"),  # with the robot's model (doctor --robot-mjcf)
    "affordance map of another task": (_needs_donor, "affordance map"),  # its donor: another task's episode
}
OTHER_TASK_DONOR = {"affordance map of another task": affordance_from}  # defect -> its edit from the donor bag
COPIES = ("near-duplicate episode", "time-reversed copy", "near-duplicate 0.2 mm")  # planted from another bag


def plant(src: Path, dst: Path, defect: str, donor: Path | None = None) -> None:
    edits = DEFECTS | DEFECTS_E2 | DEFECTS_E3
    edit = OTHER_TASK_DONOR[defect](donor) if defect in OTHER_TASK_DONOR else edits[defect][0]
    write(dst, edit(list(read(src))))
