"""A LeRobotDataset v3.0 of every frame, written with pyarrow as the frames are read (one episode in memory).

    meta/info.json                                  codebase_version v3.0, fps, features, totals, path templates
    meta/stats.json                                 per feature: min, max, mean, std, count
    meta/tasks.parquet                              index: task (string), column task_index
    meta/episodes/chunk-000/file-000.parquet        per episode: episode_index, tasks, length, where its frames are
                                                    (data/chunk_index, data/file_index, dataset_from/to_index),
                                                    stats/<feature>/<stat>
    data/chunk-{c:03d}/file-{f:03d}.parquet         one row per frame; a new file past data_files_size_in_mb

    videos/<key>/chunk-000/file-{f:03d}.mp4         the cameras as LeRobot records them (lerobot_video.py); with
                                                    images="png" they are PNG in the data files instead
    meta/info.json "calibration"                    per camera, of the first episode: intrinsics (fx, fy, cx, cy,
                                                    distortion model and coefficients), extrinsics (T_base_camera,
                                                    row-major) and their frames; "adlpipe": the topic map
    README.md                                       the dataset card, as LeRobot writes one

Per frame: observation.images.rgb (video, or PNG; in a dataset of several cameras, observation.images.<name> for
each camera instead: the other cameras' frames nearest each frame of the first one, black where none),
observation.images.depth (16-bit PNG, millimetres, 0 = no return; when the dataset has depth),
observation.images.affordance (8-bit PNG of the map; when it has maps; with maps="video" both are MP4 video instead,
grey in 3 channels, depth at DEPTH_VIDEO_MM a level: lossy, for readers that take video features only; maps="none"
leaves both out), observation.state (end effector x, y, z in the base frame, the joints, the gripper; NaN where a
bag had no sample near the frame), action (the end effector's position at the next frame; the last frame repeats its
own), observation.camera_timestamp (the camera's stamp, s from the episode's first frame: jitter and dropped
stretches show here), timestamp (frame_index / fps, LeRobot's convention), frame_index, episode_index, index,
task_index. PNG images are stored in the parquet files as Hugging Face `datasets` Image structs ({bytes, path}),
as LeRobot does for image features; depth and affordance maps are by default (lossless). Per episode, beside
LeRobot's columns: adlpipe/name, and adlpipe/<camera>/K and adlpipe/<camera>/T_base_camera (its calibration, row-major).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..dataset import schema
from ..plumbing.errors import AdlError
from .lerobot_video import VIDEO_FILE_MB, VIDEO_PATH, VideoFiles, video_feature

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000  # files per chunk folder
DATA_FILE_MB = 100  # a data file is closed after this much
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
MAPS = ("png", "video", "none")  # how the depth and affordance maps are exported
DEPTH_VIDEO_MM = 20  # a depth video's grey level is this many mm (8 bits: 0-5.1 m, the default scenes' 95th
# percentile is 3.8 m; PNG keeps 16-bit mm)
RGB, DEPTH, AFFORDANCE = "observation.images.rgb", "observation.images.depth", "observation.images.affordance"
STATE, ACTION = "observation.state", "action"
INTERVENTION = "intervention"  # an operator drove at the frame (false in episodes recorded without the flag)
CAMERA_TIMESTAMP = "observation.camera_timestamp"  # the camera's stamp (timestamp is frame_index / fps, LeRobot's)
IMAGE_STRUCT = pa.struct([("bytes", pa.binary()), ("path", pa.string())])


class Moments:
    """Running min, max, mean and std over samples of a feature (per channel for images)."""

    def __init__(self) -> None:
        self.n = 0
        self.lo = self.hi = self.sum = self.sq = None

    def add(self, x: np.ndarray) -> None:
        """x: (N, D) samples; NaNs are left out."""
        x = x.astype(np.float64)
        ok = ~np.isnan(x)
        lo, hi = np.where(ok, x, np.inf).min(0), np.where(ok, x, -np.inf).max(0)
        s, sq, n = np.where(ok, x, 0).sum(0), np.where(ok, x * x, 0).sum(0), ok.sum(0)
        if self.lo is None:
            self.lo, self.hi, self.sum, self.sq, self.count = lo, hi, s, sq, n
        else:
            self.lo, self.hi = np.minimum(self.lo, lo), np.maximum(self.hi, hi)
            self.sum, self.sq, self.count = self.sum + s, self.sq + sq, self.count + n
        self.n += len(x)

    def merge(self, other: Moments) -> None:
        if other.lo is None:
            return
        if self.lo is None:
            self.lo, self.hi, self.sum, self.sq, self.count, self.n = (other.lo, other.hi, other.sum, other.sq,
                                                                      other.count, other.n)
            return
        self.lo, self.hi = np.minimum(self.lo, other.lo), np.maximum(self.hi, other.hi)
        self.sum, self.sq, self.count, self.n = (self.sum + other.sum, self.sq + other.sq,
                                                 self.count + other.count, self.n + other.n)

    def stats(self, image: bool) -> dict[str, list]:
        c = np.maximum(self.count, 1)
        mean = self.sum / c
        std = np.sqrt(np.maximum(self.sq / c - mean * mean, 0))
        shape = (-1, 1, 1) if image else (-1,)  # LeRobot keeps image stats per channel as (C, 1, 1)
        out = {"min": self.lo, "max": self.hi, "mean": mean, "std": std}
        return {**{k: np.where(np.isfinite(v), v, np.nan).reshape(shape).tolist() for k, v in out.items()},
                "count": [int(self.n)]}


def png(image: np.ndarray) -> dict[str, object]:
    ok, buf = cv2.imencode(".png", image[..., ::-1] if image.ndim == 3 else image)
    if not ok:
        raise AdlError("cannot encode a frame as PNG")
    return {"bytes": buf.tobytes(), "path": None}


@dataclass
class Layout:
    """What the export holds, decided from the dataset before the first frame is written."""

    size: int
    joint_names: list[str]
    depth: bool
    affordance: bool
    fps: int
    cameras: list[str] = field(default_factory=list)  # every camera's name when there are several, else empty
    video: bool = True  # the cameras as MP4 video (LeRobot's own form), else PNG in the data files
    maps_video: bool = False  # depth and affordance as MP4 video (8-bit grey, lossy), else PNG in the data files
    intervention: bool = False  # an operator's take-over flag per frame (LeRobot's `intervention`; HG-DAgger bags)

    def image_key(self, camera: str) -> str:
        return f"observation.images.{camera}" if self.cameras else RGB

    def features(self) -> dict[str, dict]:
        img = {"dtype": "image", "names": ["height", "width", "channels"]}
        camera = video_feature(self.size, self.fps) if self.video else {**img, "shape": [self.size, self.size, 3]}
        f: dict[str, dict] = {self.image_key(c): camera for c in self.cameras or ["rgb"]}
        if self.depth:
            f[DEPTH] = (video_feature(self.size, self.fps, depth_mm_per_level=DEPTH_VIDEO_MM) if self.maps_video else
                        {**img, "shape": [self.size, self.size, 1], "info": {"is_depth_map": True, "unit": "mm"}})
        if self.affordance:
            f[AFFORDANCE] = (video_feature(self.size, self.fps) if self.maps_video else
                             {**img, "shape": [self.size, self.size, 1]})
        state = ["ee_x", "ee_y", "ee_z", *self.joint_names, "gripper"]
        f[STATE] = {"dtype": "float32", "shape": [len(state)], "names": state}
        f[ACTION] = {"dtype": "float32", "shape": [3], "names": ["ee_x", "ee_y", "ee_z"]}
        f[CAMERA_TIMESTAMP] = {"dtype": "float32", "shape": [1], "names": None}
        if self.intervention:
            f[INTERVENTION] = {"dtype": "bool", "shape": [1], "names": None}
        for key, dtype in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                           ("index", "int64"), ("task_index", "int64")):
            f[key] = {"dtype": dtype, "shape": [1], "names": None}
        return f

    def video_keys(self) -> list[str]:
        return [k for k, v in self.features().items() if v["dtype"] == "video"]

    def schema(self) -> pa.Schema:
        feats = {k: v for k, v in self.features().items() if v["dtype"] != "video"}  # videos live in videos/
        fields = [pa.field(k, IMAGE_STRUCT) for k, v in feats.items() if v["dtype"] == "image"]
        fields += [pa.field(STATE, pa.list_(pa.float32(), len(feats[STATE]["names"]))),
                   pa.field(ACTION, pa.list_(pa.float32(), 3)), pa.field(CAMERA_TIMESTAMP, pa.float32()),
                   pa.field("timestamp", pa.float32())]
        fields += [pa.field(INTERVENTION, pa.bool_())] if self.intervention else []
        fields += [pa.field(k, pa.int64()) for k in ("frame_index", "episode_index", "index", "task_index")]
        hf = {"info": {"features": {k: ({"_type": "Image"} if v["dtype"] == "image" else
                                        {"feature": {"dtype": "float32", "_type": "Value"}, "length": v["shape"][0],
                                         "_type": "Sequence"} if k in (STATE, ACTION) else
                                        {"dtype": v["dtype"], "_type": "Value"}) for k, v in feats.items()}}}
        return pa.schema(fields, metadata={"huggingface": json.dumps(hf)})


def plan(f: h5py.File, names: list[str], video: bool = True, maps: str = "png") -> Layout:
    """Decide the features from the episodes' small arrays; every episode must have the same joints."""
    if maps not in MAPS:
        raise AdlError(f"maps {maps!r}: one of {', '.join(MAPS)}")
    joints: list[str] | None = None
    cameras: list[str] | None = None
    depth = affordance = intervention = False
    rates = []
    for n in names:
        g = f[schema.EPISODES][n]
        jn = [str(j) for j in g["series/joint_pos"].attrs["joint_names"]]
        if joints is None:
            joints = jn
        elif jn != joints:
            raise AdlError(f"episode {n}: joints {jn} differ from {joints} of the first episode; a LeRobot dataset "
                           "has one state vector: export the robots' episodes separately (--episodes)")
        names_of = schema.camera_names(g)
        if cameras is None:
            cameras = names_of
        elif names_of != cameras:
            raise AdlError(f"episode {n}: cameras {names_of} differ from {cameras} of the first episode; a LeRobot "
                           "dataset has one set of image keys: export them separately (--episodes)")
        fr = _frames_checked(g, n)  # every episode checked before anything is written
        depth |= bool(g.attrs.get("has_depth", False)) and "depth" in fr and len(fr["depth"]) > 0
        affordance |= bool(g.attrs.get("has_affordance", False)) and "affordance" in fr and len(fr["affordance"]) > 0
        intervention |= "intervention" in fr
        t = fr["t"][()]
        if len(t) > 1:
            interval = float(np.median(np.diff(t)))
            if interval <= 0:
                raise AdlError(f"episode {n}: its frame stamps do not advance (median interval {interval} s); "
                               "re-ingest its bag")
            rates.append(1.0 / interval)
    fps = max(1, int(round(float(np.median(rates))))) if rates else 1
    several = cameras if cameras and len(cameras) > 1 else []
    keep = maps != "none"
    return Layout(int(f.attrs["image_size"]), joints or [], depth and keep, affordance and keep, fps, several, video,
                  maps_video=maps == "video", intervention=intervention)


