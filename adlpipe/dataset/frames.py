"""Every camera frame of an episode, streamed into its HDF5 group as the bag is read (docs/reference/frame_storage.md).

    frames/t              (T,)        float64  header stamp, s from the first image
    frames/rgb            (T, S, S, 3) uint8   one chunk per frame, gzip 4 + shuffle
    frames/ee_pos         (T, 3)      float32  end effector in base_frame, interpolated in tf at each frame's stamp
    frames/joint_pos      (T, J)      float32  the joint state nearest each frame within the sync tolerance (NaN: none)
    frames/gripper        (T,)        float32  the topic map's gripper joint at each frame (NaN: no such joint)
    frames/state, frames/action (T, D) float32 the topic map's state / action stream nearest each frame within the
                                               tolerance (NaN: none); attr names. Only when the bag has the topic.
    frames/state_stream, frames/action_stream (M, D) float32 and their stamps frames/<key>_stream_t (M,) float64:
                                               the whole stream at its own rate (a command at 100 Hz is followed
                                               between 15 Hz frames, whatever the camera's rate)
    frames/intervention   (T,)        bool     an operator drove at the frame (the topic map's intervention flag: the
                                               last value at or before the frame, false before any); with
                                               frames/intervention_stream (M,) bool and its stamps _t (M,). Only when
                                               the bag has the topic.
    frames/depth          (D, S, S)   uint16   millimetres, 0 = no return; frames/depth_t (D,) its stamps
    frames/depth_index    (T,)        int32    the depth image nearest each frame within the tolerance, -1: none
    frames/affordance     (A, S, S)   float32  frames/affordance_t (A,); frames/affordance_index (T,): the map
                                               nearest each frame within the tolerance, else the latest before it,
                                               else the first (-1: the bag has none)

A bag's frames are never all in memory: each is resized and appended to its dataset when its message is read.
"""

from __future__ import annotations

import heapq
import os
import zlib
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import cv2
import h5py
import numpy as np

from ..plumbing.errors import AdlError

FRAMES = "frames"
CAMERAS = "cameras"  # an episode's other cameras: cameras/<name>/frames/{t, rgb, T_base_camera, index, depth...}
# Chosen in bench/frame_storage.py: built into every HDF5 (no plugin for readers), 4x smaller than raw RGB at 128 px,
# ~15,000 random frame reads/s in one process.
CODEC = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
DEPTH_MM_MAX = 65535
# A camera driver with two threads, or a bag merged by log time, logs a frame a little after a later one. Frames are
# ordered by header stamp within this many frames of look-ahead (held resized, so memory stays flat); a frame
# later than that cannot be ordered and the bag is refused.
REORDER_FRAMES = 8
# Compressing a frame took two thirds of ingest's time in the reading thread (docs/reference/frame_storage.md). zlib
# releases the GIL, so frames are compressed in threads into exactly the chunk HDF5's filters would store, and
# written with write_direct_chunk in order, while the reading thread decodes and resizes the next ones.
COMPRESS_THREADS = max(1, min(4, os.cpu_count() or 1))
IN_FLIGHT = 2 * COMPRESS_THREADS  # frames being compressed at once: bounded, memory stays flat
_pool: ThreadPoolExecutor | None = None


def _compressor() -> ThreadPoolExecutor:
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(COMPRESS_THREADS, thread_name_prefix="adlpipe-compress")
    return _pool


def _forget_pool() -> None:
    """A forked process (ingest's pool workers) inherits the pool object but none of its threads: work submitted
    to it would wait forever, so the child starts its own."""
    global _pool
    _pool = None


os.register_at_fork(after_in_child=_forget_pool)


def chunk_bytes(arr: np.ndarray) -> bytes:
    """One frame's chunk as CODEC stores it: the shuffle filter (bytes grouped by significance; nothing to do for
    one-byte elements), then deflate at level 4. Byte-identical to what HDF5 writes (tests/test_frames.py)."""
    a = np.ascontiguousarray(arr)
    raw = a.view(np.uint8).reshape(-1, a.itemsize).T.tobytes() if a.itemsize > 1 else a.tobytes()
    return zlib.compress(raw, CODEC["compression_opts"])


