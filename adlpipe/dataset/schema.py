"""The HDF5 dataset schema, written down once (docs/reference/hdf5_schema.md describes the same layout).

A dataset is an index file (`adl.h5`) and a folder of episode files beside it (`adl.shards/<run>/<bag>.h5`, one
per bag, one run folder per ingest: adlpipe.dataset.shards). The index links each episode group to its file
(an HDF5 external link), so readers open the index and see every episode under /episodes.

    /                          attrs: format_version, n_waypoints, image_size
    /catalog/{name,key,task,file}  one row per episode: what dedup and the split read without opening the files
    /episodes/<name>/          one group per bag (or per demonstration of a segmented bag);
                               <name> = "<task_slug>-<sha256[:16]>" [+ "-s<segment>"]
        attrs: task, source_path, source_sha256, source_format, duration_s, stamp0_ns, base_frame,
               camera_frame, has_depth, has_affordance, note (what a --recover ingest lost),
               distortion_model (CameraInfo's: plumb_bob, rational_polynomial, equidistant; "" = pinhole)
        rgb          (H, W, 3) uint8     first camera frame, resized to image_size
        depth        (H, W)    float32   metres, NaN = no return (only if has_depth)
        affordance   (H, W)    float32   [0, 1] Gaussian blobs (zeros if the bag had none)
        traj3d       (N, 3)    float32   end-effector path in base_frame, metres, N waypoints evenly in time
        traj2d       (N, 2)    float32   traj3d projected into rgb, pixels (u right, v down), through the lens
        K            (3, 3)    float64   intrinsics of the stored rgb
        D            (k,)      float64   distortion coefficients of distortion_model (empty: pinhole)
        T_base_camera (4, 4)   float64   camera optical frame pose in base_frame
        objects      (M, 7)    float64   initial pose (x y z qw qx qy qz) in base_frame; attr names
        series/ee_t  (P,) float64 s from the first image; series/ee_pos (P, 3) base_frame
        series/joint_t (Q,) float64; series/joint_pos (Q, J) float64; attr joint_names
        frames/...   every camera frame, synced (adlpipe.dataset.frames)
        cameras/<name>/  the topic map's other cameras (a wrist camera beside the scene camera); attrs
                     camera_frame, distortion_model; K, D, T_base_camera (at the first image), traj2d (traj3d
                     seen by this camera, through its lens); frames/ its own frames (adlpipe.dataset.frames)
        attr camera_name: the name of the camera stored at the top level ("camera" for a one-camera map)
        attrs topic_map (the map it was ingested with, JSON), window_ns (a segment's log-time span, ns)
"""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..geometry.camera import PINHOLE, Lens, read_lens
from ..plumbing.errors import AdlError, one_line
from .frames import CAMERAS, check_camera_frames, check_frames

FORMAT_VERSION = 2  # 2: every frame, sharded; 1: the first frame only, one file
EPISODES = "episodes"


@dataclass
class CameraView:
    """One more camera of an episode: its model, its pose at the first image and the trajectory as it sees it."""

    name: str
    camera_frame: str
    K: np.ndarray
    T_base_camera: np.ndarray
    traj2d: np.ndarray
    lens: Lens = PINHOLE


@dataclass
class Episode:
    task: str
    source_path: str
    source_sha256: str
    source_format: str
    duration_s: float
    stamp0_ns: int
    base_frame: str
    camera_frame: str
    rgb: np.ndarray
    affordance: np.ndarray
    traj3d: np.ndarray
    traj2d: np.ndarray
    K: np.ndarray
    T_base_camera: np.ndarray
    depth: np.ndarray | None = None
    has_affordance: bool = True
    object_names: list[str] = field(default_factory=list)
    objects: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    ee_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ee_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    joint_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    joint_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    joint_names: list[str] = field(default_factory=list)
    note: str = ""  # e.g. what a --recover ingest of a truncated bag lost
    segment: int = -1  # the demonstration's index in a bag holding several; -1: the whole bag
    lens: Lens = PINHOLE  # the camera's distortion (CameraInfo's model and d): traj2d is where points appear
    camera_name: str = "camera"  # the topic map's name for the camera above
    cameras: list[CameraView] = field(default_factory=list)  # the map's other cameras
    topic_map: str = ""  # the topic map it was ingested with (JSON): what doctor --verify reads the bag with again
    window_ns: tuple[int, int] | None = None  # one demonstration of several in the bag: its log-time span

    @property
    def name(self) -> str:
        return episode_name(self.task, self.source_sha256, self.segment)

    @property
    def key(self) -> str:
        """What makes an episode the same on a re-ingest: its bag's sha256 and its segment."""
        return episode_key(self.source_sha256, self.segment)


