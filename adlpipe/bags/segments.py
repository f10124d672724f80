"""Many demonstrations in one bag: where each episode starts and ends, in the bag's log time.

Three ways, in this order of precedence:
  - a sidecar YAML beside the bag (<bag>.segments.yaml, or --segments FILE): `segments: [[t0, t1], ...]`,
    seconds from the bag's first message;
  - a marker topic (topic map `segment_topic`): std_msgs/String "start" / "stop", or std_msgs/Bool true / false;
  - motion (topic map `segment_idle_s` set): the end effector (and, if `segment_gripper_joint` names one, the
    gripper joint) idle for at least segment_idle_s separates demonstrations; idle means slower than
    segment_speed_mps (and the gripper joint slower than segment_gripper_rate per second). Segments shorter than
    segment_min_s are dropped.
A bag with none of these is one episode.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry.transforms import TfBuffer, pose_matrix
from ..plumbing.errors import AdlError, read_small_yaml
from .episode_reader import stamp_s
from .reader import BagSource
from .topics import TopicMap

Window = tuple[int, int]  # log time, ns, inclusive


def sidecar_path(bag: Path) -> Path:
    return bag.with_name(bag.name + ".segments.yaml")


def find_segments(bag: Path, tm: TopicMap, sidecar: Path | None = None) -> list[Window] | None:
    """The episodes' windows, or None if the bag is one episode."""
    sidecar = sidecar or (sidecar_path(bag) if sidecar_path(bag).exists() else None)
    src = BagSource(bag)
    if sidecar is not None:
        return _from_sidecar(src, sidecar)
    if tm.segment_topic:
        if tm.segment_topic not in src.topics():
            raise AdlError(f"{bag}: segment_topic {tm.segment_topic} is not in the bag")
        return _from_markers(src, tm.segment_topic)
    if tm.segment_idle_s is not None:
        return _from_motion(src, tm)
    return None


def _first_log_ns(src: BagSource) -> int:
    for _topic, log_ns, _decode in src.messages(list(src.topics())):
        return log_ns
    raise AdlError(f"{src.path}: the bag has no messages")


def _from_sidecar(src: BagSource, path: Path) -> list[Window]:
    raw = read_small_yaml(path, "segments file") or {}
    try:
        pairs = [(float(a), float(b)) for a, b in raw["segments"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise AdlError(f"{path}: not a segments file (want `segments: [[t0, t1], ...]` in seconds from the bag's "
                       f"first message; {type(exc).__name__})") from None
    if not pairs or any(not (0 <= a < b) for a, b in pairs):
        raise AdlError(f"{path}: each segment needs 0 <= t0 < t1 (seconds from the bag's first message)")
    t0 = _first_log_ns(src)
    return [(t0 + int(a * 1e9), t0 + int(b * 1e9)) for a, b in sorted(pairs)]


def _from_markers(src: BagSource, topic: str) -> list[Window]:
    out: list[Window] = []
    start: int | None = None
    for _t, log_ns, decode in src.messages([topic]):
        value = decode().data
        on = value if isinstance(value, bool | np.bool_) else str(value).strip().lower() in ("start", "begin", "1",
                                                                                              "true")
        off = (not value) if isinstance(value, bool | np.bool_) else str(value).strip().lower() in (
            "stop", "end", "0", "false")
        if on and start is None:
            start = log_ns
        elif off and start is not None:
            out.append((start, log_ns))
            start = None
    if start is not None:
        raise AdlError(f"{src.path}: topic {topic}: a 'start' marker without its 'stop'")
    if not out:
        raise AdlError(f"{src.path}: topic {topic}: no start/stop marker pairs")
    return out


def _from_motion(src: BagSource, tm: TopicMap) -> list[Window]:
    """Active stretches between idle ones, from the end-effector tf (and the gripper joint)."""
    tf = TfBuffer()
    offsets: list[float] = []
    grip_t: list[float] = []
    grip_q: list[float] = []
    topics = [t for t in (tm.tf, tm.tf_static) if t]
    if tm.segment_gripper_joint and tm.joints:
        topics.append(tm.joints)
    for topic, log_ns, decode in src.messages([t for t in topics if t in src.topics()]):
        msg = decode()
        if topic == tm.joints:
            names = [str(n) for n in msg.name]
            if tm.segment_gripper_joint in names:
                grip_t.append(stamp_s(msg))
                grip_q.append(float(msg.position[names.index(tm.segment_gripper_joint)]))
            continue
        for tr in msg.transforms:
            tt, rr = tr.transform.translation, tr.transform.rotation
            tf.add(str(tr.header.frame_id).lstrip("/"), str(tr.child_frame_id).lstrip("/"), stamp_s(tr),
                   pose_matrix([tt.x, tt.y, tt.z], [rr.w, rr.x, rr.y, rr.z]), static=topic == tm.tf_static)
            if topic == tm.tf:
                offsets.append(log_ns * 1e-9 - stamp_s(tr))
    moving = tf.motion_times(tm.ee_frame, tm.base_frame)
    if moving is None:
        raise AdlError(f"{src.path}: motion segmentation needs a moving end-effector frame {tm.ee_frame!r}")
    t = np.asarray(moving[1])
    p = np.array([tf.lookup(tm.base_frame, tm.ee_frame, ti)[:3, 3] for ti in t])
    speed = np.r_[np.linalg.norm(np.diff(p, axis=0), axis=1) / np.maximum(np.diff(t), 1e-9), 0.0]
    idle = speed < tm.segment_speed_mps
    if grip_t:
        rate = np.abs(np.gradient(np.asarray(grip_q), np.asarray(grip_t)))
        idle &= np.interp(t, grip_t, rate) < tm.segment_gripper_rate
    windows = _active_runs(t, idle, tm.segment_idle_s, tm.segment_min_s)
    if not windows:
        raise AdlError(f"{src.path}: motion segmentation found no demonstration (no motion faster than "
                       f"{tm.segment_speed_mps} m/s for {tm.segment_min_s} s)")
    off = float(np.median(offsets)) if offsets else 0.0
    return [(int(round((a + off) * 1e9)), int(round((b + off) * 1e9))) for a, b in windows]


def _active_runs(t: np.ndarray, idle: np.ndarray, idle_s: float, min_s: float) -> list[tuple[float, float]]:
    """Split where the robot idles for at least idle_s; keep active stretches of at least min_s (stamps, s)."""
    breaks: list[tuple[float, float]] = []  # long idle stretches
    i = 0
    while i < len(t):
        if idle[i]:
            j = i
            while j + 1 < len(t) and idle[j + 1]:
                j += 1
            if t[j] - t[i] >= idle_s:
                breaks.append((t[i], t[j]))
            i = j + 1
        else:
            i += 1
    edges = [t[0], *[x for b in breaks for x in b], t[-1]]
    runs = [(edges[k], edges[k + 1]) for k in range(0, len(edges) - 1, 2)]
    return [(a, b) for a, b in runs if b - a >= min_s]