class Export:
    """Writes episodes one after another into the v3 layout under `root` (which must not exist yet)."""

    def __init__(self, root: Path, layout: Layout, tasks: list[str]) -> None:
        self.root, self.layout = root, layout
        self.task_index = {t: i for i, t in enumerate(tasks)}
        self.schema = layout.schema()
        self.frames = 0
        self.chunk = self.file = 0
        self.writer: pq.ParquetWriter | None = None
        self.episodes: list[dict] = []
        self.totals: dict[str, Moments] = {}
        self.videos = {k: VideoFiles(root, k, layout.size, layout.fps) for k in layout.video_keys()}
        self.calibration: dict[str, dict] = {}
        self.topic_map: str | None = None

    def _data_file(self) -> pq.ParquetWriter:
        if self.writer is not None and self.path.stat().st_size > DATA_FILE_MB * 1e6:
            self.writer.close()
            self.writer = None
            self.file += 1
            if self.file >= CHUNKS_SIZE:
                self.chunk, self.file = self.chunk + 1, 0
        if self.writer is None:
            self.path = self.root / DATA_PATH.format(chunk_index=self.chunk, file_index=self.file)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = pq.ParquetWriter(self.path, self.schema)
        return self.writer

    def add(self, g: h5py.Group, index: int) -> None:
        """Episode `index` from its HDF5 group: one row group of its frames."""
        name = g.name.split("/")[-1]
        fr = _frames_checked(g, name)
        t = fr["t"][()]
        T = len(t)
        ee = fr["ee_pos"][()].astype(np.float32)
        joints = fr["joint_pos"][()].astype(np.float32).reshape(T, -1)
        gripper = fr["gripper"][()].astype(np.float32).reshape(T, 1)
        state = np.concatenate([ee, joints, gripper], 1)
        action = np.concatenate([ee[1:], ee[-1:]], 0)
        task = str(g.attrs["task"])
        stats = {STATE: Moments(), ACTION: Moments(), CAMERA_TIMESTAMP: Moments()}
        stats[STATE].add(state)
        stats[ACTION].add(action)
        stats[CAMERA_TIMESTAMP].add(t.reshape(-1, 1))  # the camera's own stamps: jitter and gaps, in meta/stats
        # one frame decoded at a time; the episode's PNG bytes are what is held
        images = {self.layout.image_key(schema.camera_names(g)[0]): ((fr["rgb"][k] for k in range(T)), 255.0)}
        blank = np.zeros((self.layout.size, self.layout.size), np.float32)
        for cam in self.layout.cameras[1:]:
            cf = g[f"{schema.CAMERAS}/{cam}/frames"]
            images[self.layout.image_key(cam)] = (_synced(cf["rgb"], cf["index"][()],
                                                          np.zeros((*blank.shape, 3), np.uint8)), 255.0)
        if self.layout.depth:
            di = fr["depth_index"][()] if "depth_index" in fr else np.full(T, -1)
            depth = _synced(fr["depth"], di, blank.astype(np.uint16))
            images[DEPTH] = ((_grey_rgb(np.round(d / DEPTH_VIDEO_MM)) for d in depth), 1.0) \
                if self.layout.maps_video else (depth, 1.0)  # video: grey levels of DEPTH_VIDEO_MM; PNG: mm
        if self.layout.affordance:
            maps = _synced(fr["affordance"], fr["affordance_index"][()], blank)
            grey = ((np.clip(np.nan_to_num(a), 0, 1) * 255).round().astype(np.uint8) for a in maps)
            images[AFFORDANCE] = (((_grey_rgb(a) for a in grey) if self.layout.maps_video else grey), 255.0)
        cols: dict[str, list] = {}
        ep: dict = {}
        for key, (frames, scale) in images.items():
            if key in self.videos:
                stats[key] = Moments()
                ep.update(self.videos[key].add(_counted(frames, stats[key], scale)))
            else:
                cols[key], stats[key] = _image_column(frames, scale)
        writer = self._data_file()
        table = pa.table({
            **{k: pa.array(v, IMAGE_STRUCT) for k, v in cols.items()},
            STATE: pa.array(list(state), self.schema.field(STATE).type),
            ACTION: pa.array(list(action), self.schema.field(ACTION).type),
            CAMERA_TIMESTAMP: pa.array(t.astype(np.float32), pa.float32()),
            "timestamp": pa.array((np.arange(T) / self.layout.fps).astype(np.float32), pa.float32()),
            "frame_index": pa.array(np.arange(T), pa.int64()),
            "episode_index": pa.array(np.full(T, index), pa.int64()),
            "index": pa.array(np.arange(self.frames, self.frames + T), pa.int64()),
            "task_index": pa.array(np.full(T, self.task_index[task]), pa.int64()),
            **({INTERVENTION: pa.array(fr["intervention"][()].astype(bool) if "intervention" in fr
                                       else np.zeros(T, bool), pa.bool_())} if self.layout.intervention else {}),
        }, schema=self.schema)
        writer.write_table(table)
        ep = {"episode_index": index, "tasks": [task], "length": T, "data/chunk_index": self.chunk,
              "data/file_index": self.file, "dataset_from_index": self.frames, "dataset_to_index": self.frames + T,
              "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0, "adlpipe/name": g.name.split("/")[-1],
              **ep, **self._calibrate(g)}
        for key, m in stats.items():
            image = key.startswith("observation.images.")
            for stat, v in m.stats(image).items():
                ep[f"stats/{key}/{stat}"] = v
            self.totals.setdefault(key, Moments()).merge(m)
        self.episodes.append(ep)
        self.frames += T

    def _calibrate(self, g: h5py.Group) -> dict:
        """The episode's calibration columns; the first episode's also goes into info.json."""
        cols = {}
        for cam in schema.camera_names(g):
            view = schema.read_camera(g, cam)
            cols[f"adlpipe/{cam}/K"] = view.K.ravel().tolist()
            cols[f"adlpipe/{cam}/T_base_camera"] = view.T_base_camera.ravel().tolist()
            self.calibration.setdefault(cam, {
                "intrinsics": {"fx": float(view.K[0, 0]), "fy": float(view.K[1, 1]), "cx": float(view.K[0, 2]),
                               "cy": float(view.K[1, 2]), "width": self.layout.size, "height": self.layout.size,
                               "distortion_model": view.lens.model or "pinhole", "D": list(view.lens.D)},
                # T_base_camera, row-major: the camera's optical frame in the base frame
                "extrinsics": view.T_base_camera.ravel().tolist(),
                "extrinsics_frames": {"parent": str(g.attrs["base_frame"]), "child": view.camera_frame}})
        if self.topic_map is None:
            self.topic_map = str(g.attrs.get("topic_map", ""))
        return cols

    def abort(self) -> None:
        """A failed export (a full disk, a Ctrl-C): drop the open writers without flushing them, so none writes again
        from its finaliser (pyarrow's ParquetWriter.__del__ printed a trace after the stage's one line)."""
        writer, self.writer = self.writer, None
        if writer is not None:
            with contextlib.suppress(Exception):
                writer.close()
        for videos in self.videos.values():
            with contextlib.suppress(Exception):
                videos.close()

    def finish(self) -> dict:
        """Close the data and video files and write meta/ (info, stats, tasks, episodes) and the dataset card."""
        if self.writer is not None:
            self.writer.close()
        for videos in self.videos.values():
            videos.close()
        meta = self.root / "meta"
        meta.mkdir(parents=True, exist_ok=True)
        feats = self.layout.features()
        info = {"codebase_version": CODEBASE_VERSION, "robot_type": None, "total_episodes": len(self.episodes),
                "total_frames": self.frames, "total_tasks": len(self.task_index), "chunks_size": CHUNKS_SIZE,
                "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
                "fps": self.layout.fps, "splits": {"train": f"0:{len(self.episodes)}"}, "data_path": DATA_PATH,
                "video_path": VIDEO_PATH if self.videos else None, "features": feats,
                "calibration": self.calibration,
                "adlpipe": {"topic_map": json.loads(self.topic_map) if self.topic_map else None}}
        (meta / "info.json").write_text(json.dumps(info, indent=4))
        (self.root / "README.md").write_text(dataset_card(info))
        stats = {k: m.stats(k.startswith("observation.images.")) for k, m in self.totals.items()}
        (meta / "stats.json").write_text(json.dumps(stats, indent=4, allow_nan=True))
        write_tasks(meta / "tasks.parquet", sorted(self.task_index, key=self.task_index.get))
        eps = self.root / EPISODES_PATH
        eps.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist(self.episodes), eps)
        return info