def safe_name(text: str, limit: int = 40) -> str:
    """An HDF5-safe name component: letters, digits and '_' only (no '/', '.', or path tricks)."""
    return (re.sub(r"[^A-Za-z0-9_]+", "_", text).strip("_") or "unnamed")[:limit]


def episode_name(task: str, sha256: str, segment: int = -1) -> str:
    return f"{safe_name(task)}-{sha256[:16]}" + (f"-s{segment:03d}" if segment >= 0 else "")


def episode_key(sha256: str, segment: int = -1) -> str:
    return sha256 if segment < 0 else f"{sha256}#{segment}"


def create_file(f: h5py.File, n_waypoints: int, image_size: int) -> None:
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["n_waypoints"] = n_waypoints
    f.attrs["image_size"] = image_size
    f.require_group(EPISODES)


def check_file(f: h5py.File, path: str, n_waypoints: int | None = None, image_size: int | None = None) -> None:
    """Refuse files of another format version or with other waypoint/image settings than asked for."""
    version = f.attrs.get("format_version")
    if version == 1:
        raise AdlError(f"{path}: dataset of format version 1 (first frame only); this adlpipe reads version "
                       f"{FORMAT_VERSION} (every frame): re-ingest the bags into a new file "
                       "(python -m adlpipe.ingest BAGS -o NEW.h5)")
    if version != FORMAT_VERSION or EPISODES not in f:
        raise AdlError(f"{path}: not an adlpipe dataset of format version {FORMAT_VERSION} (found {version})")
    for key, want in (("n_waypoints", n_waypoints), ("image_size", image_size)):
        try:
            value = int(f.attrs[key])
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise AdlError(f"{path}: no readable integer '{key}' attribute ({one_line(exc)}); not an adlpipe dataset "
                           "or a damaged one") from None
        if value <= 0:
            raise AdlError(f"{path}: {key}={value}; not an adlpipe dataset or a damaged one")
        if want is not None and value != want:
            raise AdlError(f"{path}: file has {key}={value}, asked for {want}; use a new output file")


# What h5py raises when a file's structure is damaged where it reads it (a header, a symbol table, a heap): the
# open file is readable but the object is not. DAMAGED adds the OS errors of a file HDF5 cannot open at all.
DAMAGED_STRUCTURE = (KeyError, RuntimeError, ValueError, TypeError, SystemError)
DAMAGED = (*DAMAGED_STRUCTURE, OSError)


def raise_if_interrupted(exc: BaseException) -> None:
    """A Ctrl-C that lands inside h5py's compiled code comes out as a SystemError ("returned a result with an
    exception set") whose cause is the KeyboardInterrupt: an interrupt, not damage. Raise it as the interrupt."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            raise KeyboardInterrupt from None
        seen.add(id(e))
        e = e.__cause__ or e.__context__


# Episode attributes readers take as one value: name -> numpy dtype kinds (text; bool, integer, float).
SCALAR_ATTRS = {"task": "OSU", "has_depth": "biuf", "has_affordance": "biuf", "duration_s": "biuf",
                "stamp0_ns": "biu", "segment": "biu"}


def _scalar_of(value: object, kinds: str) -> bool:
    if isinstance(value, str):
        return "U" in kinds
    a = np.asarray(value)
    return a.ndim == 0 and a.dtype.kind in kinds and (a.dtype.kind != "f" or bool(np.isfinite(a)))


REQUIRED = {"rgb": 3, "affordance": 2, "traj3d": 2, "traj2d": 2, "K": 2, "T_base_camera": 2, "objects": 2}


@contextmanager
def open_dataset(path: Path | str, names: list[str] | None = None) -> Iterator[h5py.File]:
    """Open an adlpipe dataset for reading, or fail with one line saying what is wrong with it: missing, a folder,
    empty, not HDF5, unreadable, another format, episodes missing, malformed or holding non-finite trajectories.
    `names`: the episodes the caller will read (all of them if None)."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise AdlError(f"{path}: no such dataset; run python -m adlpipe.ingest first") from None
    except OSError as exc:
        raise AdlError(f"{path}: cannot open dataset ({exc.strerror})") from None
    if stat.S_ISDIR(st.st_mode):
        raise AdlError(f"{path}: is a folder, not an HDF5 dataset file")
    if not stat.S_ISREG(st.st_mode):
        raise AdlError(f"{path}: not a regular file")
    if st.st_size == 0:
        raise AdlError(f"{path}: empty file, not an HDF5 dataset")
    try:
        f = h5py.File(path, "r")
    except PermissionError:
        raise AdlError(f"{path}: permission denied") from None
    except OSError as exc:
        raise AdlError(f"{path}: not an HDF5 file ({one_line(exc, 120)})") from None
    with f:
        try:
            check_file(f, str(path))
            present = set(f[EPISODES].keys())
            wanted = episode_names(f) if names is None else list(names)
            missing = [n for n in wanted if n not in present]
            if missing:
                raise AdlError(f"{path}: {len(missing)} episode(s) named by the split are not in the dataset "
                               f"(e.g. {missing[0]!r}); re-run python -m adlpipe.split on this file")
            files = {n: episode_path(path, f, n) for n in present}  # every link resolved and confined (no file is
            # opened for this) before HDF5 follows any of them
        except DAMAGED as exc:
            raise_if_interrupted(exc)
            raise AdlError(f"{path}: the dataset's index is damaged ({one_line(exc)}); ingest the bags again into "
                           "a new dataset") from None
        for n in wanted:
            check_episode_file(path, f, n, files[n])
        yield f


