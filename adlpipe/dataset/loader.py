"""A torch Dataset over the HDF5 file: image channels in, normalised trajectory out.

Inputs: RGB (3) + affordance map (1) [+ depth (1)] as channels at the model's image size, in [-1, 1].
Target: N waypoints x 5 = (u, v) pixels at the stored size and (x, y, z) metres, each dimension scaled to [-1, 1]
with min/max statistics of the train split only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from ..geometry.camera import PINHOLE, Lens, project, read_lens
from ..geometry.recovery import recovering_plan
from ..geometry.transforms import path_at
from ..plumbing.errors import AdlError
from . import schema
from .frames import metres_from_mm

DEPTH_SCALE_M = 2.0  # depth / 2 m - 1 keeps the table-top range inside [-1, 1]
ACTION_DIM = 5  # u, v, x, y, z


def raw_target(g: h5py.Group) -> np.ndarray:
    return np.concatenate([g["traj2d"][()], g["traj3d"][()]], axis=1).astype(np.float32)


def compute_stats(path: str, names: list[str]) -> dict[str, list[float]]:
    """Per-dimension min/max of the targets over `names` (the train split)."""
    with h5py.File(path, "r") as f:
        allv = np.concatenate([raw_target(f[schema.EPISODES][n]) for n in names])
    return padded_range(allv.min(0), allv.max(0))


def padded_range(lo: np.ndarray, hi: np.ndarray, prefix: str = "") -> dict[str, list[float]]:
    """{prefix}min / {prefix}max: the range widened by 5 % each side, so test values rarely leave [-1, 1]."""
    pad = np.maximum((hi - lo) * 0.05, 1e-3)
    return {f"{prefix}min": (lo - pad).tolist(), f"{prefix}max": (hi + pad).tolist()}


STATE_DIM = 4  # closed-loop ADL state per observation frame: the measured end effector (x, y, z) and gripper


def frame_state(frames: h5py.Group) -> np.ndarray:
    """(T, 4) float32: the measured end-effector position at each frame and the gripper joint (0 where the bag has
    no gripper joint: a constant input then)."""
    grip = np.nan_to_num(frames["gripper"][()].astype(np.float32), nan=0.0)
    return np.concatenate([frames["ee_pos"][()].astype(np.float32), grip[:, None]], 1)


def command_series(g: h5py.Group, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, commanded end-effector positions (M, 3)) of an episode: the first three values of its action stream
    at the stream's own rate (a dataset ingested before the stream was kept: at each frame), samples without a
    command left out."""
    fr = g["frames"]
    if "action" not in fr or fr["action"].shape[1] < 3:
        raise AdlError(f"{where}: no commanded end-effector position per frame (frames/action); ingest with the "
                       "topic map's action topic naming the arm's Cartesian command (x, y, z first), or train "
                       "--target ee on the measured end effector")
    if "action_stream" in fr:
        t, cmd = fr["action_stream_t"][()], fr["action_stream"][:, :3].astype(float)
    else:
        t, cmd = fr["t"][()], fr["action"][:, :3].astype(float)
    ok = np.isfinite(cmd).all(1)
    if ok.sum() < 1:
        raise AdlError(f"{where}: frames/action holds no finite command")
    return t[ok], cmd[ok]


def relative_waypoints(t_now: np.ndarray, now: np.ndarray, series_t: np.ndarray, series_p: np.ndarray,
                       horizon: int, rate_hz: float, K: np.ndarray, T: np.ndarray, lens: Lens = PINHOLE,
                       size: int | None = None,
                       reference: tuple[np.ndarray, ...] | None = None) -> np.ndarray:
    """(F, horizon, 5): the positions of a series (the commanded or the measured end effector) at t_now + 1/rate ..
    t_now + horizon/rate, the last one held after the end, relative to `now` (F, 3): pixels (u, v) from its
    projection through the camera's lens, metres (x, y, z). The closed-loop policies' target format. reference
    (stamps, positions) of a disturbed demonstrator's own path: instead of the series, the plan it would follow
    back onto that path from `now` (adlpipe.geometry.recovery); with (phase stamps, phases) after them (a labelled
    rollout's, adlpipe.sim.dagger), from the phase of the path reached at each frame instead of the frame's time."""
    ahead = np.arange(1, horizon + 1)[None] / rate_hz
    future = np.asarray(t_now, float)[:, None] + ahead
    if reference is not None:
        ref_t, ref_p, *phase = reference
        at = np.interp(t_now, phase[0], phase[1]) if phase else np.asarray(t_now, float)
        xyz = recovering_plan(at, now, ref_t, ref_p, at[:, None] + ahead)
    else:
        xyz = path_at(future, series_t, series_p[:, :3])  # (F, Tp, 3)
    now = np.asarray(now, float)
    wh = (size, size) if size else None  # the stored images' size: the lens holds inside them
    uv = (project(xyz.reshape(-1, 3), K, T, lens, wh).reshape(*xyz.shape[:2], 2)
          - project(now, K, T, lens, wh)[:, None])
    return np.concatenate([uv, xyz - now[:, None]], -1).astype(np.float32)


