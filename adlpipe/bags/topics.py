"""The topic map: which topic/frame of a bag carries which input. Defaults match `adlpipe.record`; users remap
them for their robot with a YAML file (`--config topics.yaml`, same keys)."""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from ..plumbing.errors import AdlError, read_small_yaml

# A trial bag's own topics (adlpipe.deploy.trial_bags writes them, adlpipe.evaluation.trials reads them)
OUTCOME, POLICY = "/adl/outcome", "/adl/policy"
UNFILLED = "FILL_ME"  # what ingest --suggest-config writes where it found no topic or frame


@dataclass(frozen=True)
class TopicMap:
    image: str = "/camera/color/image_raw"  # sensor_msgs/Image or sensor_msgs/CompressedImage
    depth: str | None = "/camera/depth/image_raw"  # optional (null: no depth)
    camera_info: str = "/camera/color/camera_info"
    affordance: str | None = "/adl/affordance"  # 32FC1 image; optional (null: no affordance map)
    joints: str | None = "/joint_states"
    # A policy's own state and action streams (sensor_msgs/JointState, position field), kept per frame: joint-space
    # policies and Push-T (adlpipe/envs/pusht.py). Optional: null, or absent from a bag, means none. The ADL world
    # publishes its arm's command on `action`: the commanded tcp position (x, y, z in base_frame) and the gripper
    # command, the stream closed-loop ADL policies learn (train --closed-loop --target command).
    state: str | None = None
    action: str | None = "/arm/tcp_command"
    task: str | None = "/adl/task"  # std_msgs/String; optional: --task names it for bags without one
    # The demonstrator's undisturbed tcp path beside a disturbed command (x, y, z as the action's first three;
    # `record --recoveries`): what `train --target recovery` makes its labels from. Optional.
    reference: str | None = "/adl/demo_reference"
    # An operator's take-over flag (std_msgs/Bool, true from when the person drives until false: HG-DAgger rollouts,
    # LeRobot's `intervention`); stored per frame as the last value at or before it (false before any). Optional.
    intervention: str | None = "/adl/intervention"
    # A labelled rollout's expert phase (sensor_msgs/JointState, one position: s along the reference path; adlpipe
    # rollout): `train --target recovery` labels each frame from the reference path at that phase. Optional.
    expert_phase: str | None = "/adl/expert_phase"
    tf: str = "/tf"
    tf_static: str = "/tf_static"
    base_frame: str = "base_link"
    ee_frame: str = "ee_link"
    sync_tolerance_s: float = 0.05  # depth/affordance/ee matched to the first image within this
    trajectory_end_s: float | None = None  # seconds after the first image; null: to the last ee pose
    gripper_joint: str | None = "finger_left"  # joint stored per frame as the gripper state (null: none)
    max_tf_gap_s: float = 0.2  # a longer gap in the end-effector tf is an error (or, with --allow-tf-gaps, a note)
    # Several demonstrations in one bag (adlpipe.bags.segments): a start/stop marker topic, or motion.
    segment_topic: str | None = None  # std_msgs/String "start"/"stop" or std_msgs/Bool true/false
    segment_idle_s: float | None = None  # split where the robot idles this long (null: no motion segmentation)
    segment_speed_mps: float = 0.01  # end effector slower than this is idle
    segment_gripper_joint: str | None = None  # also require this joint (the gripper) to be still
    segment_gripper_rate: float = 0.01  # joint units per second
    segment_min_s: float = 1.0  # shorter active stretches are not demonstrations
    # Several cameras (a scene camera and a wrist camera): a list of {name, image, camera_info, depth (optional)}.
    # The first is the primary camera: it takes the place of image/camera_info/depth above (the episode's own
    # layout); every other one is stored under cameras/<name>/ of the episode. Null: one camera, named "camera".
    cameras: list | None = None

    @classmethod
    def load(cls, paths: str | Path | list | None) -> TopicMap:
        """The defaults, overridden by each YAML in turn (a camera preset, then a robot preset, then your own)."""
        if paths is None or paths == []:
            return cls()
        merged: dict = {}
        paths = paths if isinstance(paths, list | tuple) else [paths]
        for path in paths:
            raw = cls._read(path)
            unfilled = [k for k, v in raw.items() if v == UNFILLED]
            if unfilled:
                raise AdlError(f"{path}: {', '.join(unfilled)} still {UNFILLED}: ingest --suggest-config found no "
                               "topic for them; name them (ingest --list shows the bag's topics); adlpipe needs a "
                               "camera (image, camera_info) and the end effector in tf")
            merged.update(raw)
        try:
            return cls(**merged)
        except AdlError as exc:
            raise AdlError(f"{', '.join(map(str, paths))}: {exc}") from None

    @classmethod
    def _read(cls, path: str | Path) -> dict:
        raw = read_small_yaml(Path(path), "topic map") or {}
        if not isinstance(raw, dict):
            raise AdlError(f"{path}: topic map must be a mapping of keys to topics")
        _refuse_unknown_keys(f"{path}: unknown topic-map keys", raw, cls)
        for f in fields(cls):
            if f.name in raw:
                _check_value(path, f.name, raw[f.name], str(f.type))  # a string: annotations are postponed
        both = sorted({"image", "camera_info", "depth"} & set(raw)) if raw.get("cameras") is not None else []
        if both:
            raise AdlError(f"{path}: give the cameras either as image/camera_info/depth or as a cameras list, not "
                           f"both ({', '.join(both)} beside cameras)")
        return raw

    def __post_init__(self) -> None:
        if self.cameras is not None:
            cams = [_camera_entry(c, k) for k, c in enumerate(self.cameras)]
            if not cams:
                raise AdlError("topic map: cameras is an empty list; name at least one camera, or leave it out")
            names = [c.name for c in cams]
            if len(set(names)) < len(names):
                raise AdlError(f"topic map: camera names repeat in cameras ({names}); give each its own name")
            topics = [t for c in cams for t in (c.image, c.camera_info, c.depth) if t]
            if len(set(topics)) < len(topics):
                raise AdlError("topic map: two cameras share a topic in cameras; each needs its own image, "
                               "camera_info and depth topics")
            object.__setattr__(self, "cameras", cams)
            first = cams[0]
            for key in ("image", "camera_info", "depth"):
                object.__setattr__(self, key, getattr(first, key))
        if not self.image or not self.camera_info or not self.tf:
            raise AdlError("topic map: image, camera_info and tf are required and cannot be null")

    @property
    def camera_name(self) -> str:
        """The primary camera's name (the first of `cameras`; "camera" for a one-camera map)."""
        return self.cameras[0].name if self.cameras else PRIMARY_CAMERA

    @property
    def extra_cameras(self) -> list[CameraTopics]:
        """The cameras stored beside the primary one, under cameras/<name>/ of each episode."""
        return list(self.cameras[1:]) if self.cameras else []

    def to_dict(self) -> dict:
        return asdict(self)

    def required_topics(self) -> list[str]:
        return [self.image, self.camera_info, self.tf] + [t for c in self.extra_cameras
                                                          for t in (c.image, c.camera_info)]

    def optional_topics(self) -> list[str]:
        return [t for t in (self.depth, self.affordance, self.joints, self.task, self.tf_static, self.state,
                            self.action, self.reference, self.intervention, self.expert_phase,
                            *(c.depth for c in self.extra_cameras)) if t]