def check_episode_file(path: Path, f: h5py.File, name: str, file: Path) -> None:
    """Episode `name` of the open index `f` readable from its own file `file` (episode_path), self-contained and
    well formed; one line naming the episode and the file otherwise."""
    try:
        g = f[EPISODES][name]
    except DAMAGED as exc:  # truncated, emptied, not HDF5, unreadable: HDF5 cannot open it
        raise_if_interrupted(exc)
        prefix = os.environ.get("HDF5_EXT_PREFIX")
        link = f[EPISODES].get(name, getlink=True)
        if prefix and any((Path(p) / getattr(link, "filename", "")).exists() for p in prefix.split(os.pathsep)):
            # HDF5 looked for the episode's file under this prefix first: what it could not read (a file, a
            # folder) is not ours
            raise AdlError(f"{path}: episode {name}: HDF5_EXT_PREFIX={prefix} sends HDF5 to its file's name "
                           f"there, which cannot be read ({one_line(exc)}); unset HDF5_EXT_PREFIX to read {file}") \
                from None
        raise AdlError(f"{path}: episode {name}: its file {file} cannot be read ({one_line(exc)}); re-ingest its bag "
                       "into a new dataset, or leave it out (python -m adlpipe.split --skip-bad)") from None
    if Path(g.file.filename).resolve() != file:
        raise AdlError(f"{path}: episode {name}: HDF5 opened {g.file.filename} instead of {file}")
    try:
        check_self_contained(g.file, f"{path}: episode {name}")
        check_episode(g, f"{path}:{name}")
    except DAMAGED as exc:
        raise_if_interrupted(exc)
        raise AdlError(f"{path}: episode {name}: its file {file} is damaged ({one_line(exc)}); re-ingest its bag "
                       "into a new dataset, or leave it out (python -m adlpipe.split --skip-bad)") from None


def readable_episodes(path: Path | str, names: list[str] | None = None) -> tuple[list[str], list[str]]:
    """(the episodes of `names` (all if None) that open_dataset would read, one line for each that it would
    refuse): what a stage given --skip-bad goes on with. The dataset itself must be readable."""
    path = Path(path)
    with open_dataset(path, names=[]) as f:
        wanted = episode_names(f) if names is None else list(names)
        good, bad = [], []
        for n in wanted:
            try:
                if n not in f[EPISODES]:
                    raise AdlError(f"{path}: episode {n} is not in the dataset")
                check_episode_file(path, f, n, episode_path(path, f, n))
                good.append(n)
            except AdlError as exc:
                bad.append(str(exc))
    return good, bad


def shards_root(index: Path) -> Path:
    """adl.h5 -> adl.shards beside it: the only folder a dataset's episode files may lie in."""
    return index.with_name(index.stem + ".shards") if index.suffix else index.with_name(index.name + ".shards")