def anchor_series(g: h5py.Group, target: str, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(series stamps, series positions, the anchor at each frame (T, 3)) of a closed-loop target: "command" the
    commanded end effector, relative to the command at the frame; "ee" the measured one, relative to the measured
    position at the frame."""
    if target in ("command", "recovery"):
        ct, cmd = command_series(g, where)
        t = g["frames/t"][()]
        return ct, cmd, path_at(t, ct, cmd)
    return g["series/ee_t"][()], g["series/ee_pos"][()], g["frames/ee_pos"][()].astype(float)


def reference_series(g: h5py.Group, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, positions (M, 3)) of the path a disturbed demonstrator returns to (record --recoveries): its
    reference stream; an undisturbed demonstration's reference is its own command."""
    fr = g["frames"]
    if "reference_stream" not in fr:
        return command_series(g, where)
    t, ref = fr["reference_stream_t"][()], fr["reference_stream"][()].astype(float)
    if ref.ndim != 2 or ref.shape[1] < 3 or not np.isfinite(ref[:, :3]).all():
        raise AdlError(f"{where}: frames/reference_stream is not a finite (M, 3) path")
    return t, ref[:, :3]


def expert_reference(g: h5py.Group, where: str) -> tuple[np.ndarray, ...]:
    """The reference a frame's recovery label is made from: (stamps, positions) of the path, and where a labelled
    rollout recorded it, (stamps, phases) of the expert's phase on it (frames/expert_phase_stream)."""
    ref = reference_series(g, where)
    fr = g["frames"]
    if "expert_phase_stream" not in fr:
        return ref
    t, phase = fr["expert_phase_stream_t"][()], fr["expert_phase_stream"][()].astype(float).reshape(-1)
    if len(t) != len(phase) or not np.isfinite(phase).all():
        raise AdlError(f"{where}: frames/expert_phase_stream is not one finite phase per stamp")
    return (*ref, t, phase)


def any_reference(index: str | Path, names: list[str]) -> bool:
    """Does any of the episodes carry a disturbed demonstrator's reference stream?"""
    files = _EpisodeFiles(str(index), list(names))
    return any("reference_stream" in files.group(n)["frames"] for n in names)


def compute_window_stats(index: str | Path, names: list[str], windows: Windows) -> dict[str, list[float]]:
    """Min/max of closed-loop targets over every frame of `names`: waypoints relative to the anchor (the command,
    or the measured end effector, at the frame; pixels and metres), and, as state_min/state_max, the measured
    end-effector position and gripper the state input takes. Reads only the small arrays, an episode at a time."""
    files = _EpisodeFiles(str(index), list(names))
    lo, hi = np.full(ACTION_DIM, np.inf), np.full(ACTION_DIM, -np.inf)
    slo, shi = np.full(STATE_DIM, np.inf), np.full(STATE_DIM, -np.inf)
    for n in names:
        g = files.group(n)
        where = f"{files.files[n]}: episode {n}"
        series_t, series_p, now = anchor_series(g, windows.target, where)
        ref = expert_reference(g, where) if windows.target == "recovery" else None
        rel = relative_waypoints(g["frames/t"][()], now, series_t, series_p, windows.horizon, windows.rate_hz,
                                 g["K"][()], g["T_base_camera"][()], read_lens(g),
                                 int(g["rgb"].shape[1]), ref).reshape(-1, ACTION_DIM)
        state = frame_state(g["frames"])
        lo, hi = np.minimum(lo, rel.min(0)), np.maximum(hi, rel.max(0))
        slo, shi = np.minimum(slo, state.min(0)), np.maximum(shi, state.max(0))
    return {**padded_range(lo, hi), **padded_range(slo, shi, "state_")}


class Normalizer:
    def __init__(self, stats: dict[str, list[float]]) -> None:
        self.lo = torch.tensor(stats["min"], dtype=torch.float32)
        self.hi = torch.tensor(stats["max"], dtype=torch.float32)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return 2 * (x - self.lo.to(x)) / (self.hi - self.lo).to(x) - 1

    def unnormalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x + 1) / 2 * (self.hi - self.lo).to(x) + self.lo.to(x)


