"""A Rerun recording of the dataset itself: every frame of the chosen episodes, one after another.

Timelines: `dataset_time` (seconds; the episodes back to back, a second apart, so scrubbing walks through them all),
`frame` (a global frame count) and `episode` (its index in the selection). Entities, shared by every episode:

    world                              right-handed, z up (the robot's base frame)
    world/camera (+ /image)            Transform3D base <- camera and the Pinhole of the stored image: the frustum
    world/camera/image/rgb             every RGB frame
    world/camera/image/depth           the depth image synced to the frame (millimetres), when the bag had depth
    world/camera/image/affordance      the affordance map synced to the frame, as a colour overlay
    world/camera/image/ee              the end effector projected into the image
    world/cameras/<name> (+ /image/rgb, /image/ee)  each other camera of the episode (a wrist camera): its pose and
                                       frame at each of its own stamps, and the end effector as it sees it
    world/ee_path, world/ee            the episode's end-effector path in 3D, and where it is at the frame
    joints/<name>, gripper             joint positions and the gripper at each frame (time series)
    task                               the episode's task, bag and frame count

The blueprint puts the image (with its overlays) beside the 3D view, the joint time series and the task below.
Frames are read and logged one at a time: memory stays flat in the number of episodes.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..dataset import schema
from ..geometry.camera import project, read_lens
from ..plumbing.atomic import atomic_path
from ..plumbing.errors import AdlError, one_line

EE_COLOR = [250, 200, 40]
GAP_S = 1.0  # between episodes on dataset_time


def affordance_overlay(aff: np.ndarray) -> np.ndarray:
    """RGBA: a jet colour map whose opacity follows the affordance value."""
    a = np.clip(np.nan_to_num(aff), 0, 1)
    rgb = cv2.cvtColor(cv2.applyColorMap((a * 255).astype(np.uint8), cv2.COLORMAP_JET), cv2.COLOR_BGR2RGB)
    return np.dstack([rgb, (a * 180).astype(np.uint8)])


def blueprint(cameras: list[str] = ()) -> rrb.Blueprint:
    """The first camera (with its overlays) and the 3D view above; each other camera (a wrist camera) beside them;
    joints, gripper and task below."""
    others = [rrb.Spatial2DView(origin=f"world/cameras/{c}/image", name=c) for c in cameras]
    return rrb.Blueprint(rrb.Vertical(
        rrb.Horizontal(rrb.Spatial2DView(origin="world/camera/image", name="camera + affordance"), *others,
                       rrb.Spatial3DView(origin="world", name="end effector and cameras")),
        rrb.Horizontal(rrb.TimeSeriesView(origin="joints", name="joints"),
                       rrb.TimeSeriesView(origin="gripper", name="gripper"),
                       rrb.TextDocumentView(origin="task", name="task")),
        row_shares=[3, 2]), collapse_panels=True)


def write_dataset_recording(out: Path, data: Path, names: list[str]) -> int:
    """Record the named episodes of the dataset to `out` (temp file, then renamed); returns the frames logged."""
    try:
        return _write_dataset_recording(out, data, names)
    except schema.DAMAGED_STRUCTURE as exc:  # damage below what opening the dataset checks (a table deep in a
        # file); OS errors (a full disk) pass as they are
        schema.raise_if_interrupted(exc)
        raise AdlError(f"{data}: a damaged episode or index ({one_line(exc)}); re-ingest its bags into a new "
                       "dataset") from None


def _write_dataset_recording(out: Path, data: Path, names: list[str]) -> int:
    with schema.open_dataset(data, names) as f:
        eps = [f[schema.EPISODES][n] for n in names]
        # Rerun keeps images raw: RGB, depth and the affordance overlay, about 11 bytes a pixel
        check_recording_space(out, sum(int(np.prod(g["frames"]["rgb"].shape[:3])) * 11 for g in eps)
                              + sum(int(np.prod(g[f"{schema.CAMERAS}/{c}/frames/rgb"].shape[:3])) * 3
                                    for g in eps for c in schema.camera_names(g)[1:]))
        cameras = sorted({c for g in eps for c in schema.camera_names(g)[1:]})
        with atomic_path(out) as tmp:
            rec = rr.RecordingStream("adlpipe_dataset")
            rec.save(tmp, default_blueprint=blueprint(cameras))
            rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            start, frame = 0.0, 0
            for i, g in enumerate(eps):
                duration, frame = _episode(rec, g, i, start, frame)
                start += duration + GAP_S
            close_recording(rec, tmp, out)
    return frame


# Rerun writes a saved recording on its own thread. When the disk fills, that writer stops and every later flush
# (and the flush at exit) waits forever; a stage would hang with a truncated .rrd in place. Flushes are polled so a
# full disk is seen, and the stage's command line then leaves without waiting for the writer (writer_stuck).
FLUSH_POLL_S = 5.0
_stuck: list[Path] = []
# Rerun's save() itself waits forever when the disk is full as it starts: a recording starts only with room for
# what it will log and this margin.
SPACE_MARGIN = 8 << 20


def check_recording_space(out: Path, estimate: int) -> None:
    """Refuse to start a recording of about `estimate` bytes where the disk cannot hold it."""
    parent = out.parent if out.parent.exists() else Path(".")
    st = os.statvfs(parent)
    free = st.f_bavail * st.f_frsize
    if free < estimate + SPACE_MARGIN:
        raise OSError(errno.ENOSPC, f"No space left on device (needs about {(estimate + SPACE_MARGIN) / 1e6:.0f} "
                      f"MB, {free / 1e6:.1f} MB free)", str(out))


def close_recording(rec: rr.RecordingStream, tmp: Path, out: Path) -> None:
    """Flush a recording saved to `tmp` and close it; a full disk is an OSError naming `out` (the temp file is then
    removed by atomic_path and the previous `out` is kept)."""
    while True:
        try:
            rec.flush(timeout_sec=FLUSH_POLL_S)
            break
        except RuntimeError:  # not flushed yet: a slow disk, or a writer that stopped on a full one
            st = os.statvfs(tmp.parent)
            if st.f_bavail * st.f_frsize >= 1 << 20:
                continue
            _stuck.append(out)
            raise OSError(errno.ENOSPC, "No space left on device", str(out)) from None
    rec.disconnect()


def writer_stuck() -> bool:
    """Whether a recording's writer stopped on a full disk (this process cannot end through Python's exit, whose
    flush would wait for it)."""
    return bool(_stuck)


def _episode(rec: rr.RecordingStream, g: object, index: int, start: float, frame: int) -> tuple[float, int]:
    fr = g["frames"]
    t = fr["t"][()]
    K, T = g["K"][()], g["T_base_camera"][()]
    size = int(fr["rgb"].shape[1])
    ee = fr["ee_pos"][()].astype(float)
    joints, names = fr["joint_pos"][()], [str(n) for n in g["series/joint_pos"].attrs["joint_names"]]
    gripper = fr["gripper"][()]
    uv = project(ee, K, T, read_lens(g), (size, size))  # where the end effector appears in the stored (distorted) image
    rec.set_time("dataset_time", duration=start)
    rec.set_time("frame", sequence=frame)
    rec.set_time("episode", sequence=index)
    rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    rec.log("world/camera/image", rr.Pinhole(image_from_camera=K, resolution=[size, size]))
    rec.log("world/ee_path", rr.LineStrips3D([g["series/ee_pos"][()]], colors=[EE_COLOR], radii=0.002))
    rec.log("task", rr.TextDocument(f"{g.attrs['task']}\n\nepisode {index}: {g.name.split('/')[-1]}\n"
                                    f"{g.attrs.get('source_path', '')}\n{len(t)} frames, {float(t[-1]):.1f} s"))
    depth_index = fr["depth_index"][()] if "depth_index" in fr else np.full(len(t), -1)
    aff_index = fr["affordance_index"][()] if "affordance_index" in fr else np.full(len(t), -1)
    last_aff = -2
    for k, tk in enumerate(t):
        rec.set_time("dataset_time", duration=start + float(tk))
        rec.set_time("frame", sequence=frame + k)
        rec.set_time("episode", sequence=index)
        rec.log("world/camera/image/rgb", rr.Image(fr["rgb"][k]))
        if depth_index[k] >= 0:
            rec.log("world/camera/image/depth", rr.DepthImage(fr["depth"][int(depth_index[k])], meter=1000.0))
        if aff_index[k] >= 0 and aff_index[k] != last_aff:  # maps change rarely: log one when it does
            rec.log("world/camera/image/affordance",
                    rr.Image(affordance_overlay(fr["affordance"][int(aff_index[k])])))
            last_aff = int(aff_index[k])
        rec.log("world/camera/image/ee", rr.Points2D([uv[k]], colors=[EE_COLOR], radii=1.5))
        rec.log("world/ee", rr.Points3D([ee[k]], colors=[EE_COLOR], radii=0.01))
        for j, jn in enumerate(names):
            if np.isfinite(joints[k, j]):
                rec.log(f"joints/{jn}", rr.Scalars(float(joints[k, j])))
        if np.isfinite(gripper[k]):
            rec.log("gripper", rr.Scalars(float(gripper[k])))
    for name in schema.camera_names(g)[1:]:
        _other_camera(rec, g, name, ee, t, start, index)
    return float(t[-1]) if len(t) else 0.0, frame + len(t)


def _other_camera(rec: rr.RecordingStream, g: object, name: str, ee: np.ndarray, t_ee: np.ndarray, start: float,
                  index: int) -> None:
    """Another camera's frames at its own stamps on dataset_time, with its pose (it may move) and the end effector
    as it sees it."""
    c = g[f"{schema.CAMERAS}/{name}"]
    fr = c["frames"]
    K, size, lens = c["K"][()], int(fr["rgb"].shape[1]), read_lens(c)
    poses = fr["T_base_camera"][()]
    rec.log(f"world/cameras/{name}/image", rr.Pinhole(image_from_camera=K, resolution=[size, size]))
    for k, tk in enumerate(fr["t"][()]):
        rec.set_time("dataset_time", duration=start + float(tk))
        rec.set_time("episode", sequence=index)
        T = poses[k]
        rec.log(f"world/cameras/{name}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        rec.log(f"world/cameras/{name}/image/rgb", rr.Image(fr["rgb"][k]))
        p = np.array([np.interp(tk, t_ee, ee[:, i]) for i in range(3)])[None]
        rec.log(f"world/cameras/{name}/image/ee", rr.Points2D(project(p, K, T, lens, (size, size)),
                                                               colors=[EE_COLOR], radii=1.5))


def write_bag_beside_episode(out: Path, data: Path, name: str, bag: Path, config: list[Path] | None = None) -> int:
    """One recording of a raw bag and the episode ingest made of it, on one `dataset_time` timeline (seconds from
    the episode's first frame): the bag's every camera image at its own resolution and stamp (bag/image), its
    joint states (bag/joints/<name>) and the end-effector path as its tf gives it (world/bag_ee), beside the
    stored episode's entities. Returns the bag images logged."""
    from ..bags.episode_reader import read_bag, stamp_s
    from ..bags.images import as_rgb8, decode_image
    from ..bags.reader import BagSource
    from ..curation.verify import topic_map_of
    from ..dataset.from_bag import end_effector_path, sha256_of

    with schema.open_dataset(data, [name]) as f:
        g = f[schema.EPISODES][name]
        if bag.exists() and sha256_of(bag) != str(g.attrs["source_sha256"]):
            raise AdlError(f"{bag}: not the bag episode {name} was ingested from (its sha256 differs; the episode "
                           f"came from {g.attrs['source_path']})")
        tm = topic_map_of(g, config)
        t0 = int(g.attrs["stamp0_ns"]) / 1e9
        window = tuple(int(v) for v in g.attrs["window_ns"]) if "window_ns" in g.attrs else None
        src = BagSource(bag)
        r = read_bag(src, tm, window)  # tf, joints and the first image: what the path needs (no frames kept)
        ee_t, ee_p, _t_end, _note = end_effector_path(r, tm, allow_gaps=True)
        check_recording_space(out, int(np.prod(g["frames"]["rgb"].shape[:3])) * 11
                              + len(g["frames/t"]) * int(np.prod(r.image.shape)) * 2)
        with atomic_path(out) as tmp:
            rec = rr.RecordingStream("adlpipe_bag_and_episode")
            rec.save(tmp, default_blueprint=_side_by_side_blueprint())
            rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            _episode(rec, g, 0, 0.0, 0)
            rec.log("world/bag_ee_path", rr.LineStrips3D([ee_p], colors=[[90, 160, 255]], radii=0.002), static=True)
            for t, p in zip(ee_t, ee_p, strict=True):
                rec.set_time("dataset_time", duration=float(t))
                rec.log("world/bag_ee", rr.Points3D([p], colors=[[90, 160, 255]], radii=0.008))
            for k, q in enumerate(r.joint_pos):
                rec.set_time("dataset_time", duration=float(r.joint_t[k] - t0))
                for j, jn in enumerate(r.joint_names):
                    rec.log(f"bag/joints/{jn}", rr.Scalars(float(q[j])))
            images = 0
            lo, hi = window or (None, None)
            for _topic, log_ns, decode in src.messages([tm.image]):
                if window and not lo <= log_ns <= hi:
                    continue
                msg = decode()
                where = f"{bag}: topic {tm.image}"
                rec.set_time("dataset_time", duration=stamp_s(msg) - t0)
                rec.log("bag/image", rr.Image(as_rgb8(decode_image(msg, where), where)))
                images += 1
            close_recording(rec, tmp, out)
    return images


def _side_by_side_blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(rrb.Vertical(
        rrb.Horizontal(rrb.Spatial2DView(origin="bag/image", name="bag: camera as recorded"),
                       rrb.Spatial2DView(origin="world/camera/image", name="dataset: stored frame"),
                       rrb.Spatial3DView(origin="world", name="end effector: bag tf (blue) and stored")),
        rrb.Horizontal(rrb.TimeSeriesView(origin="bag/joints", name="bag: joint states"),
                       rrb.TimeSeriesView(origin="joints", name="dataset: joints per frame"),
                       rrb.TextDocumentView(origin="task", name="task")),
        row_shares=[3, 2]), collapse_panels=True)
