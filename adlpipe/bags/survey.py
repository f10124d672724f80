"""A look at a bag one has never seen: per topic its type, counts, rate, largest gap and how far header.stamp lies
from the log time (the timestamp audit to do before converting), and a topic map guessed from what is there
(`ingest --list` and `ingest --suggest-config`)."""

from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from pathlib import Path

from ..plumbing.errors import NoDecoder
from .episode_reader import stamp_s
from .reader import BagSource
from .splits import split_note

COLOR_ENCODINGS = {"rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8uc3", "8uc1"}
DEPTH_ENCODINGS = {"16uc1", "32fc1", "mono16"}
EE_WORDS = ("tool", "tcp", "end_effector", "ee", "hand", "flange", "gripper")


@dataclass
class TopicStats:
    msgtype: str
    declared: int | None
    read: int = 0
    log_times: list[float] = field(default_factory=list, repr=False)
    offsets: list[float] = field(default_factory=list, repr=False)  # log time - header.stamp, seconds
    kind: str = ""  # color / depth / other, for images
    frame_id: str = ""
    undecoded: str = ""  # why its messages were counted but not decoded (no decoder for their encoding)

    @property
    def rate_hz(self) -> float | None:
        t = self.log_times
        return (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else None

    @property
    def max_gap_s(self) -> float | None:
        t = self.log_times
        return max(b - a for a, b in zip(t[:-1], t[1:], strict=True)) if len(t) > 1 else None

    @property
    def stamp_offset_s(self) -> float | None:
        return statistics.median(self.offsets) if self.offsets else None


@dataclass
class Survey:
    bag: Path
    topics: dict[str, TopicStats]
    parent: dict[str, str]  # tf child -> parent
    moving: set[str]  # frames with changing transforms on a non-static tf topic
    static: set[str]
    parts: list[Path] = field(default_factory=list)  # a ROS1 split recording's files, read as one


def survey(bag: Path) -> Survey:
    """Read every message of the bag once (decoding them: a message that does not decode is a bad bag)."""
    src = BagSource(bag)
    info = src.topics()
    stats = {t: TopicStats(i.msgtype, i.declared) for t, i in info.items()}
    parent: dict[str, str] = {}
    moving: set[str] = set()
    static: set[str] = set()
    first_tf: dict[str, tuple] = {}
    for topic, log_ns, decode in src.messages(list(info)):
        s = stats[topic]
        s.read += 1
        s.log_times.append(log_ns * 1e-9)
        if s.undecoded:
            continue
        try:
            msg = decode()
        except NoDecoder as exc:  # a type no decoder knows is listed as such; a message that does not decode is a
            s.undecoded = f"no decoder for encoding {exc.encoding!r}"  # bad bag (its AdlError goes on)
            continue
        header = getattr(msg, "header", None)
        if header is not None and hasattr(header, "stamp"):
            s.offsets.append(log_ns * 1e-9 - stamp_s(msg))
            s.frame_id = s.frame_id or str(getattr(header, "frame_id", ""))
        if s.read == 1:
            s.kind = _image_kind(msg)
        for tr in getattr(msg, "transforms", None) or []:
            child, par = str(tr.child_frame_id).lstrip("/"), str(tr.header.frame_id).lstrip("/")
            parent[child] = par
            if tr is msg.transforms[0]:
                s.offsets.append(log_ns * 1e-9 - stamp_s(tr))
            if "static" in topic:
                static.add(child)
                continue
            t = tr.transform.translation
            key = (round(t.x, 6), round(t.y, 6), round(t.z, 6), round(tr.transform.rotation.w, 6))
            if child in first_tf and first_tf[child] != key:
                moving.add(child)
            first_tf.setdefault(child, key)
    return Survey(bag, stats, parent, moving, static, src.parts)


def _image_kind(msg: object) -> str:
    enc = str(getattr(msg, "encoding", "")).lower()
    fmt = str(getattr(msg, "format", "")).lower()
    if "compresseddepth" in fmt.replace(" ", "") or enc in DEPTH_ENCODINGS:
        return "depth"
    if enc in COLOR_ENCODINGS or fmt.split(";")[0].strip() in ("jpeg", "png", "jpg", "rgb8", "bgr8"):
        return "color"
    return ""


def list_lines(s: Survey) -> list[str]:
    """What `ingest --list` prints for one bag."""
    head = f"{s.bag}:" if len(s.parts) < 2 else f"{s.bag}: {split_note(s.parts)}:"
    out = [head, f"  {'topic':40s} {'type':34s} {'message counts':>27} {'rate Hz':>8} {'max gap s':>9} "
           f"{'stamp offset s':>14}"]
    for topic, t in sorted(s.topics.items()):
        flag = "" if t.declared in (None, t.read) else "   <-- count mismatch"
        rate = f"{t.rate_hz:.1f}" if t.rate_hz else "-"
        gap = f"{t.max_gap_s:.3f}" if t.max_gap_s is not None else "-"
        off = f"{t.stamp_offset_s:+.4f}" if t.stamp_offset_s is not None else "-"
        note = f"   (counted, not decoded: {t.undecoded})" if t.undecoded else ""
        out.append(f"  {topic:40s} {t.msgtype:34s} declared {t.declared!s:>6} read {t.read:>6} {rate:>8} {gap:>9} "
                   f"{off:>14}{flag}{note}")
    return out


def _chain(frame: str, parent: dict[str, str]) -> list[str]:
    out = [frame]
    while out[-1] in parent and len(out) < 64:
        out.append(parent[out[-1]])
    return out


def suggest_config(s: Survey) -> str:
    """A topic-map YAML guessed from the bag, with comments saying what was guessed and why."""
    by_type = lambda *types: sorted(t for t, x in s.topics.items() if x.msgtype in types)  # noqa: E731
    images = by_type("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
    # a float image named for affordances is the affordance map (its 32FC1 encoding would otherwise read as depth)
    affordance = [t for t in images if "affordance" in t.lower()]
    images = [t for t in images if t not in affordance]
    color = [t for t in images if s.topics[t].kind == "color"]
    depth = [t for t in images if s.topics[t].kind == "depth"]
    infos = by_type("sensor_msgs/msg/CameraInfo")
    lines = [f"# Topic map guessed by adlpipe.ingest --suggest-config from {s.bag}; check every line.",
             "# Use it with: python -m adlpipe.ingest BAGS -o data.h5 --config THIS.yaml"]

    def pick(cands: list[str], prefer: tuple[str, ...]) -> str | None:
        ranked = sorted(cands, key=lambda t: (not any(w in t for w in prefer), "compressed" in t, len(t), t))
        return ranked[0] if ranked else None

    image = pick([t for t in color if _sibling_info(t, infos)] or color, ("color", "rgb"))
    info = _sibling_info(image, infos) if image else None
    info = info or (infos[0] if infos else None)
    lines.append(f"# colour images: {color or 'none found'}; chosen the one with a camera_info beside it")
    lines.append(f"image: {image or 'FILL_ME'}")
    lines.append(f"camera_info: {info or 'FILL_ME'}")
    d = pick(depth, ("aligned", "registered", "depth_to_rgb", "depth"))
    lines.append(f"# depth images (16UC1 mm / 32FC1 m / compressedDepth): {depth or 'none: depth stays null'}")
    lines.append(f"depth: {d or 'null'}")
    lines.append(f"affordance: {affordance[0]}  # image topics named affordance: {affordance}" if affordance else
                 "affordance: null  # no affordance topic (real robots rarely have one); the stored map stays zeros")
    joints = by_type("sensor_msgs/msg/JointState")
    lines.append(f"joints: {joints[0] if joints else 'null'}  # JointState topics: {joints or 'none'}")
    strings = by_type("std_msgs/msg/String")
    lines.append(f"task: {strings[0] if strings else 'null'}  # no task topic: pass --task NAME" if not strings
                 else f"task: {strings[0]}  # String topics: {strings}")
    tfs = by_type("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
    lines.append(f"tf: {'/tf' if '/tf' in tfs else (tfs[0] if tfs else 'FILL_ME')}")
    lines.append(f"tf_static: {'/tf_static' if '/tf_static' in tfs else 'null'}")
    base, ee, others = _guess_frames(s)
    cam = s.topics[image].frame_id if image else ""
    # connected: the camera hangs below the base, or both below a common root (world, map, odom)
    linked = bool(cam) and bool(base) and bool(set(_chain(cam.lstrip("/"), s.parent)) & set(_chain(base, s.parent)))
    lines.append(f"# tf roots: {sorted(_roots(s))}; base: the root above the moving frames")
    lines.append(f"base_frame: {base or 'FILL_ME'}")
    lines.append(f"# end-effector candidates (frames carried by the moving links, deepest first): {others}")
    lines.append(f"ee_frame: {ee or 'FILL_ME'}")
    lines.append(f"# camera frame {cam!r} is {'connected to' if linked else 'NOT connected to'} the base in tf")
    lines += ["sync_tolerance_s: 0.05", "max_tf_gap_s: 0.2", "trajectory_end_s: null"]
    return "\n".join(lines) + "\n"


def _sibling_info(image: str | None, infos: list[str]) -> str | None:
    if not image:
        return None
    prefix = image.rsplit("/", 1)[0]
    for cand in (f"{prefix}/camera_info", f"{prefix.rsplit('/', 1)[0]}/camera_info"):
        if cand in infos:
            return cand
    return None


def _roots(s: Survey) -> set[str]:
    return {p for p in s.parent.values() if p not in s.parent}


def _guess_frames(s: Survey) -> tuple[str | None, str | None, list[str]]:
    carried = [f for f in s.parent if any(c in s.moving for c in _chain(f, s.parent)[:-1])]
    if not carried:
        return (sorted(_roots(s))[0] if _roots(s) else None), None, []
    children = set(s.parent.values())
    leaves = [f for f in carried if f not in children]
    depth = {f: len(_chain(f, s.parent)) for f in carried}
    ranked = sorted(leaves or carried, key=lambda f: (not any(w in f.lower() for w in EE_WORDS), -depth[f], f))
    ee = ranked[0]
    base = _chain(ee, s.parent)[-1]
    return base, ee, ranked