def observation(g: h5py.Group, image_size: int, use_depth: bool, cameras: tuple[str, ...] = ()) -> np.ndarray:
    """(C, S, S) float32 in [-1, 1] of a stored episode's first frame: RGB, affordance, optional depth. With
    `cameras` (names, in order), one such stack per camera, concatenated: another camera's frame is the one nearest
    the first image, with a blank affordance map (-1) and its own depth."""
    if not cameras:
        depth = (g["depth"][()] if "depth" in g else None) if use_depth else None
        return observation_from_arrays(g["rgb"][()], g["affordance"][()], depth, image_size, use_depth)
    have = schema.camera_names(g)
    primary = have[0]
    views = []
    for name in cameras:
        if name not in have:
            raise AdlError(f"episode {g.name.rpartition('/')[2]} has no camera {name!r} (its cameras: "
                           f"{', '.join(have)}); the model was trained on data with other cameras")
        if name == primary:
            views.append(observation(g, image_size, use_depth))
            continue
        fr = g[f"{schema.CAMERAS}/{name}/frames"]
        k = int(fr["index"][0])
        if k < 0:
            raise AdlError(f"episode {g.name.rpartition('/')[2]}: camera {name} has no frame near the first image")
        d = int(fr["depth_index"][k]) if use_depth and "depth_index" in fr else -1
        depth = metres_from_mm(fr["depth"][d]) if d >= 0 else None
        blank = np.zeros(fr["rgb"].shape[1:3], np.float32)
        views.append(observation_from_arrays(fr["rgb"][k], blank, depth, image_size, use_depth))
    return np.concatenate(views)


def check_cameras(f: h5py.File, names: list[str], cameras: tuple[str, ...], where: str) -> None:
    """Every named episode has the cameras a model sees; one line naming the first that lacks one."""
    for n in names:
        have = schema.camera_names(f[schema.EPISODES][n])
        missing = [c for c in cameras if c not in have]
        if missing:
            raise AdlError(f"{where}: episode {n} has no camera {missing[0]!r} (its cameras: {', '.join(have)}); "
                           "--cameras names cameras of the topic map the bags were ingested with")


def observation_from_arrays(rgb: np.ndarray, affordance: np.ndarray, depth: np.ndarray | None, image_size: int,
                            use_depth: bool) -> np.ndarray:
    """The network input from images (also a live camera's, in closed-loop replay)."""
    rgb = cv2.resize(rgb, (image_size, image_size), interpolation=cv2.INTER_AREA)
    aff = cv2.resize(affordance, (image_size, image_size), interpolation=cv2.INTER_AREA)
    chans = [rgb.transpose(2, 0, 1).astype(np.float32) / 127.5 - 1.0, aff[None] * 2.0 - 1.0]
    if use_depth:
        chans.append(depth_channel(depth, image_size)[None])
    return np.concatenate(chans).astype(np.float32)


def depth_channel(metres: np.ndarray | None, image_size: int) -> np.ndarray:
    """Depth in metres (NaN = no return; None: no depth image) as the network's channel in [-1, 1]."""
    if metres is None:
        return np.full((image_size, image_size), -1.0, np.float32)  # as a frame of no returns
    d = cv2.resize(np.nan_to_num(metres, nan=0.0), (image_size, image_size), interpolation=cv2.INTER_NEAREST)
    return np.clip(d / DEPTH_SCALE_M - 1.0, -1, 1).astype(np.float32)


