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
TF = "/tf"
JOINTS = "/joint_states"
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


def plant(src: Path, dst: Path, defect: str) -> None:
    write(dst, DEFECTS[defect][0](list(read(src))))