class FrameWriter:
    """Appends resized frames of one episode to `group/frames` as they are read from the bag."""

    def __init__(self, group: h5py.Group, size: int) -> None:
        self.group = group
        self.g = group.require_group(FRAMES)
        self.cameras: dict[str, FrameWriter] = {}  # the episode's other cameras (under cameras/<name>/)
        self.kept_t = np.zeros(0)  # the kept frames' stamps, s from the first image (set by finish)
        self.size = size
        self.t: dict[str, list[float]] = {"rgb": [], "depth": [], "affordance": []}  # stamps of what is written
        self._pending: list[tuple[float, int, np.ndarray]] = []  # (stamp, arrival, resized rgb): the look-ahead
        self._arrived = 0
        self._latest = -np.inf
        self.reordered = 0  # frames logged after a frame with a later stamp
        self.early = 0  # frames stamped before the episode's first image (dropped by finish)
        self._compressing: deque[tuple[h5py.Dataset, tuple[int, ...], Future[bytes]]] = deque()

    def _append(self, key: str, t: float, arr: np.ndarray) -> None:
        if key not in self.g:
            self.g.create_dataset(key, shape=(0, *arr.shape), maxshape=(None, *arr.shape), dtype=arr.dtype,
                                  chunks=(1, *arr.shape), **CODEC)
        d = self.g[key]
        i = len(self.t[key])
        d.resize(i + 1, axis=0)
        self.t[key].append(t)
        self._compressing.append((d, (i,) + (0,) * arr.ndim, _compressor().submit(chunk_bytes, arr)))
        while len(self._compressing) > IN_FLIGHT:
            self._write_compressed()

    def _write_compressed(self) -> None:
        """Store the oldest compressed frame (HDF5 is only touched from the reading thread)."""
        d, corner, chunk = self._compressing.popleft()
        d.id.write_direct_chunk(corner, chunk.result())

    def rgb(self, t: float, image: np.ndarray, where: str = "image") -> None:
        """Take a frame in log order; it is written in header-stamp order once REORDER_FRAMES later frames came."""
        img = image if image.ndim == 3 else np.repeat(image[..., None], 3, 2)
        small = cv2.resize(img, (self.size, self.size), interpolation=cv2.INTER_AREA).astype(np.uint8)
        self.reordered += t < self._latest
        self._latest = max(self._latest, t)
        heapq.heappush(self._pending, (t, self._arrived, small))
        self._arrived += 1
        if len(self._pending) > REORDER_FRAMES:
            self._write_oldest(where)

    def _write_oldest(self, where: str) -> None:
        t, _, small = heapq.heappop(self._pending)
        if self.t["rgb"] and t < self.t["rgb"][-1]:
            raise AdlError(f"{where}: a frame's header stamp is {self.t['rgb'][-1] - t:.3f} s before one logged more "
                           f"than {REORDER_FRAMES} frames earlier; frames cannot be ordered")
        self._append("rgb", t, small)

    def flush(self, where: str) -> None:
        """Write the frames still held in the look-ahead (the end of the bag) and those still being compressed."""
        while self._pending:
            self._write_oldest(where)
        while self._compressing:
            self._write_compressed()

    def camera(self, name: str) -> FrameWriter:
        """The writer of another camera of the episode: its frames go to cameras/<name>/frames."""
        if name not in self.cameras:
            self.cameras[name] = FrameWriter(self.group.require_group(f"{CAMERAS}/{name}"), self.size)
        return self.cameras[name]

    def depth(self, t: float, metres: np.ndarray) -> None:
        d = cv2.resize(metres.astype(np.float32), (self.size, self.size), interpolation=cv2.INTER_NEAREST)
        m = np.clip(np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0), 0.0, DEPTH_MM_MAX / 1000.0)
        self._append("depth", t, np.round(m * 1000.0).astype(np.uint16))

    def affordance(self, t: float, image: np.ndarray) -> None:
        a = cv2.resize(np.nan_to_num(image.astype(np.float32)), (self.size, self.size), interpolation=cv2.INTER_LINEAR)
        self._append("affordance", t, a)

    def finish(self, t0: float, t_end: float, tolerance: float, ee_t: np.ndarray, ee_pos: np.ndarray,
               joint_t: np.ndarray, joint_pos: np.ndarray, gripper: int | None, where: str,
               series: dict | None = None) -> int:
        """Make stamps relative to the first image (t0, absolute s), drop frames after the path's end, and sync the
        end effector, joints, state and action (series: name -> Series), depth and affordance to each kept frame.
        Returns the number of frames."""
        t = self.kept_t = self._trim(t0, t_end, tolerance, where)
        keep = len(t)
        self.g.create_dataset("ee_pos", data=np.stack([np.interp(t, ee_t, ee_pos[:, k]) for k in range(3)], 1)
                              .astype(np.float32))
        self.g.create_dataset("joint_pos", data=_nearest_rows(t, joint_t, joint_pos, tolerance).astype(np.float32))
        grip = (_nearest_rows(t, joint_t, joint_pos[:, [gripper]], tolerance)[:, 0] if gripper is not None
                else np.full(keep, np.nan))
        self.g.create_dataset("gripper", data=grip.astype(np.float32))
        for key, s in (series or {}).items():
            rows = np.asarray(s.rows, float).reshape(len(s.t), len(s.names))
            synced = _nearest_rows(t, np.asarray(s.t) - t0, rows, tolerance)
            missing = np.flatnonzero(~np.isfinite(synced).all(1)) if synced.shape[1] else []
            if len(missing):  # a policy trained on it would read NaN: the frame has no value, say which and why
                i = int(missing[0])
                why = (" (the message there was left out: it held non-finite values)" if s.non_finite else "")
                raise AdlError(f"{where}: frame {i} ({t[i]:.2f} s) has no {key} message within {tolerance} s"
                               f"{why}; {len(missing)} frame(s) so")
            d = self.g.create_dataset(key, data=synced.astype(np.float32))
            d.attrs["names"] = list(s.names)
            self.g.create_dataset(f"{key}_stream_t", data=np.asarray(s.t, float) - t0)
            self.g.create_dataset(f"{key}_stream", data=rows.astype(np.float32))
        self._sync_images(t, t0, tolerance, ("depth", "affordance"))
        return keep

    def intervention(self, t0: float, flags: list[tuple[float, bool]]) -> None:
        """The operator's flag (log time s, value) at each kept frame: the last value at or before it (a flag is
        published when the operator takes over or hands back, or at a rate), false before the first."""
        t = np.array([x for x, _ in flags], float) - t0
        v = np.array([b for _, b in flags], bool)
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
        at = np.searchsorted(t, self.kept_t + 1e-9, side="right") - 1
        self.g.create_dataset("intervention", data=np.where(at >= 0, v[np.maximum(at, 0)], False))
        self.g.create_dataset("intervention_stream_t", data=t)
        self.g.create_dataset("intervention_stream", data=v)

    def _trim(self, t0: float, t_end: float, tolerance: float, where: str) -> np.ndarray:
        """Write what is held, keep the frames from the first image (t0, absolute s) to the path's end and store
        their stamps relative to t0 (frames/t); returns them."""
        self.flush(where)
        t = np.asarray(self.t["rgb"], float) - t0
        # a frame stamped before the episode's first image (logged after it) precedes the episode: not kept
        first = int(np.searchsorted(t, 0.0, side="left"))
        keep = int(np.searchsorted(t, t_end + tolerance, side="right"))
        if "rgb" in self.g:
            rgb = self.g["rgb"]
            for i in range(keep - first if first else 0):  # one frame at a time: memory flat
                rgb[i] = rgb[i + first]
            rgb.resize(keep - first, axis=0)
        t = t[first:keep]
        repeats = int(np.sum(np.diff(t) <= 0))
        if len(t) > 2 and repeats > len(t) // 2:  # a driver whose stamps stopped: no frame can be placed in time
            raise AdlError(f"{where}: {repeats} of {len(t)} images carry the stamp of the one before (the camera's "
                           "stamps do not advance); restamp the images or re-record")
        self.early = first
        self.g.create_dataset("t", data=t)
        return t

    def _sync_images(self, t: np.ndarray, t0: float, tolerance: float, keys: tuple[str, ...]) -> None:
        for key in keys:
            ts = np.asarray(self.t[key], float) - t0
            self.g.create_dataset(f"{key}_t", data=ts)
            latest = key == "affordance"  # a map published once (or slowly) holds until the next one
            self.g.create_dataset(f"{key}_index", data=nearest_index(t, ts, tolerance, latest).astype(np.int32))
        self.g.attrs["sync_tolerance_s"] = tolerance

    def finish_camera(self, t0: float, t_end: float, tolerance: float, primary_t: np.ndarray,
                      poses: Callable[[np.ndarray], np.ndarray], where: str) -> np.ndarray:
        """Another camera's frames, kept over the same span as the primary camera's: their stamps, their depth
        images synced to them, the camera's pose at each (poses: relative stamps -> (n, 4, 4); a wrist camera
        moves with the arm) and, per primary frame, this camera's nearest frame within the tolerance (index, -1:
        none). Returns index."""
        t = self._trim(t0, t_end, tolerance, where)
        self._sync_images(t, t0, tolerance, ("depth",))
        self.g.create_dataset("T_base_camera", data=poses(t).astype(np.float64).reshape(len(t), 4, 4))
        index = nearest_index(primary_t, t, tolerance).astype(np.int32)
        self.g.create_dataset("index", data=index)
        return index


