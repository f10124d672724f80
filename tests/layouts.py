"""Bags laid out as real robots and cameras publish them, written with the real writers (mcap, rosbags) through
adlpipe's BagWriter: a Kinova Gen3 arm (a moving chain ending in bracelet_link, with end_effector_link and
tool_frame on /tf_static), an Azure Kinect, RealSense or ZED camera, namespaced joint states, compressedDepth.

The ground truth is returned beside the bag: where the end-effector frame really was at every tf stamp.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
from rosbags.typesys import get_types_from_msg

from adlpipe.bags import messages as M
from adlpipe.bags.images import encode_compressed_depth
from adlpipe.bags.writer import BagWriter
from adlpipe.geometry.transforms import matrix_to_quat, pose_matrix

CAMERAS = {  # driver topic names
    "azure_kinect": dict(image="/rgb/image_raw", camera_info="/rgb/camera_info", depth="/depth_to_rgb/image_raw",
                         frame="rgb_camera_link"),
    "realsense": dict(image="/camera/camera/color/image_raw", camera_info="/camera/camera/color/camera_info",
                      depth="/camera/camera/aligned_depth_to_color/image_raw", frame="camera_color_optical_frame"),
    "zed": dict(image="/zed/zed_node/rgb/image_rect_color", camera_info="/zed/zed_node/rgb/camera_info",
                depth="/zed/zed_node/depth/depth_registered", frame="zed_left_camera_optical_frame"),
}
ROBOTS = {  # (base, moving chain, static chain to the end effector, joint-state topic)
    "kinova_gen3": dict(base="base_link", moving=["shoulder_link", "bracelet_link"],
                        static=[("end_effector_link", 0.0615), ("tool_frame", 0.18)], joints="/my_gen3/joint_states"),
    "franka": dict(base="fr3_link0", moving=["fr3_link1", "fr3_link8"], static=[("fr3_hand", 0.0),
                                                                              ("fr3_hand_tcp", 0.1034)],
                   joints="/joint_states"),
    "ur": dict(base="base_link", moving=["shoulder_link", "wrist_3_link"], static=[("flange", 0.0), ("tool0", 0.0)],
               joints="/joint_states"),
}


@dataclass
class Layout:
    camera: str = "azure_kinect"
    robot: str = "kinova_gen3"
    fmt: str = "mcap"
    depth: str | None = "16UC1"  # 16UC1 | 32FC1 | compressed16 | compressed32 | rvl16 | None
    joints: bool = True
    task: str | None = "wipe the table"
    duration_s: float = 3.0
    tf_gap: tuple[float, float] | None = None  # (start, end) seconds with no moving tf
    size: tuple[int, int] = (64, 48)  # width, height
    demos: int = 1  # demonstrations in the bag, each duration_s long, with pause_s of stillness after each
    pause_s: float = 0.0
    markers: bool = False  # std_msgs/String "start"/"stop" on /segment around each demonstration
    camera_hz: float = 10.0
    tf_hz: float = 50.0
    lens: tuple[str, tuple[float, ...]] | None = None  # CameraInfo distortion_model and d (None: zeros)
    top_down: bool = False  # the camera 0.7 m above the workspace looking down (it sees the whole path)
    root: str | None = None  # a common root (world, map, odom): robot base and camera both hang below it
    encoding: str = "rgb8"  # the camera's sensor_msgs/Image encoding (bayer_*, yuv422, rgb16, mono16, ...)
    smooth: bool = False  # smooth colour gradients instead of noise (what demosaicing and 4:2:2 chroma keep)
    split_s: float | None = None  # ROS1 only: `rosbag record --split`, a new <name>_<k>.bag every split_s seconds
    late_frames: dict[int, float] | None = None  # frame index -> frames it is logged late (its header stamp unchanged)
    wrist: bool = False  # a second camera on the arm (WRIST), moving with the last moving link, at wrist_hz
    wrist_hz: float = 15.0
    wrist_tf: bool = True  # False: the wrist camera's frame is on no tf (a forgotten static transform)
    frozen: tuple[int, int] | None = None  # frames k0..k1 repeat frame k0's image (a camera driver that froze)
    tf_glitch_s: float | None = None  # the moving tf sample nearest this time is 0.5 m off (a tf glitch)
    idle_start_s: float = 0.0  # the arm holds still this long before it moves (an operator who paused)
    zero_image_stamps: bool = False  # the camera's header.stamp is 0 (a driver that never sets it); log times right
    joint_spike_s: float | None = None  # joint_3's sample nearest this time is 1 rad off (an encoder glitch)
    joint_nan_s: float | None = None  # joint_3's sample nearest this time is NaN (a driver's lost reading)
    joint_stuck: tuple[float, float] | None = None  # joint_3 repeats its value from t0 to t1 s (a stuck sensor)
    clock_offset_s: float = 0.0  # every stamp later by this (the same demonstration saved again later)
    video: str | None = None  # the camera as H.264 video: "CompressedVideo" (foxglove_msgs) or "FFMPEGPacket"
    video_cut: int = 0  # the recording starts this many packets into the stream (between keyframes: GOP 10)


# A wrist camera as labs mount one: fixed to the arm's last moving link by /tf_static, its own topics and size.
WRIST = dict(image="/wrist/color/image_raw", camera_info="/wrist/color/camera_info", depth="/wrist/depth/image_raw",
             frame="wrist_camera_color_optical_frame", size=(40, 30), offset=(0.0, 0.06, 0.03), fx=30.0)


def wrist_image(k: int) -> np.ndarray:
    """The wrist camera's k-th frame (rgb8)."""
    width, height = WRIST["size"]
    return _noise(10_000 + k, height, width)