def _frames_checked(g: h5py.Group, name: str) -> h5py.Group:
    """The episode's frames group (its arrays and their layout were checked when the dataset was opened:
    frames.check_frames), or one line naming the episode: no frames group, or no frame at all."""
    if "frames" not in g or not isinstance(g["frames"], h5py.Group):
        raise AdlError(f"episode {name}: no frames group (ingested without frames?); re-ingest its bag")
    fr = g["frames"]
    if len(fr["t"]) == 0:
        raise AdlError(f"episode {name}: no frames to export")
    return fr


def _synced(images: h5py.Dataset, index: np.ndarray, blank: np.ndarray) -> Iterator[np.ndarray]:
    """The image synced to each frame (index -1: none, the blank image instead)."""
    return (images[int(i)] if i >= 0 else blank for i in index)


def _grey_rgb(image: np.ndarray) -> np.ndarray:
    """A one-channel map as the RGB frame a video stream takes (clipped to 0-255: depth past 255 levels of
    DEPTH_VIDEO_MM saturates)."""
    grey = np.clip(image, 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)


def _counted(frames: Iterable[np.ndarray], moments: Moments, scale: float) -> Iterator[np.ndarray]:
    """The frames, passed on one at a time, their per-channel statistics (values / scale; at most ~4,096 pixels a
    frame) into `moments`."""
    for image in frames:
        channels = image.shape[2] if image.ndim == 3 else 1
        moments.add(image.reshape(-1, channels)[:: max(1, image.size // channels // 4096)] / scale)
        yield image


def dataset_card(info: dict) -> str:
    """README.md as LeRobot writes a dataset's card: the Hub's front matter (robotics, the LeRobot tag, the data
    files), what it holds and meta/info.json."""
    cameras = ", ".join(k for k, v in info["features"].items() if v["dtype"] in ("video", "image"))
    shown = {k: v for k, v in info.items() if k not in ("calibration", "adlpipe")}
    return "\n".join([
        "---", "license: other", "task_categories:", "- robotics", "tags:", "- LeRobot", "- adlpipe", "configs:",
        "- config_name: default", "  data_files: data/*/*.parquet", "---", "",
        "This dataset was exported by adlpipe (`python -m adlpipe.export`) from ROS bags, in the layout of",
        "[LeRobot](https://github.com/huggingface/lerobot) datasets v3.0. Set its license before you share it.", "",
        "## Dataset Description", "",
        f"- **Episodes:** {info['total_episodes']}, **frames:** {info['total_frames']} at {info['fps']} fps, "
        f"**tasks:** {info['total_tasks']}",
        f"- **Cameras:** {cameras}; their intrinsics and extrinsics are in `meta/info.json` under `calibration`, "
        "the topic map under `adlpipe`",
        f"- **observation.state:** {', '.join(info['features']['observation.state']['names'])}",
        "- **action:** the end effector's position at the next frame", "",
        "## Dataset Structure", "", "[meta/info.json](meta/info.json):", "```json", json.dumps(shown, indent=4), "```",
        ""])


def _image_column(frames: Iterable[np.ndarray], scale: float) -> tuple[list[dict], Moments]:
    """PNG structs of the frames and their per-channel statistics (as _counted)."""
    moments = Moments()
    return [png(image) for image in _counted(frames, moments, scale)], moments


def write_tasks(path: Path, tasks: list[str]) -> None:
    """tasks.parquet as pandas writes a DataFrame indexed by task (LeRobot's layout): a task_index column and the
    task strings as the index, so pd.read_parquet gives them back as the index."""
    pandas_meta = {"index_columns": ["task"], "column_indexes": [], "columns": [
        {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
         "metadata": None},
        {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": None}],
        "creator": {"library": "pyarrow", "version": pa.__version__}}
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": pa.array(tasks, pa.string())})
    pq.write_table(table.replace_schema_metadata({"pandas": json.dumps(pandas_meta)}), path)