# The per-frame arrays FrameWriter writes: key -> (shape after the frame axis, given the image size S; dtype kinds).
# None: any one axis (joints, state and action widths).
_PER_FRAME = {"t": ((), "f"), "rgb": (("S", "S", 3), "u"), "ee_pos": ((3,), "f"), "joint_pos": ((None,), "f"),
              "gripper": ((), "f"), "state": ((None,), "f"), "action": ((None,), "f"),
              "depth_index": ((), "iu"), "affordance_index": ((), "iu")}
_IMAGES = {"depth": ("depth_index", "u"), "affordance": ("affordance_index", "f")}
FRAME_ARRAYS = ("t", "rgb", "ee_pos", "joint_pos", "gripper")  # FrameWriter writes these for every episode


def check_frames(fr: h5py.Group, where: str, size: int) -> None:
    """A frames group laid out as FrameWriter writes it (shapes, types, indices in range, finite stamps in order),
    so that no reader meets a malformed array; one line naming the array otherwise."""
    if not isinstance(fr, h5py.Group):
        raise AdlError(f"{where}: frames is not a group")
    missing = [k for k in FRAME_ARRAYS if k not in fr]
    if missing:
        raise AdlError(f"{where}: frames lack {', '.join(missing)}; re-ingest its bag")
    n = fr["t"].shape[0] if fr["t"].ndim == 1 else -1
    for key, (tail, kinds) in _PER_FRAME.items():
        if key not in fr:
            continue
        d = fr[key]
        want = tuple(size if a == "S" else a for a in tail)
        ok = (isinstance(d, h5py.Dataset) and d.dtype.kind in kinds and d.ndim == 1 + len(want)
              and d.shape[0] == n and all(w is None or w == s for w, s in zip(want, d.shape[1:], strict=True)))
        if not ok:
            shape = d.shape if isinstance(d, h5py.Dataset) else "a group"
            raise AdlError(f"{where}: frames/{key} is {shape} {getattr(d, 'dtype', '')}, expected "
                           f"({n}, {', '.join('J' if w is None else str(w) for w in want)}) of kind {kinds}; "
                           "re-ingest its bag")
    for key, (index, kind) in _IMAGES.items():
        if key in fr:
            d = fr[key]
            if not isinstance(d, h5py.Dataset) or d.dtype.kind != kind or d.ndim != 3 or d.shape[1:] != (size, size):
                raise AdlError(f"{where}: frames/{key} is {getattr(d, 'shape', 'a group')}, expected (N, {size}, "
                               f"{size}); re-ingest its bag")
        if key in fr and index not in fr:
            raise AdlError(f"{where}: frames/{key} without frames/{index}; re-ingest its bag")
        if index in fr:
            i = fr[index][()]
            if i.size and (i.min() < -1 or i.max() >= (len(fr[key]) if key in fr else 0)):
                raise AdlError(f"{where}: frames/{index} points outside frames/{key}; re-ingest its bag")
    t = fr["t"][()]
    if not np.isfinite(t).all() or np.any(np.diff(t) < 0):
        raise AdlError(f"{where}: frame stamps are not finite or go backwards; re-ingest its bag")