def episode_path(index: Path | str, f: h5py.File, name: str) -> Path:
    """The file holding episode `name`, resolved by adlpipe rather than by HDF5's link search path (which tries
    HDF5_EXT_PREFIX first and the current folder last): a relative link to /episodes/<name> in a file that exists
    inside a .shards folder beside the index (after resolving symlinks). Anything else is one line naming the
    episode and the target."""
    index = Path(index)
    link = f[EPISODES].get(name, getlink=True)
    if isinstance(link, h5py.HardLink):  # an episode stored in the index itself
        return index.resolve()
    if not isinstance(link, h5py.ExternalLink):
        raise AdlError(f"{index}: episode {name}: a {type(link).__name__}, not a link into {shards_root(index).name}/")
    target = str(link.filename)
    if link.path != f"/{EPISODES}/{name}":
        raise AdlError(f"{index}: episode {name}: links to {link.path!r} in {target}, not to its own group")
    # its own <stem>.shards, or the .shards folder beside it that the link names (an index copied under another
    # name keeps linking into the folder it was written with)
    first = Path(target).parts[0] if Path(target).parts else ""
    root = index.parent / first if first.endswith(".shards") and first not in (".", "..") else shards_root(index)
    return confined_file(index.parent, target, root,
                         outside=f"{index}: episode {name}: links to {target}, outside the dataset's {root.name} "
                         "folder; refused (a dataset reads only its own files)",
                         missing=f"{index}: episode {name}: its file {index.parent / target} is missing (was "
                         f"{root.name}/ moved, renamed or deleted apart from the index?)")


def confined_file(base: Path, relative: str, root: Path, outside: str, missing: str) -> Path:
    """`relative` resolved from `base`, which must be a file inside `root` once symlinks are resolved; otherwise
    the one-line error `outside` (absolute, or out of `root`) or `missing` (no file there)."""
    resolved = (base / relative).resolve()
    if Path(relative).is_absolute() or not resolved.is_relative_to(root.resolve()):
        raise AdlError(outside)
    if not resolved.is_file():
        raise AdlError(missing)
    return resolved


def check_self_contained(f: h5py.File, where: str) -> None:
    """An episode file must hold its own bytes: no dataset with external raw storage (it reads any file the user
    can), no virtual dataset, no link into another file."""
    if f.filename in _CHECKED:
        return
    bad: list[str] = []

    def visit(name: str, link: object) -> None:
        if isinstance(link, h5py.ExternalLink):
            bad.append(f"{name} links to {link.filename}")
            return
        if isinstance(link, h5py.HardLink):
            obj = f.get(name)
            if isinstance(obj, h5py.Dataset):
                if obj.external:
                    bad.append(f"{name} stores its data in {obj.external[0][0]!r}")
                elif obj.is_virtual:
                    bad.append(f"{name} is a virtual dataset over {obj.virtual_sources()[0].file_name!r}")

    f.visititems_links(visit)
    if bad:
        raise AdlError(f"{where}: {bad[0]}; refused (a dataset reads only its own files)")
    _CHECKED.add(f.filename)


_CHECKED: set[str] = set()  # episode files already checked by this process (a reader opens them again)


def check_episode(g: h5py.Group, where: str) -> None:
    """The datasets every reader needs, with the right number of axes and finite trajectories."""
    if not isinstance(g, h5py.Group):
        raise AdlError(f"{where}: not an episode group")
    for key, ndim in REQUIRED.items():
        if key not in g or not isinstance(g[key], h5py.Dataset) or g[key].ndim != ndim:
            raise AdlError(f"{where}: episode lacks a {ndim}-D '{key}' dataset")
    if "task" not in g.attrs:
        raise AdlError(f"{where}: episode has no 'task' attribute")
    for key, kinds in SCALAR_ATTRS.items():  # what readers take as one text, flag or number
        if key in g.attrs and not _scalar_of(g.attrs[key], kinds):
            raise AdlError(f"{where}: attribute '{key}' is {str(g.attrs[key])[:40]!r}, not one "
                           f"{'text' if kinds == 'OSU' else 'number'}; re-ingest its bag")
    h, w, c = g["rgb"].shape
    if c != 3 or h != w or g["affordance"].shape != (h, w) or ("depth" in g and g["depth"].shape != (h, w)):
        raise AdlError(f"{where}: first-frame images rgb {g['rgb'].shape} / affordance {g['affordance'].shape}, "
                       "expected (S, S, 3) / (S, S)")
    if "frames" in g:
        check_frames(g["frames"], where, h)
    t3, t2 = g["traj3d"], g["traj2d"]
    if t3.shape[1:] != (3,) or t2.shape != (t3.shape[0], 2):
        raise AdlError(f"{where}: traj3d/traj2d shapes {t3.shape}/{t2.shape}, expected (N, 3)/(N, 2)")
    if not (np.isfinite(t3[()]).all() and np.isfinite(t2[()]).all()):
        raise AdlError(f"{where}: non-finite values (NaN or inf) in the stored trajectory; re-ingest the bag")
    if CAMERAS in g:
        n_frames = g["frames"]["t"].shape[0] if "frames" in g else None
        for name in g[CAMERAS]:
            _check_camera(g[CAMERAS][name], f"{where}: camera {name}", h, t3.shape[0], n_frames)