def wrist_pose(t: float, lay: Layout) -> np.ndarray:
    """The wrist camera's true pose in the robot's base frame at bag time t."""
    a, b = _moving(_clock(t, lay)[0])
    return a @ b @ pose_matrix(list(WRIST["offset"]), [1.0, 0, 0, 0])


def wrist_K() -> np.ndarray:
    width, height = WRIST["size"]
    return np.array([[WRIST["fx"], 0, (width - 1) / 2], [0, WRIST["fx"], (height - 1) / 2], [0, 0, 1]])


def _moving(t: float) -> list[np.ndarray]:
    """Poses of the moving chain at time t: a yawing shoulder and a bracelet sweeping and tilting."""
    yaw = 0.4 * np.sin(0.8 * t)
    a = pose_matrix([0, 0, 0.28], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
    tilt = 0.3 * t
    b = pose_matrix([0.45 + 0.05 * np.sin(t), 0.1 * t, 0.2],
                    [np.cos((np.pi + tilt) / 2), np.sin((np.pi + tilt) / 2), 0, 0])  # pointing down, tilting
    return [a, b]


def _clock(t: float, lay: Layout) -> tuple[float, int]:
    """(motion time, demonstration index) at bag time t: the motion clock stops while the robot pauses."""
    t = max(0.0, t - lay.idle_start_s)
    period = lay.duration_s + lay.pause_s
    k = min(int(t // period), lay.demos - 1) if period > 0 else 0
    return k * lay.duration_s + min(t - k * period, lay.duration_s), k


def write_layout_bag(path: Path, lay: Layout) -> tuple[Path, np.ndarray, np.ndarray]:
    """Write the bag; returns (path, ee stamps in s from the bag's start, true ee positions in the base frame)."""
    cam, robot = CAMERAS[lay.camera], ROBOTS[lay.robot]
    w = BagWriter(path, lay.fmt)
    f = w.msgs
    t0 = 1_767_225_600 * 10**9 + int(lay.clock_offset_s * 1e9)
    ns = lambda t: t0 + int(round(t * 1e9))  # noqa: E731
    width, height = lay.size
    K = np.array([[50.0, 0, (width - 1) / 2], [0, 50.0, (height - 1) / 2], [0, 0, 1]])
    events: list[tuple[int, int, str, str, object]] = []
    cam_pose = (np.array([0.9, -0.5, 0.9]), matrix_to_quat(np.array([[0, -1, 0], [-0.6, 0, -0.8], [0.8, 0, -0.6]])))
    if lay.top_down:
        cam_pose = (np.array([0.42, 0.12, 1.2]), matrix_to_quat(np.diag([1.0, -1.0, -1.0])))
    statics = [(robot["base"], "camera_base", cam_pose[0], cam_pose[1]),
               ("camera_base", cam["frame"], np.zeros(3), np.array([1.0, 0, 0, 0]))]
    if lay.root:  # the room's frame holds both: the base 2 m along x and turned 90 degrees, the camera where it was
        root_base = pose_matrix([2.0, 0.5, 0.0], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
        root_cam = root_base @ pose_matrix(*cam_pose)
        statics[0] = (lay.root, "camera_base", root_cam[:3, 3], matrix_to_quat(root_cam[:3, :3]))
        statics.append((lay.root, robot["base"], root_base[:3, 3], matrix_to_quat(root_base[:3, :3])))
    parent = robot["moving"][-1]
    if lay.wrist and lay.wrist_tf:
        statics.append((parent, WRIST["frame"], np.array(WRIST["offset"]), np.array([1.0, 0, 0, 0])))
    for child, dz in robot["static"]:
        statics.append((parent, child, np.array([0.0, 0.0, dz]), np.array([1.0, 0, 0, 0])))
        parent = child
    events.append((ns(0), 0, "/tf_static", M.TF, lambda: f.tf(ns(0), statics)))
    if lay.task:
        events.append((ns(0), 1, "/task", M.STRING, lambda: f.string(lay.task)))
    total = lay.demos * (lay.duration_s + lay.pause_s) - lay.pause_s + lay.idle_start_s
    if lay.markers:
        for k in range(lay.demos):
            a = k * (lay.duration_s + lay.pause_s)
            events.append((ns(a), 1, "/segment", M.STRING, lambda: f.string("start")))
            events.append((ns(a + lay.duration_s), 9, "/segment", M.STRING, lambda: f.string("stop")))
    encoder = _H264(lay) if lay.video else None
    for k in range(int(round(total * lay.camera_hz)) + 1):
        t = k / lay.camera_hz
        tn = ns(t)
        events.append((tn, 2, cam["camera_info"], M.CAMERA_INFO,
                       lambda tn=tn: f.camera_info(tn, cam["frame"], K, width, height,
                                                   *((lay.lens[0], np.array(lay.lens[1])) if lay.lens else ()))))
        late = ns(t + (lay.late_frames or {}).get(k, 0.0) / lay.camera_hz)  # log time; the header keeps tn
        stamp = 0 if lay.zero_image_stamps else tn
        if lay.video:
            if k >= lay.video_cut:
                events.append(_video_event(f, lay, cam, k, tn, encoder))
            continue
        events.append((late, 3, cam["image"], M.IMAGE,  # made when written: a long bag is never all in memory
                       lambda stamp=stamp, k=k: f.image(stamp, cam["frame"], *_camera_image(k, lay))))
        if lay.depth:
            d = np.full((height, width), 1.5, np.float32) + np.linspace(0, 1, width, dtype=np.float32)
            d[:4] = np.nan  # no return
            events.append(_depth_event(f, lay.depth, cam, tn, d))
    if lay.wrist:
        ww, wh = WRIST["size"]
        for k in range(int(round(total * lay.wrist_hz)) + 1):
            tn = ns(k / lay.wrist_hz)
            events.append((tn, 2, WRIST["camera_info"], M.CAMERA_INFO,
                           lambda tn=tn: f.camera_info(tn, WRIST["frame"], wrist_K(), ww, wh)))
            events.append((tn, 3, WRIST["image"], M.IMAGE,
                           lambda tn=tn, k=k: f.image(tn, WRIST["frame"], wrist_image(k), "rgb8")))
            raw = np.full((wh, ww), 400 + k, np.uint16)  # millimetres
            events.append((tn, 3, WRIST["depth"], M.IMAGE,
                           lambda tn=tn, raw=raw: f.image(tn, WRIST["frame"], raw, "16UC1")))
    ee_t, ee_p = [], []
    for k in range(int(round(total * lay.tf_hz)) + 1):  # the moving tf
        t = k / lay.tf_hz
        if lay.tf_gap and lay.tf_gap[0] < t < lay.tf_gap[1]:
            continue
        tn = ns(t)
        chain = _moving(_clock(t, lay)[0])
        if lay.tf_glitch_s is not None and abs(t - lay.tf_glitch_s) < 0.5 / lay.tf_hz:
            chain[1] = chain[1] @ pose_matrix([0.5, 0.0, 0.0], [1.0, 0, 0, 0])
        names = [robot["base"], *robot["moving"]]
        tfs = [(names[i], names[i + 1], T[:3, 3], matrix_to_quat(T[:3, :3])) for i, T in enumerate(chain)]
        events.append((tn, 4, "/tf", M.TF, lambda tn=tn, tfs=tfs: f.tf(tn, tfs)))
        T = chain[0] @ chain[1]
        for _child, dz in robot["static"]:
            T = T @ pose_matrix([0, 0, dz], [1, 0, 0, 0])
        ee_t.append(t)
        ee_p.append(T[:3, 3])
    if lay.joints:
        names = [f"joint_{i}" for i in range(1, 8)]
        for k in range(int(round(total * 100)) + 1):
            tn = ns(k / 100)
            q = np.sin(np.arange(7) + k / 100)
            if lay.joint_stuck and lay.joint_stuck[0] <= k / 100 <= lay.joint_stuck[1]:
                q[2] = np.sin(2 + lay.joint_stuck[0])
            if k == round((lay.joint_spike_s or -1) * 100):
                q[2] += 1.0
            if k == round((lay.joint_nan_s or -1) * 100):
                q[2] = np.nan
            events.append((tn, 5, robot["joints"], M.JOINT_STATE,
                           lambda tn=tn, q=q: f.joint_state(tn, names, q, np.zeros(7))))
    events.sort(key=lambda e: (e[0], e[1]))
    if lay.split_s:  # the parts of one recording: each message in the part its log time falls in
        w.abort()
        stem = path.with_suffix("")
        parts: list[BagWriter] = []
        for tn, _, topic, msgtype, build in events:
            k = int((tn - t0) / 1e9 // lay.split_s)
            while len(parts) <= k:
                parts.append(BagWriter(Path(f"{stem}_{len(parts)}.bag"), "bag"))
            parts[k].write(topic, msgtype, tn, build())
        return [p.close() for p in parts][0], np.array(ee_t), np.array(ee_p)
    try:
        for tn, _, topic, msgtype, build in events:
            w.write(topic, msgtype, tn, build())
        return w.close(), np.array(ee_t), np.array(ee_p)
    except BaseException:
        w.abort()
        raise


def _noise(k: int, height: int, width: int) -> np.ndarray:
    return np.random.default_rng(k).integers(0, 255, (height, width, 3), dtype=np.uint8)


def smooth_rgb(k: int, height: int, width: int) -> np.ndarray:
    """Slow colour gradients that move with k: what a Bayer or 4:2:2 camera reproduces nearly exactly."""
    y, x = np.mgrid[0:height, 0:width].astype(float)
    r = 128 + 100 * np.sin(x / width * 3 + k / 5)
    g = 128 + 100 * np.cos(y / height * 2 + k / 7)
    b = 128 + 90 * np.sin((x + y) / (width + height) * 4)
    return np.clip(np.stack([r, g, b], -1), 0, 255).astype(np.uint8)


BAYER = {"bayer_rggb8": "RGGB", "bayer_bggr8": "BGGR", "bayer_gbrg8": "GBRG", "bayer_grbg8": "GRBG"}


def encode_rgb(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """An RGB frame laid out as a camera driver publishes it in `encoding` (the message's data as an array)."""
    import cv2

    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if encoding in ("rgb8", "8UC3"):
        return rgb
    if encoding in ("mono8", "8UC1"):
        return grey
    if encoding in ("rgb16", "bgr16", "mono16"):
        v = {"rgb16": rgb, "bgr16": rgb[..., ::-1], "mono16": grey}[encoding].astype(np.uint16)
        return (v << 8) | v  # the full 16-bit range, as a 16-bit sensor fills it
    if encoding in BAYER:
        out = np.zeros(rgb.shape[:2], np.uint8)
        for i, c in enumerate(BAYER[encoding]):
            out[i // 2::2, i % 2::2] = rgb[i // 2::2, i % 2::2, "RGB".index(c)]
        return out
    # 4:2:2 YUV from OpenCV's own BT.601 4:2:0 planes (the range its inverse expects), chroma rows repeated
    h, w = grey.shape
    yuv = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420).reshape(-1)
    y, u, v = yuv[:h * w].reshape(h, w), yuv[h * w:h * w * 5 // 4], yuv[h * w * 5 // 4:]
    u, v = (np.repeat(c.reshape(h // 2, w // 2), 2, axis=0) for c in (u, v))
    out = np.zeros((h, w // 2, 4), np.uint8)
    if encoding in ("yuv422", "uyvy"):
        out[..., 0], out[..., 1], out[..., 2], out[..., 3] = u, y[:, 0::2], v, y[:, 1::2]
    else:  # yuv422_yuy2, yuyv
        out[..., 0], out[..., 1], out[..., 2], out[..., 3] = y[:, 0::2], u, y[:, 1::2], v
    return out.reshape(h, w, 2)


VIDEO_DEFS = {  # the two video transports' message definitions, registered in the writer's type store
    "CompressedVideo": ("foxglove_msgs/msg/CompressedVideo",
                        "builtin_interfaces/Time timestamp\nstring frame_id\nuint8[] data\nstring format"),
    "FFMPEGPacket": ("ffmpeg_image_transport_msgs/msg/FFMPEGPacket",
                     "std_msgs/Header header\nint32 width\nint32 height\nstring encoding\nuint64 pts\nuint8 flags\n"
                     "bool is_bigendian\nuint8[] data"),
}


class _H264:
    """Every camera frame of the layout encoded with PyAV's libx264 as a streaming encoder sends it: one packet per
    frame (no B-frames), a keyframe every 10 frames and no other, Annex B with its parameter sets in every keyframe."""

    def __init__(self, lay: Layout) -> None:
        import av

        width, height = lay.size
        ctx = av.CodecContext.create("libx264", "w")
        ctx.width, ctx.height, ctx.pix_fmt = width, height, "yuv420p"
        ctx.time_base = Fraction(1, int(lay.camera_hz))
        ctx.options = {"g": "10", "bf": "0", "tune": "zerolatency", "crf": "12", "x264-params": "scenecut=0"}
        self.packets: list[tuple[bytes, bool]] = []
        total = lay.demos * (lay.duration_s + lay.pause_s) - lay.pause_s + lay.idle_start_s
        for k in range(int(round(total * lay.camera_hz)) + 1):
            frame = av.VideoFrame.from_ndarray(smooth_rgb(k, height, width), format="rgb24")
            frame.pts = k
            self.packets += [(bytes(p), bool(p.is_keyframe)) for p in ctx.encode(frame)]
        self.packets += [(bytes(p), bool(p.is_keyframe)) for p in ctx.encode()]


def _video_event(f: M.MessageFactory, lay: Layout, cam: dict, k: int, tn: int, encoder: _H264) -> tuple:
    msgtype, msgdef = VIDEO_DEFS[lay.video]
    if msgtype not in f.T:
        f.store.register(get_types_from_msg(msgdef, msgtype))
    data, key = encoder.packets[k]
    width, height = lay.size

    def build() -> object:
        payload = np.frombuffer(data, np.uint8)
        if lay.video == "CompressedVideo":
            return f.T[msgtype](timestamp=f.stamp(tn), frame_id=cam["frame"], data=payload, format="h264")
        return f.T[msgtype](header=f.header(tn, cam["frame"]), width=width, height=height, encoding="libx264",
                            pts=k, flags=int(key), is_bigendian=False, data=payload)

    return (tn, 3, cam["image"], msgtype, build)


def _camera_image(k: int, lay: Layout) -> tuple[np.ndarray, str]:
    width, height = lay.size
    if lay.frozen and lay.frozen[0] <= k <= lay.frozen[1]:
        k = lay.frozen[0]
    rgb = smooth_rgb(k, height, width) if lay.smooth else _noise(k, height, width)
    return encode_rgb(rgb, lay.encoding), lay.encoding


def _depth_event(f: M.MessageFactory, kind: str, cam: dict, tn: int, d: np.ndarray) -> tuple:
    if kind == "16UC1":
        raw = np.clip(np.round(np.nan_to_num(d) * 1000), 0, 65535).astype(np.uint16)
        return (tn, 3, cam["depth"], M.IMAGE, lambda: f.image(tn, cam["frame"], raw, "16UC1"))
    if kind == "32FC1":
        return (tn, 3, cam["depth"], M.IMAGE, lambda: f.image(tn, cam["frame"], d, "32FC1"))
    encoding = "16UC1" if kind.endswith("16") else "32FC1"
    fmt, data = encode_compressed_depth(d, encoding, "rvl" if kind.startswith("rvl") else "png")

    def build() -> object:
        return f.T[M.COMPRESSED](header=f.header(tn, cam["frame"]), format=fmt, data=np.frombuffer(data, np.uint8))

    return (tn, 3, cam["depth"] + "/compressedDepth", M.COMPRESSED, build)


def topic_map(lay: Layout, **over: object) -> dict:
    """The topic-map YAML content for this layout."""
    cam, robot = CAMERAS[lay.camera], ROBOTS[lay.robot]
    depth = None
    if lay.depth:
        depth = cam["depth"] + ("/compressedDepth" if lay.depth.startswith(("compressed", "rvl")) else "")
    out = dict(image=cam["image"], camera_info=cam["camera_info"], depth=depth, affordance=None,
               joints=robot["joints"], task="/task", base_frame=robot["base"], ee_frame=robot["static"][-1][0])
    if lay.wrist:
        scene = {"name": "scene", "image": out.pop("image"), "camera_info": out.pop("camera_info")}
        depth = out.pop("depth")
        scene.update({"depth": depth} if depth else {})
        out["cameras"] = [scene, {"name": "wrist", "image": WRIST["image"], "camera_info": WRIST["camera_info"],
                                  "depth": WRIST["depth"]}]
    out.update(over)
    return out