def check_camera_frames(fr: h5py.Group | None, where: str, size: int, n_primary: int) -> None:
    """Another camera's frames as finish_camera writes them: its own stamps, frames and poses, depth indices in
    range, and an index per primary frame into its frames; one line naming the array otherwise."""
    if not isinstance(fr, h5py.Group) or not all(k in fr for k in ("t", "rgb", "T_base_camera", "index")):
        raise AdlError(f"{where}: frames lack t, rgb, T_base_camera or index; re-ingest its bag")
    n = fr["t"].shape[0] if fr["t"].ndim == 1 else -1
    shapes = {"rgb": (n, size, size, 3), "T_base_camera": (n, 4, 4), "index": (n_primary,)}
    for key, shape in shapes.items():
        if not isinstance(fr[key], h5py.Dataset) or fr[key].shape != shape:
            raise AdlError(f"{where}: frames/{key} is {getattr(fr[key], 'shape', 'a group')}, expected {shape}; "
                           "re-ingest its bag")
    index = fr["index"][()]
    if index.size and (index.min() < -1 or index.max() >= n):
        raise AdlError(f"{where}: frames/index points outside its frames; re-ingest its bag")
    t = fr["t"][()]
    if not np.isfinite(t).all() or np.any(np.diff(t) < 0) or not np.isfinite(fr["T_base_camera"][()]).all():
        raise AdlError(f"{where}: frame stamps or poses are not finite, or stamps go backwards; re-ingest its bag")
    if "depth" in fr:
        d, i = fr["depth"], fr.get("depth_index")
        if d.ndim != 3 or d.shape[1:] != (size, size) or i is None or i.shape != (n,) or (
                i.size and (i[()].min() < -1 or i[()].max() >= len(d))):
            raise AdlError(f"{where}: frames/depth or frames/depth_index malformed; re-ingest its bag")