def _check_camera(c: h5py.Group, where: str, size: int, n_waypoints: int, n_frames: int | None) -> None:
    """Another camera's group laid out as ingest writes it; one line naming the camera and the array otherwise."""
    want = {"K": (3, 3), "T_base_camera": (4, 4), "traj2d": (n_waypoints, 2), "D": None}
    for key, shape in want.items():
        d = c.get(key) if isinstance(c, h5py.Group) else None
        if not isinstance(d, h5py.Dataset) or (shape is not None and d.shape != shape) or d.dtype.kind != "f":
            raise AdlError(f"{where}: lacks a {shape or '1-D'} float '{key}' dataset; re-ingest its bag")
        if not np.isfinite(d[()]).all():
            raise AdlError(f"{where}: non-finite values in '{key}'; re-ingest its bag")
    if "camera_frame" not in c.attrs:
        raise AdlError(f"{where}: no 'camera_frame' attribute; re-ingest its bag")
    if n_frames is not None:
        check_camera_frames(c.get("frames"), where, size, n_frames)


def write_episode(g: h5py.Group, ep: Episode) -> None:
    """The episode's attributes, first-frame images, trajectories and series into its group (frames are written
    by adlpipe.dataset.frames)."""
    for key in ("task", "source_path", "source_sha256", "source_format", "base_frame", "camera_frame"):
        g.attrs[key] = getattr(ep, key)
    g.attrs["duration_s"] = float(ep.duration_s)
    g.attrs["stamp0_ns"] = int(ep.stamp0_ns)
    g.attrs["has_depth"] = ep.depth is not None
    g.attrs["has_affordance"] = bool(ep.has_affordance)
    g.attrs["note"] = ep.note
    g.attrs["segment"] = int(ep.segment)
    img = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
    g.create_dataset("rgb", data=ep.rgb.astype(np.uint8), **img)
    g.create_dataset("affordance", data=ep.affordance.astype(np.float32), **img)
    if ep.depth is not None:
        g.create_dataset("depth", data=ep.depth.astype(np.float32), **img)
    g.create_dataset("traj3d", data=ep.traj3d.astype(np.float32))
    g.create_dataset("traj2d", data=ep.traj2d.astype(np.float32))
    g.create_dataset("K", data=ep.K.astype(np.float64))
    g.attrs["distortion_model"] = ep.lens.model  # "" for the pinhole
    g.create_dataset("D", data=ep.lens.array().astype(np.float64))
    g.create_dataset("T_base_camera", data=ep.T_base_camera.astype(np.float64))
    obj = g.create_dataset("objects", data=ep.objects.astype(np.float64).reshape(-1, 7))
    obj.attrs["names"] = [str(n) for n in ep.object_names]
    s = g.create_group("series")
    s.create_dataset("ee_t", data=ep.ee_t.astype(np.float64))
    s.create_dataset("ee_pos", data=ep.ee_pos.astype(np.float64))
    s.create_dataset("joint_t", data=ep.joint_t.astype(np.float64))
    jp = s.create_dataset("joint_pos", data=ep.joint_pos.astype(np.float64))
    jp.attrs["joint_names"] = [str(n) for n in ep.joint_names]
    g.attrs["camera_name"] = ep.camera_name
    g.attrs["topic_map"] = ep.topic_map
    if ep.window_ns is not None:
        g.attrs["window_ns"] = np.asarray(ep.window_ns, np.int64)
    for cam in ep.cameras:
        c = g.require_group(f"{CAMERAS}/{cam.name}")
        c.attrs["camera_frame"] = cam.camera_frame
        c.attrs["distortion_model"] = cam.lens.model
        c.create_dataset("K", data=cam.K.astype(np.float64))
        c.create_dataset("D", data=cam.lens.array().astype(np.float64))
        c.create_dataset("T_base_camera", data=cam.T_base_camera.astype(np.float64))
        c.create_dataset("traj2d", data=cam.traj2d.astype(np.float32))


