"""Reads what an episode needs from one bag, streaming: the first camera frame and its camera info, the depth and
affordance images nearest it, the whole tf tree over time, joint states and the task name; with a frame sink, every
camera, depth and affordance image too, handed over one at a time as its message is read.

Only messages on topics of the topic map are decoded, images only when they may be kept, so memory stays flat in
bag length. Every optional topic of the map may be absent from the bag or set to null; a message whose definition
lacks a field the ingest needs is one clear error naming the topic and the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from ..geometry.transforms import TfBuffer, pose_matrix
from ..plumbing.errors import AdlError
from .foxglove import AS_ROS
from .images import DEPTH_TYPES, as_rgb8, decode_depth, decode_image
from .reader import BagSource, TopicInfo
from .topics import TopicMap
from .video import VIDEO_TYPES, VideoDecoder, is_video

IMAGE_TYPES = {"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", *VIDEO_TYPES}
TF_TYPES = {"tf2_msgs/msg/TFMessage", "tf/msg/tfMessage"}  # tf/tfMessage: old ROS1 bags, same layout


MAX_NAMED = 8  # topics an error line names before it says how many more there are


class FrameSink(Protocol):
    """Takes every image as it is read (adlpipe.dataset.frames.FrameWriter); stamps are header stamps, s."""

    def rgb(self, t: float, image: np.ndarray, where: str) -> None: ...
    def depth(self, t: float, metres: np.ndarray) -> None: ...
    def affordance(self, t: float, image: np.ndarray) -> None: ...
    def camera(self, name: str) -> FrameSink: ...  # the sink of another camera of the episode


@dataclass
class CameraReadout:
    """What the bag says about one more camera of a multi-camera map: its first frame's size and frame id, and
    its first CameraInfo (its frames go to the sink's camera(name))."""

    name: str
    shape: tuple[int, ...] | None = None
    frame: str = ""
    t_first: float | None = None
    info: object | None = None


@dataclass
class BagReadout:
    """What one bag says about an episode, before any geometry."""

    bag: Path
    kind: str
    topics: dict[str, TopicInfo]
    image: np.ndarray
    t_img: float
    camera_frame: str
    info: object
    task: str | None
    tf: TfBuffer
    depth: tuple[float, object] | None = None  # (stamp, message) nearest the first image
    affordance: tuple[float, object] | None = None
    first_pose: dict[str, tuple[float, str, np.ndarray]] = field(default_factory=dict)  # child -> (t, parent, T)
    joint_t: list[float] = field(default_factory=list)
    joint_pos: list[np.ndarray] = field(default_factory=list)
    joint_names: list[str] = field(default_factory=list)
    read: dict[str, int] = field(default_factory=dict)
    series: dict[str, Series] = field(default_factory=dict)  # "state" / "action" -> what its topic carried
    cameras: dict[str, CameraReadout] = field(default_factory=dict)  # the map's other cameras, by name
    video_skipped: dict[str, int] = field(default_factory=dict)  # video topic -> packets before its first keyframe
    # The intervention topic's flags (log time s, value): std_msgs/Bool has no header, so the time it was logged
    intervention: list[tuple[float, bool]] = field(default_factory=list)


@dataclass
class Series:
    """A JointState topic read as a vector stream: stamps (s), one row of positions per message, their names."""

    names: list[str] = field(default_factory=list)
    t: list[float] = field(default_factory=list)
    rows: list[np.ndarray] = field(default_factory=list)
    non_finite: list[tuple[float, str]] = field(default_factory=list)  # (stamp, first such name) of dropped rows

    def add(self, msg: object, where: str) -> None:
        if not self.names:
            self.names = [check_name(str(n), "joint", where) for n in msg.name]
        pos = np.asarray(msg.position, float)
        if len(pos) != len(self.names):
            raise AdlError(f"{where}: field position has {len(pos)} values for {len(self.names)} names")
        if not np.isfinite(pos).all():  # a sensor's NaN: the message is left out, and the episode says so
            self.non_finite.append((stamp_s(msg), self.names[int(np.flatnonzero(~np.isfinite(pos))[0])]))
            return
        self.t.append(stamp_s(msg))
        self.rows.append(pos)


def stamp_s(msg: object) -> float:
    """header.stamp in seconds (ROS2 sec/nanosec, ROS1 secs/nsecs)."""
    # foxglove's CompressedVideo has a timestamp and no header; every other stamped message has a header
    st = msg.timestamp if hasattr(msg, "timestamp") and not hasattr(msg, "header") else msg.header.stamp
    sec = getattr(st, "sec", None)
    if sec is None:
        sec = st.secs
    nsec = getattr(st, "nanosec", None)
    if nsec is None:
        nsec = st.nsecs
    return int(sec) + int(nsec) * 1e-9


def frame_id(msg: object) -> str:
    return str(msg.frame_id if hasattr(msg, "frame_id") and not hasattr(msg, "header") else msg.header.frame_id)


def stamped(msg: object, where: str) -> float:
    """An image's header.stamp in seconds; a zero stamp (a driver that never sets it) is one line: such frames
    cannot be put in time beside tf and the joints."""
    t = stamp_s(msg)
    if t == 0.0:
        raise AdlError(f"{where}: header.stamp is zero (a camera driver that never sets it): its frames cannot be "
                       "aligned with tf and the joints; set the stamps in the driver, or restamp the bag from its "
                       "log times before ingest")
    return t


def check_name(name: str, what: str, where: str) -> str:
    """Frame, joint and object names end up as HDF5 strings: no control characters (NUL among them)."""
    if any(ord(c) < 32 for c in name) or len(name) > 256:
        raise AdlError(f"{where}: {what} {name[:40]!r} has control characters or is too long")
    return name


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


def check_types(bag: Path, topics: dict, tm: TopicMap) -> None:
    want = {tm.image: IMAGE_TYPES, tm.camera_info: {"sensor_msgs/msg/CameraInfo"},
            **{c.image: IMAGE_TYPES for c in tm.extra_cameras},
            **{c.camera_info: {"sensor_msgs/msg/CameraInfo"} for c in tm.extra_cameras},
            **{c.depth: DEPTH_TYPES for c in tm.extra_cameras if c.depth},
            tm.tf: TF_TYPES, tm.tf_static: TF_TYPES,
            tm.depth: DEPTH_TYPES, tm.affordance: {"sensor_msgs/msg/Image"},
            tm.joints: {"sensor_msgs/msg/JointState"}, tm.task: {"std_msgs/msg/String"},
            tm.state: {"sensor_msgs/msg/JointState"}, tm.action: {"sensor_msgs/msg/JointState"},
            tm.reference: {"sensor_msgs/msg/JointState"}, tm.intervention: {"std_msgs/msg/Bool"},
            tm.expert_phase: {"sensor_msgs/msg/JointState"}}
    for topic, types in want.items():
        if topic and topic in topics and AS_ROS.get(topics[topic].msgtype, topics[topic].msgtype) not in types | {"?"}:
            expected = " or ".join(sorted(types))
            raise AdlError(f"{bag}: topic {topic} has type {topics[topic].msgtype}, expected {expected}")


def check_counts(bag: Path, topics: dict, read: dict[str, int]) -> None:
    """Compare messages read with the bag's own counts: a reader that silently yields nothing (e.g. a rosbag2
    QoS mismatch) must not pass as an empty topic."""
    for topic, n in read.items():
        declared = topics[topic].declared
        if declared is not None and n != declared:
            raise AdlError(f"{bag}: read {n} of the {declared} messages the bag declares on {topic}")


TF_LEAD_NS = 1_000_000_000  # tf before a segment's start: the poses the first image's lookups need


def read_bag(src: BagSource, tm: TopicMap, window: tuple[int, int] | None = None,
             sink: FrameSink | None = None) -> BagReadout:
    """Stream the topics of the map once and keep what an episode needs; with a window (log time, ns), only what
    lies in it (one demonstration of several in the bag): static tf and the task name are kept from anywhere."""
    bag = src.path
    topics = src.topics()
    missing = [t for t in tm.required_topics() if t not in topics]
    if missing:
        named = [f"{t} ({i.msgtype})" for t, i in sorted(topics.items())[:MAX_NAMED]]
        more = len(topics) - len(named)
        have = (", ".join(named) + (f" and {more} more (ingest --list names them all)" if more else "")
                if topics else "no topics")
        raise AdlError(f"{bag}: missing required topic(s) {', '.join(missing)}; the bag has: {have}")
    check_types(bag, topics, tm)
    wanted = [t for t in tm.required_topics() + tm.optional_topics() if t in topics]
    state = _Streams(bag, tm, sink)
    read = dict.fromkeys(wanted, 0)
    lo, hi = window or (None, None)
    for topic, log_ns, decode in src.messages(wanted):
        read[topic] += 1
        if window and topic not in (tm.tf_static, tm.task):
            if log_ns > hi or log_ns < lo - (TF_LEAD_NS if topic == tm.tf else 0):
                continue
        try:
            if topic == tm.intervention:
                state.intervention.append((log_ns / 1e9, bool(decode().data)))
                continue
            state.take(topic, decode)
        except (AttributeError, TypeError, ValueError, IndexError) as exc:
            raise AdlError(f"{bag}: topic {topic}: message lacks a field or holds a bad value "
                           f"({type(exc).__name__}: {' '.join(str(exc).split())[:120]})") from None
    if state.image is None or state.t_img is None:
        span = f" in the segment {lo / 1e9:.3f}-{hi / 1e9:.3f} s (log time)" if window else ""
        raise AdlError(f"{bag}: no message could be read on the image topic {tm.image}{span}")
    if state.info is None:
        raise AdlError(f"{bag}: no message on the camera-info topic {tm.camera_info}")
    for c in tm.extra_cameras:
        cam = state.cameras[c.name]
        if cam.shape is None:
            raise AdlError(f"{bag}: no message could be read on camera {c.name}'s image topic {c.image}")
        if cam.info is None:
            raise AdlError(f"{bag}: no message on camera {c.name}'s camera-info topic {c.camera_info}")
    return BagReadout(
        bag=bag, kind=src.kind, topics=topics, image=state.image, t_img=state.t_img,
        camera_frame=state.camera_frame, info=state.info, task=state.task, tf=state.tf,
        depth=state.depth.finish(state.t_img) if tm.depth in topics else None,
        affordance=state.aff.finish(state.t_img) if tm.affordance in topics else None,
        first_pose=state.first_pose, joint_t=state.joint_t, joint_pos=state.joint_pos,
        joint_names=state.joint_names, read=read, series=state.series, cameras=state.cameras,
        video_skipped={t: d.skipped for t, d in state.video.items() if d.skipped},
        intervention=state.intervention)


class _Streams:
    """The state of one pass over a bag's messages."""

    def __init__(self, bag: Path, tm: TopicMap, sink: FrameSink | None = None) -> None:
        self.bag, self.tm, self.sink = bag, tm, sink
        self.image: np.ndarray | None = None
        self.t_img: float | None = None
        self.camera_frame = ""
        self.info: object | None = None
        self.task: str | None = None
        self.depth, self.aff = _Nearest(), _Nearest()
        self.settled: set[str] = set()  # depth/affordance topics whose stamps have passed the first image
        self.tf = TfBuffer()
        self.first_pose: dict[str, tuple[float, str, np.ndarray]] = {}
        self.joint_t: list[float] = []
        self.joint_pos: list[np.ndarray] = []
        self.joint_names: list[str] = []
        self.series: dict[str, Series] = {}
        self.intervention: list[tuple[float, bool]] = []
        self.cameras = {c.name: CameraReadout(c.name) for c in tm.extra_cameras}
        self.camera_of = {t: (c.name, role) for c in tm.extra_cameras
                          for role, t in (("image", c.image), ("info", c.camera_info), ("depth", c.depth)) if t}
        self.video: dict[str, VideoDecoder] = {}  # camera topics that carry video: their decoders

    def frames(self, topic: str, msg: object) -> list[tuple[float, np.ndarray]]:
        """(stamp, RGB image) of what one camera message completes: its image, or for a video topic the frames
        its packet decodes to (none before the first keyframe)."""
        where = self.where(topic)
        if is_video(msg):
            return self.video.setdefault(topic, VideoDecoder(where)).feed(msg, stamped(msg, where))
        return [(stamped(msg, where), as_rgb8(decode_image(msg, where), where))]

    def where(self, topic: str) -> str:
        return f"{self.bag}: topic {topic}"

    def take(self, topic: str, decode: object) -> None:
        tm = self.tm
        if topic in self.camera_of:
            self._other_camera(topic, decode)
        elif topic == tm.image:
            if self.image is None or self.sink:
                msg = decode()
                for t, image in self.frames(topic, msg):
                    if self.image is None:
                        self.image, self.t_img = image, t
                        self.camera_frame = check_name(frame_id(msg), "frame", self.where(topic))
                    elif image.shape[:2] != self.image.shape[:2]:
                        raise AdlError(f"{self.where(topic)}: image size changes from {self.image.shape[1]}x"
                                       f"{self.image.shape[0]} to {image.shape[1]}x{image.shape[0]} within the bag")
                    if self.sink:
                        self.sink.rgb(t, image, self.where(topic))
        elif topic == tm.camera_info:
            if self.info is None:
                self.info = decode()
        elif topic in (tm.depth, tm.affordance):
            if topic not in self.settled or self.sink:
                msg = decode()
                t = stamped(msg, self.where(topic))
                if topic not in self.settled:
                    (self.depth if topic == tm.depth else self.aff).offer(t, msg, self.t_img)
                    if self.t_img is not None and t > self.t_img + tm.sync_tolerance_s:
                        self.settled.add(topic)
                if self.sink:
                    self._to_sink(topic, t, msg)
        elif topic in (tm.tf, tm.tf_static):
            self._tf(decode().transforms, static=topic == tm.tf_static, where=self.where(topic))
        elif topic == tm.joints:
            msg = decode()
            pos = np.asarray(msg.position, float)
            if not self.joint_names:
                self.joint_names = [check_name(str(n), "joint", self.where(topic)) for n in msg.name]
            if len(pos) == len(self.joint_names) and len(pos):
                self.joint_t.append(stamp_s(msg))
                self.joint_pos.append(pos)
        elif topic == tm.task and self.task is None:
            self.task = str(decode().data)
        if topic in (tm.state, tm.action, tm.reference, tm.expert_phase):  # may also be the joints topic
            key = {tm.state: "state", tm.action: "action", tm.reference: "reference"}.get(topic, "expert_phase")
            self.series.setdefault(key, Series()).add(decode(), self.where(topic))

    def _other_camera(self, topic: str, decode: object) -> None:
        """A message of another camera of the map: its info, its first frame's size and frame id, and (with a
        sink) every frame and depth image, into that camera's own sink."""
        name, role = self.camera_of[topic]
        cam, where = self.cameras[name], self.where(topic)
        if role == "info":
            if cam.info is None:
                cam.info = decode()
            return
        if not self.sink and (role == "depth" or cam.shape is not None):
            return
        msg = decode()
        if role == "depth":
            self.sink.camera(name).depth(stamp_s(msg), decode_depth(msg, where))
            return
        for t, image in self.frames(topic, msg):
            if cam.shape is None:
                cam.shape, cam.t_first = image.shape, t
                cam.frame = check_name(frame_id(msg), "frame", where)
            elif image.shape[:2] != cam.shape[:2]:
                raise AdlError(f"{where}: image size changes from {cam.shape[1]}x{cam.shape[0]} to "
                               f"{image.shape[1]}x{image.shape[0]} within the bag")
            if self.sink:
                self.sink.camera(name).rgb(t, image, where)

    def _to_sink(self, topic: str, t: float, msg: object) -> None:
        where = self.where(topic)
        if topic == self.tm.depth:
            self.sink.depth(t, decode_depth(msg, where))
            return
        a = decode_image(msg, where)
        if a.ndim != 2:
            raise AdlError(f"{where}: affordance map must be single channel (32FC1)")
        self.sink.affordance(t, a)

    def _tf(self, transforms: list, static: bool, where: str) -> None:
        for tr in transforms:
            tt, rr = tr.transform.translation, tr.transform.rotation
            T = pose_matrix([tt.x, tt.y, tt.z], [rr.w, rr.x, rr.y, rr.z])
            child = check_name(str(tr.child_frame_id).lstrip("/"), "frame", where)
            parent = check_name(str(tr.header.frame_id).lstrip("/"), "frame", where)
            t = stamp_s(tr)
            self.tf.add(parent, child, t, T, static=static)
            self.first_pose.setdefault(child, (t, parent, T))