def nearest_index(t: np.ndarray, ts: np.ndarray, tolerance: float, or_latest: bool = False) -> np.ndarray:
    """For each time in t the index of the nearest stamp in ts within the tolerance; otherwise -1, or (or_latest)
    the latest stamp before it, or the first."""
    out = np.full(len(t), -1, np.int64)
    if len(ts) == 0:
        return out
    order = np.argsort(ts, kind="stable")
    s = ts[order]
    j = np.clip(np.searchsorted(s, t), 1, len(s)) - 1
    j_next = np.minimum(j + 1, len(s) - 1)
    pick = np.where(np.abs(s[j_next] - t) < np.abs(s[j] - t), j_next, j)
    close = np.abs(s[pick] - t) <= tolerance
    out[close] = order[pick[close]]
    if or_latest:
        before = np.searchsorted(s, t, side="right") - 1
        fill = ~close
        out[fill] = order[np.maximum(before[fill], 0)]
    return out


def _nearest_rows(t: np.ndarray, ts: np.ndarray, rows: np.ndarray, tolerance: float) -> np.ndarray:
    idx = nearest_index(t, np.asarray(ts, float), tolerance)
    out = np.full((len(t), rows.shape[1] if rows.ndim == 2 else 0), np.nan)
    ok = idx >= 0
    if ok.any() and out.shape[1]:
        out[ok] = rows[idx[ok]]
    return out


def read_frame(g: h5py.Group, i: int, with_depth: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(rgb, affordance, depth in metres or None) of frame i of an episode group."""
    f = g[FRAMES]
    rgb = f["rgb"][i]
    a = int(f["affordance_index"][i]) if "affordance_index" in f else -1
    aff = f["affordance"][a] if a >= 0 else np.zeros(rgb.shape[:2], np.float32)
    d = int(f["depth_index"][i]) if with_depth and "depth_index" in f else -1
    return rgb, aff, metres_from_mm(f["depth"][d]) if d >= 0 else None


def metres_from_mm(mm: np.ndarray) -> np.ndarray:
    """A stored depth image (uint16 mm, 0 = no return) in metres, NaN = no return: what FrameWriter.depth took."""
    return np.where(mm > 0, mm.astype(np.float32) / 1000.0, np.nan).astype(np.float32)