def camera_names(g: h5py.Group) -> list[str]:
    """Every camera of an episode group: the top-level one first, then cameras/<name> in name order."""
    return [str(g.attrs.get("camera_name", "camera")), *(sorted(g[CAMERAS]) if CAMERAS in g else [])]


def read_camera(g: h5py.Group, name: str) -> CameraView:
    """The model, first-frame pose and trajectory pixels of any camera of an episode group, the top-level one
    included."""
    c = g if name == camera_names(g)[0] else g[CAMERAS][name]
    return CameraView(name=name, camera_frame=str(c.attrs["camera_frame"]), K=c["K"][()],
                      T_base_camera=c["T_base_camera"][()], traj2d=c["traj2d"][()], lens=read_lens(c))


def read_episode(f: h5py.File, name: str) -> Episode:
    g = f[EPISODES][name]
    a = g.attrs
    s = g["series"]
    return Episode(
        task=str(a["task"]), source_path=str(a["source_path"]), source_sha256=str(a["source_sha256"]),
        source_format=str(a["source_format"]), duration_s=float(a["duration_s"]), stamp0_ns=int(a["stamp0_ns"]),
        base_frame=str(a["base_frame"]), camera_frame=str(a["camera_frame"]),
        rgb=g["rgb"][()], affordance=g["affordance"][()], traj3d=g["traj3d"][()], traj2d=g["traj2d"][()],
        K=g["K"][()], T_base_camera=g["T_base_camera"][()],
        depth=g["depth"][()] if "depth" in g else None, has_affordance=bool(a["has_affordance"]),
        object_names=[str(n) for n in g["objects"].attrs["names"]], objects=g["objects"][()],
        ee_t=s["ee_t"][()], ee_pos=s["ee_pos"][()], joint_t=s["joint_t"][()], joint_pos=s["joint_pos"][()],
        joint_names=[str(n) for n in s["joint_pos"].attrs["joint_names"]], note=str(a.get("note", "")),
        segment=int(a.get("segment", -1)), lens=read_lens(g), camera_name=str(a.get("camera_name", "camera")),
        cameras=[read_camera(g, n) for n in camera_names(g)[1:]],
    )


def episode_names(f: h5py.File) -> list[str]:
    return sorted(f[EPISODES].keys())


def episode_keys(f: h5py.File) -> set[str]:
    """The re-ingest keys (bag sha256, and segment) of the episodes in the dataset, from its catalog."""
    return {row["key"] for row in read_catalog(f)}


CATALOG = "catalog"
CATALOG_FIELDS = ("name", "key", "task", "file")


def read_catalog(f: h5py.File) -> list[dict[str, str]]:
    """One row per episode: name, key (sha256[#segment]), task and its file relative to the index."""
    try:
        if CATALOG not in f:
            return []
        cols = {k: [v.decode() if isinstance(v, bytes) else str(v) for v in f[CATALOG][k][()]]
                for k in CATALOG_FIELDS}
        return [dict(zip(CATALOG_FIELDS, row, strict=True)) for row in zip(*cols.values(), strict=True)]
    except DAMAGED as exc:  # a column missing, of another length, or a damaged table
        raise_if_interrupted(exc)
        raise AdlError(f"{f.filename}: the dataset's catalog cannot be read ({one_line(exc)}); ingest the bags again "
                       "into a new dataset") from None


def check_horizon(model: Path | str, horizon: int, f: h5py.File, data: Path | str) -> None:
    """A first-frame model predicts its trajectories at the dataset's waypoint count, or it is not scored on it."""
    n = int(f.attrs.get("n_waypoints", horizon))
    if n != horizon:
        raise AdlError(f"{model}: predicts {horizon} waypoints but {data} holds {n} per trajectory; use data "
                       f"ingested with --waypoints {horizon} (or train on this data)")