PRIMARY_CAMERA = "camera"


@dataclass(frozen=True)
class CameraTopics:
    """One camera of a multi-camera topic map."""

    name: str
    image: str
    camera_info: str
    depth: str | None = None


def _refuse_unknown_keys(what: str, given: dict, cls: type) -> None:
    """One line listing the keys of `given` that are no field of the dataclass `cls`, with the known ones."""
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(given) - known)
    if unknown:
        raise AdlError(f"{what} {unknown}; known keys: {sorted(known)}")


def _camera_entry(entry: object, k: int) -> CameraTopics:
    """One item of the topic map's `cameras` list, checked: one line naming the camera and the key otherwise."""
    if isinstance(entry, CameraTopics):
        return entry
    where = f"topic map: cameras[{k}]"
    if not isinstance(entry, dict):
        raise AdlError(f"{where} must be a mapping with name, image, camera_info and optional depth")
    _refuse_unknown_keys(f"{where}: unknown keys", entry, CameraTopics)
    for key in ("name", "image", "camera_info"):
        if key not in entry:
            raise AdlError(f"{where}: key {key!r} is required")
    for key, value in entry.items():
        _check_value(where, key, value, "str | None" if key == "depth" else "str")
    if not re.fullmatch(r"[A-Za-z0-9_]{1,40}", entry["name"]):
        raise AdlError(f"{where}: name {entry['name']!r} must be 1-40 letters, digits or '_' (it names a group and "
                       "a LeRobot key)")
    return CameraTopics(**entry)


def _check_value(path: object, key: str, value: object, annotation: str) -> None:
    """One line naming the key when a YAML value has the wrong type (a number for a topic, a word for a number)."""
    optional = "None" in str(annotation)
    if value is None:
        if not optional:
            raise AdlError(f"{path}: topic-map key {key!r} cannot be null")
        return
    if key == "cameras":
        if not isinstance(value, list):
            raise AdlError(f"{path}: topic-map key 'cameras' must be a list of cameras, got {value!r}")
        return
    if "float" in str(annotation):
        if isinstance(value, bool) or not isinstance(value, int | float) or not value == value or value < 0:
            raise AdlError(f"{path}: topic-map key {key!r} must be a non-negative number of seconds, got {value!r}")
    elif not isinstance(value, str) or not value.strip():
        raise AdlError(f"{path}: topic-map key {key!r} must be a topic or frame name (text), got {value!r}")
    elif any(ord(c) < 32 for c in value):
        raise AdlError(f"{path}: topic-map key {key!r} has control characters")