MAX_CACHED_BYTES = 256 << 20  # per process: first-frame observations are kept in memory up to this much


class TrajectoryDataset(Dataset):
    """The seed's ADL setting: the first frame -> the whole trajectory. Lazy: the HDF5 file is opened once per
    worker process on first access; items are cached per worker (before augmentation, which differs per epoch) when
    the whole set fits in MAX_CACHED_BYTES, else read every time."""

    def __init__(self, path: str, names: list[str], stats: dict, image_size: int, use_depth: bool = False,
                 cache: bool = True, augment: Augment | None = None, seed: int = 0,
                 cameras: tuple[str, ...] = ()) -> None:
        self.path, self.names = str(path), list(names)
        self.norm = Normalizer(stats)
        self.cameras = tuple(cameras)
        item_bytes = (5 if use_depth else 4) * image_size * image_size * 4 * max(1, len(self.cameras))
        # cached only while small: a paper-size set (10,000 episodes at 224 px) would hold 8 GB per worker
        self.cache = cache and len(self.names) * item_bytes <= MAX_CACHED_BYTES
        self.image_size, self.use_depth = image_size, use_depth
        self.augment, self.seed, self.epoch = augment, seed, 0
        self._file: h5py.File | None = None
        self._pid = -1
        self._items: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.names)

    def _handle(self) -> h5py.File:
        if self._file is None or self._pid != os.getpid():  # a forked worker must not share the parent's handle
            self._file = h5py.File(self.path, "r")
            self._pid = os.getpid()
            self._items = {}
        return self._file

    def task(self, i: int) -> str:
        return str(self._handle()[schema.EPISODES][self.names[i]].attrs["task"])

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.item(i, self.epoch)

    def item(self, i: int, epoch: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Item i as epoch `epoch` augments it (the epoch comes with the index: persistent workers keep their own
        copy of the dataset, whose epoch attribute the main process cannot move)."""
        if i in self._items:
            obs, target = self._items[i]
        else:
            g = self._handle()[schema.EPISODES][self.names[i]]
            obs, target = observation(g, self.image_size, self.use_depth, self.cameras), raw_target(g)
            if self.cache:
                self._items[i] = (obs, target)
        if self.augment is not None:
            rng = np.random.default_rng([self.seed, epoch, i, 1])
            obs, target = self.augment(obs, target, rng, 5 if self.use_depth else 4)
        return torch.from_numpy(obs), self.norm.normalize(torch.from_numpy(target))

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_file"], state["_items"] = None, {}
        return state


class Augment:
    """Training-time augmentation of an observation and its target, as Diffusion Policy's random crop and colour
    jitter: a random shift of the whole image stack (edges replicated) by up to `shift` of its width, or with `crop`
    a random crop x crop window of it (the model centre-crops at test, so the shift is the window's offset from the
    centre), with the pixel targets moved by the same amount at the stored size; and brightness, contrast and
    saturation jitter of the RGB channels. The affordance map and depth move with the image and are not
    jittered."""

    def __init__(self, stored_size: int, shift: float = 0.06, jitter: float = 0.2, crop: int = 0) -> None:
        self.stored_size, self.shift, self.jitter, self.crop = stored_size, shift, jitter, crop

    def __call__(self, obs: np.ndarray, target: np.ndarray, rng: np.random.Generator,
                 channels_per_frame: int) -> tuple[np.ndarray, np.ndarray]:
        c, s, _ = obs.shape
        if self.crop and s > self.crop:
            left, top = (int(v) for v in rng.integers(0, s - self.crop + 1, 2))
            centre = (s - self.crop) // 2
            dx, dy = centre - left, centre - top
            obs = obs[:, top:top + self.crop, left:left + self.crop].copy()
        else:
            pad = max(1, int(round(self.shift * s)))
            dx, dy = (int(v) for v in rng.integers(-pad, pad + 1, 2))
            padded = np.pad(obs, ((0, 0), (pad, pad), (pad, pad)), mode="edge")
            obs = padded[:, pad - dy:pad - dy + s, pad - dx:pad - dx + s].copy()
        target = target.copy()
        target[:, 0] += dx * self.stored_size / s
        target[:, 1] += dy * self.stored_size / s
        s = obs.shape[-1]
        b, k, sat = 1 + rng.uniform(-self.jitter, self.jitter, 3)
        frames = obs.reshape(c // channels_per_frame, channels_per_frame, s, s)  # a view: edits land in obs
        rgb = (frames[:, :3] + 1) / 2  # the same jitter for every frame of the stack
        gray = rgb.mean(1, keepdims=True)
        rgb = gray + sat * (rgb - gray)
        mean = rgb.mean()
        frames[:, :3] = np.clip(((rgb - mean) * k + mean) * b, 0, 1) * 2 - 1
        return obs, target


OPEN_FILES = 32  # episode files a loader process keeps open (each costs about 0.6 MB of memory, measured)


class _EpisodeFiles:
    """Episode files opened directly (not through the index's links), up to `limit` at a time, per process, with
    their episode groups and datasets: while every episode's file fits (limit >= episodes), a training window drawn
    at random costs no file open and no path lookup (measured on 200 episodes: 0.93 ms a window with all open, 1.55
    ms with 32, where most windows re-open a file). Each file keeps a small chunk cache: a window reads its frames
    once."""

    CHUNK_CACHE = 256 << 10  # bytes per dataset (HDF5's default is 1 MB; frames are not read twice in a row)

    def __init__(self, index: str, names: list[str], limit: int = OPEN_FILES) -> None:
        from . import shards

        with h5py.File(index, "r") as f:
            self.files = {n: str(shards.episode_file(Path(index), f, n)) for n in names}
        self.limit = limit
        self._open: dict[str, h5py.File] = {}
        self._groups: dict[str, h5py.Group] = {}
        self._datasets: dict[tuple[str, str], tuple[h5py.Group, h5py.Dataset]] = {}  # (its group, the dataset)
        self._pid = -1

    def group(self, name: str) -> h5py.Group:
        if self._pid != os.getpid():  # a forked worker must not share the parent's handles
            self._open, self._groups, self._datasets, self._pid = {}, {}, {}, os.getpid()
        if name in self._groups:
            return self._groups[name]
        path = self.files[name]
        if path not in self._open:
            if len(self._open) >= self.limit:
                old, f = next(iter(self._open.items()))
                self._groups = {n: g for n, g in self._groups.items() if self.files[n] != old}
                self._datasets = {k: v for k, v in self._datasets.items() if self.files[k[0]] != old}
                self._open.pop(old)
                f.close()
            self._open[path] = h5py.File(path, "r", rdcc_nbytes=self.CHUNK_CACHE)
            schema.check_self_contained(self._open[path], f"{path}: episode {name}")
        self._groups[name] = self._open[path][schema.EPISODES][name]
        return self._groups[name]

    def dataset(self, name: str, key: str) -> h5py.Dataset:
        """A dataset of an episode group (e.g. frames/rgb), its handle kept as long as its file is open."""
        g = self.group(name)
        cached = self._datasets.get((name, key))
        if cached is None or cached[0] is not g:
            cached = self._datasets[(name, key)] = (g, g[key])
        return cached[1]

    def __getstate__(self) -> dict:
        return {"files": self.files, "limit": self.limit, "_open": {}, "_groups": {}, "_datasets": {}, "_pid": -1}


MAX_CACHED_WINDOWS = 2000  # ~0.3 GB of 8 x 64 x 64 float32 windows at most


@dataclass(frozen=True)
class Windows:
    """The closed-loop sample: observation frames t-n_obs+1..t, and the end effector's next `horizon` waypoints
    at `rate_hz` (t + 1/rate .. t + horizon/rate): target "command" the commanded end effector relative to the
    command at t (the default: what the arm is told, anchored where the last plan left it), "recovery" the same
    anchor with the disturbed demonstrator's plan back onto its reference path (record --recoveries), "ee" the
    measured one relative to the measured position at t; with target "action", the recorded actions of frames
    t..t+horizon-1 instead (absolute, the last repeated after the end) and the recorded state as the state input.
    images False: a state-only model's sample, whose image part is empty (no image is read)."""

    n_obs: int = 2
    horizon: int = 16
    rate_hz: float = 10.0
    target: str = "command"
    images: bool = True
    # HG-DAgger: an episode that carries an operator's flag (frames/intervention) gives windows only at the frames
    # the operator drove; every other episode (the demonstrations) gives every frame
    corrections_only: bool = False


def compute_action_stats(index: str | Path, names: list[str]) -> dict[str, list[float]]:
    """Min/max of the recorded actions (min/max) and states (state_min/state_max) over every frame of `names`."""
    files = _EpisodeFiles(str(index), list(names))
    acts, states = [], []
    for n in names:
        fr = files.group(n)["frames"]
        if "action" not in fr or "state" not in fr:
            raise AdlError(f"{files.files[n]}: episode {n} has no state/action per frame; ingest the bags with "
                           "the topic map's state and action topics")
        a, s = fr["action"][()], fr["state"][()]
        acts += [np.nanmin(a, 0), np.nanmax(a, 0)]
        states += [np.nanmin(s, 0), np.nanmax(s, 0)]
    return {**padded_range(np.min(acts, 0), np.max(acts, 0)),
            **padded_range(np.min(states, 0), np.max(states, 0), "state_")}


def pass_permutation(seed: int, n_pass: int, n: int) -> np.ndarray:
    """The order of all n windows in pass n_pass over them (seeded: a resumed run draws what it would have)."""
    return np.random.default_rng([seed, n_pass, 3]).permutation(n)


class WindowDataset(Dataset):
    """Every frame of every episode as a training window (Diffusion Policy's sequence sampler): observation frames
    t-To+1..t stacked as channels (the first frame repeated before the start) with the end effector's position at
    each, target the next Tp waypoints (u, v, x, y, z) at a fixed rate relative to the current end effector, the
    last pose repeated after the end, normalised with compute_window_stats.

    draws_per_epoch: an epoch is this many windows drawn uniformly over every frame of every episode (one seeded
    permutation of all windows per pass, continued from epoch to epoch, so each window is seen once before any is
    seen again); the training set passes the number of episodes, so a closed-loop model takes as many optimiser steps
    per epoch as a first-frame one. Otherwise every frame is an item, or `frames_per_episode` evenly spaced ones (a
    fixed validation or test set)."""

    def __init__(self, index: str | Path, names: list[str], stats: dict, image_size: int, windows: Windows,
                 use_depth: bool = False, augment: Augment | None = None, draws_per_epoch: int | None = None,
                 frames_per_episode: int | None = None, seed: int = 0, cameras: tuple[str, ...] = (),
                 open_files: int = OPEN_FILES) -> None:
        # A fixed set (validation, test loss) without augmentation is kept in memory when small; training windows
        # and large sets stream.
        self.names, self.w = list(names), windows
        self.cameras = tuple(cameras)  # the cameras a multi-camera model sees, in order; (): the first alone
        self.stats, self.norm = stats, Normalizer(stats)
        self.image_size, self.use_depth, self.augment = image_size, use_depth, augment
        self.draws, self.seed, self.epoch = draws_per_epoch, seed, 0
        self._perm: tuple[int, np.ndarray] = (-1, np.zeros(0, int))  # (pass, permutation of all windows)
        self.files = _EpisodeFiles(str(index), self.names, open_files)
        self._metas: dict[int, dict] = {}
        self._cached: dict[int, tuple] = {}
        lengths, drove = [], {}
        for e, n in enumerate(self.names):  # windows start at frames up to the end of the demonstration
            g = self.files.group(n)
            lengths.append(int(np.searchsorted(g["frames/t"][()], float(g.attrs["duration_s"]), "right")))
            if windows.corrections_only and "intervention" in g["frames"]:
                drove[e] = g["frames/intervention"][()]
        self.lengths = np.maximum(np.array(lengths, int), 1)
        if frames_per_episode:
            self.items = [(e, int(k)) for e, n in enumerate(self.lengths)
                          for k in np.unique(np.linspace(0, n - 1, frames_per_episode).round().astype(int))]
        else:
            self.items = [(e, k) for e, n in enumerate(self.lengths) for k in range(n)
                          if e not in drove or (k < len(drove[e]) and drove[e][k])]
        if not self.items:
            raise AdlError(f"{index}: no training window: every episode that carries an intervention flag has no "
                           "frame the operator drove, and no other episode is given")
        self.cache = bool(frames_per_episode) and augment is None and len(self.items) <= MAX_CACHED_WINDOWS

    def __len__(self) -> int:
        return self.draws if self.draws else len(self.items)

    def window(self, i: int, epoch: int | None = None) -> tuple[int, int]:
        """(episode, frame) of item i in `epoch`: fixed, or (draws_per_epoch) position epoch * draws + i of the
        concatenated seeded permutations of all windows."""
        if not self.draws:
            return self.items[i]
        pos = (self.epoch if epoch is None else epoch) * self.draws + i
        n_pass, k = divmod(pos, len(self.items))
        if self._perm[0] != n_pass:
            self._perm = (n_pass, pass_permutation(self.seed, n_pass, len(self.items)))
        return self.items[int(self._perm[1][k])]

    def episode_meta(self, e: int) -> dict:
        """An episode's small arrays (stamps, end-effector series, camera, affordance maps and sync indices), read
        once and kept for the last few episodes: a window then costs one HDF5 read of its frames."""
        if e in self._metas:
            return self._metas[e]
        g = self.files.group(self.names[e])
        fr = g["frames"]
        m = {"e": e, "aff_index": fr["affordance_index"][()], "aff": {},
             "depth_index": fr["depth_index"][()] if self.use_depth else None}
        if self.w.target == "action":
            m.update(state=fr["state"][()].astype(np.float32), action=fr["action"][()].astype(np.float32))
        else:
            where = f"{self.files.files[self.names[e]]}: episode {self.names[e]}"
            series_t, series_p, now = anchor_series(g, self.w.target, where)
            m.update(t=fr["t"][()], state=frame_state(fr), series_t=series_t, series_p=series_p, now=now,
                     ref=expert_reference(g, where) if self.w.target == "recovery" else None,
                     K=g["K"][()], T=g["T_base_camera"][()], lens=read_lens(g), size=int(g["rgb"].shape[1]))
        if len(self._metas) >= 256:
            self._metas.pop(next(iter(self._metas)))
        self._metas[e] = m
        return m

    def _affordance(self, m: dict, g: h5py.Group, k: int) -> np.ndarray:
        """The affordance channel of frame k at the model's input size, in [-1, 1] (kept per map: most bags
        publish few)."""
        a = int(m["aff_index"][k])
        if a not in m["aff"]:
            raw = g["frames/affordance"][a] if a >= 0 else np.zeros((self.image_size,) * 2, np.float32)
            m["aff"][a] = cv2.resize(raw, (self.image_size, self.image_size), interpolation=cv2.INTER_AREA) * 2 - 1
        return m["aff"][a]

    def raw(self, e: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(observation (To*C, S, S), empty without images; state at those frames (To, 4): measured end effector and
        gripper; target (Tp, 5)) of frame k of episode e: the same channels as observation_from_arrays, for a stack
        at once. The target is relative to the anchor at frame k (the command, or the measured end effector):
        pixels from its projection, metres from its position. With target "action": the recorded states and
        actions instead."""
        g = self.files.group(self.names[e])
        m = self.episode_meta(e)
        idx = [max(j, 0) for j in range(k - self.w.n_obs + 1, k + 1)]
        obs = self._images(g, m, k, idx) if self.w.images else np.zeros(0, np.float32)
        if self.w.target == "action":
            ahead = np.minimum(np.arange(k, k + self.w.horizon), len(m["action"]) - 1)
            return obs, m["state"][idx], m["action"][ahead]
        target = relative_waypoints(m["t"][k:k + 1], m["now"][k:k + 1], m["series_t"], m["series_p"],
                                    self.w.horizon, self.w.rate_hz, m["K"], m["T"], m["lens"], m["size"],
                                    m["ref"])[0]
        return obs, m["state"][idx], target

    def _images(self, g: h5py.Group, m: dict, k: int, idx: list[int]) -> np.ndarray:
        """The stacked image channels of frames idx (ending at k); with several cameras, one such stack per camera,
        in order: another camera's frames are those nearest the first camera's (its frames/index)."""
        if not self.cameras:
            return self._first_camera_images(g, m, k, idx)
        primary = schema.camera_names(g)[0]
        return np.concatenate([self._first_camera_images(g, m, k, idx) if c == primary
                               else self._other_camera_images(g, m, c, idx) for c in self.cameras])

    def _other_camera_images(self, g: h5py.Group, m: dict, name: str, idx: list[int]) -> np.ndarray:
        """Another camera's frames nearest the first camera's frames idx: RGB, a blank affordance channel (-1), its
        own depth. A frame it has none for (index -1) takes its nearest earlier one, else its first. Its sync
        indices are read once per episode, into the episode's meta."""
        fr = g[f"{schema.CAMERAS}/{name}/frames"]
        if ("camera", name) not in m:
            m[("camera", name)] = (fr["index"][()], fr["depth_index"][()] if "depth_index" in fr else None)
        index, depth_index = m[("camera", name)]
        have = np.flatnonzero(index >= 0)
        if not len(have):
            raise AdlError(f"episode {g.name.rpartition('/')[2]}: camera {name} has no frame near any frame of the "
                           "first camera")
        size = self.image_size
        blank = np.zeros(fr["rgb"].shape[1:3], np.float32)
        out = []
        for i in idx:
            j = int(index[have[max(np.searchsorted(have, i, "right") - 1, 0)]])
            d = int(depth_index[j]) if self.use_depth and depth_index is not None else -1
            out.append(observation_from_arrays(fr["rgb"][j], blank, metres_from_mm(fr["depth"][d]) if d >= 0
                                               else None, size, self.use_depth))
        return np.concatenate(out)

    def _first_camera_images(self, g: h5py.Group, m: dict, k: int, idx: list[int]) -> np.ndarray:
        lo = idx[0]
        rgbs = self.files.dataset(self.names[m["e"]], "frames/rgb")[lo:k + 1]  # one read for the whole stack
        size = (self.image_size, self.image_size)  # resized frame by frame, exactly as at inference
        rgb = np.stack([cv2.resize(rgbs[i - lo], size, interpolation=cv2.INTER_AREA) for i in idx])
        rgb = rgb.transpose(0, 3, 1, 2)
        chans = [rgb.astype(np.float32) / 127.5 - 1.0,
                 np.stack([self._affordance(m, g, i) for i in idx])[:, None]]
        if self.use_depth:
            chans.append(np.stack([self._depth(m, g, i) for i in idx])[:, None])
        return np.concatenate(chans, axis=1).reshape(-1, self.image_size, self.image_size)

    def _depth(self, m: dict, g: h5py.Group, k: int) -> np.ndarray:
        d = int(m["depth_index"][k])
        return depth_channel(metres_from_mm(g["frames/depth"][d]) if d >= 0 else None, self.image_size)

    def __getitem__(self, i: int) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor]:
        """((image channels, normalised state (4 * To)), normalised target (Tp, 5))."""
        return self.item(i, self.epoch)

    def item(self, i: int, epoch: int) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor]:
        """Item i as epoch `epoch` draws (draws_per_epoch) and augments it."""
        if i in self._cached:
            return self._cached[i]
        e, k = self.window(i, epoch)
        obs, state, target = self.raw(e, k)
        if self.augment is not None and self.w.images:
            rng = np.random.default_rng([self.seed, epoch, i, 1])
            obs, _ = self.augment(obs, target, rng, 5 if self.use_depth else 4)  # relative targets do not move
        item = ((torch.from_numpy(obs.astype(np.float32)), self.normalize_state(state)),
                self.norm.normalize(torch.from_numpy(target)))
        if self.cache:
            self._cached[i] = item
        return item

    def normalize_state(self, state: np.ndarray) -> torch.Tensor:
        return normalize_state(state, self.stats)


def normalize_state(state: np.ndarray, stats: dict) -> torch.Tensor:
    """The state at the observation frames (To, 4): end-effector metres and gripper (or the recorded state, (To, D))
    -> [-1, 1] with the state statistics, flattened."""
    lo, hi = np.asarray(stats["state_min"]), np.asarray(stats["state_max"])
    return torch.from_numpy((2 * (state - lo) / (hi - lo) - 1).astype(np.float32).reshape(-1))
