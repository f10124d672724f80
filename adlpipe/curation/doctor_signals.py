"""The doctor's checks of the recorded signals beside the camera: joint spikes and flatlines, a frozen action stream,
gripper chatter, values a sensor sent as NaN (left out at ingest, named in the episode's note) and near-duplicate
episodes. Each check compares the signal with itself (a median filter, runs of identical values) or with the task's
other episodes, so no joint limits or robot model are needed.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import h5py
import numpy as np
from scipy.signal import medfilt
from scipy.spatial.distance import pdist, squareform

from ..dataset.from_bag import NON_FINITE
from ..geometry.transforms import path_at

SIGNATURE_POINTS = 64  # frames whose end-effector position stands for a recording (near duplicates)
THUMBNAIL = 16  # and its first frame's grey thumbnail, THUMBNAIL x THUMBNAIL
LAG_MAX_S, LAG_STEP_S = 0.5, 0.01  # lags searched between the command's and the end effector's speed


def _path_moved(ee_t: np.ndarray, ee_pos: np.ndarray, t0: float, t1: float) -> float:
    """How far the end effector moved between t0 and t1 (path length, m)."""
    inside = (ee_t >= t0) & (ee_t <= t1)
    p = ee_pos[inside]
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def _longest_still_run(t: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """(start, end) in s of the longest run of consecutive identical rows of x (bit-exact: a stuck sensor or a
    stale publisher repeats its last value; a real one still moving never does)."""
    same = np.all(np.diff(x, axis=0) == 0, axis=tuple(range(1, x.ndim)))  # row i equals row i + 1
    edges = np.flatnonzero(np.diff(np.concatenate([[0], same.astype(int), [0]])))
    starts, ends = edges[::2], edges[1::2]  # rows starts[k] .. ends[k] are all one value
    if not len(starts):
        return 0.0, 0.0
    k = int(np.argmax(t[ends] - t[starts]))
    return float(t[starts[k]]), float(t[ends[k]])


def joint_figures(g: h5py.Group, gripper: str | None, ee_t: np.ndarray, ee_pos: np.ndarray) -> dict:
    """The largest one-sample joint spike (the value minus its 3-sample median, against the joint's own range) and
    the longest flatline of an arm joint (the gripper is left out: it rests for long stretches), with the end
    effector's motion meanwhile (ee_t, ee_pos: its tf samples)."""
    s = g["series"]
    t, q = s["joint_t"][()], s["joint_pos"][()]
    names = [str(n) for n in s["joint_pos"].attrs.get("joint_names", [])]
    out = {"joint_spike": 0.0, "joint_spike_share": 0.0, "joint_spike_at_s": None, "joint_spike_joint": None,
           "joint_flat_s": 0.0, "joint_flat_joint": None, "joint_flat_moved_m": 0.0}
    if len(t) < 5 or q.ndim != 2:
        return out
    for j, name in enumerate(names[:q.shape[1]]):
        x = q[:, j]
        span = float(np.percentile(x, 99) - np.percentile(x, 1))
        residual = np.abs(x - medfilt(x, 3))[1:-1]  # medfilt pads the ends with zeros
        k = int(residual.argmax())
        share = float(residual[k] / max(span, 1e-3))
        if share > out["joint_spike_share"]:
            out.update(joint_spike=float(residual[k]), joint_spike_share=share, joint_spike_at_s=float(t[k + 1]),
                       joint_spike_joint=name)
        if name == gripper:
            continue
        t0, t1 = _longest_still_run(t, x)
        if t1 - t0 > out["joint_flat_s"]:
            out.update(joint_flat_s=t1 - t0, joint_flat_joint=name,
                       joint_flat_moved_m=_path_moved(ee_t, ee_pos, t0, t1))
    return out


def action_figures(g: h5py.Group, ee_t: np.ndarray, ee_pos: np.ndarray) -> dict:
    """The longest stretch over which the action stream repeats one value, and how far the end effector moved
    meanwhile (a command frozen while the arm moves is a stale publisher); and how long the measured end effector
    follows the command (command_lag)."""
    fr = g["frames"]
    if "action_stream" not in fr or len(fr["action_stream"]) < 2:
        return {"action_frozen_s": None, "action_frozen_moved_m": None, "command_lag_s": None, "command_r": None}
    act_t, act = fr["action_stream_t"][()], fr["action_stream"][()]
    t0, t1 = _longest_still_run(act_t, act)
    moved = _path_moved(ee_t, ee_pos, t0, t1)
    return {"action_frozen_s": t1 - t0, "action_frozen_at_s": t0, "action_frozen_moved_m": moved,
            **command_lag(act_t, act, ee_t, ee_pos)}


def command_lag(act_t: np.ndarray, act: np.ndarray, ee_t: np.ndarray, ee_pos: np.ndarray) -> dict:
    """The lag (s) by which the measured end effector's speed best follows the commanded end effector's (the
    action stream's first three values, when they are a position), and that correlation: an arm moves after it is
    told to (the default's 200 recordings: 0.06-0.09 s, r 0.84 or more), so a command that trails the arm carries
    late values or late stamps."""
    out: dict = {"command_lag_s": None, "command_r": None}
    if act.ndim != 2 or act.shape[1] < 3 or len(ee_t) < 8 or not np.isfinite(act[:, :3]).all():
        return out
    lo, hi = max(act_t[0], ee_t[0]) + LAG_MAX_S, min(act_t[-1], ee_t[-1]) - LAG_MAX_S
    if hi - lo < 1.0:
        return out
    grid = np.arange(lo, hi, LAG_STEP_S)
    vc = np.linalg.norm(np.diff(path_at(grid, act_t, act[:, :3]), axis=0), axis=1)
    if vc.std() < 1e-9:
        return out
    out["command_lag_s"], out["command_r"] = best_lag(
        vc, lambda lag: np.linalg.norm(np.diff(path_at(grid + lag, ee_t, ee_pos[:, :3]), axis=0), axis=1),
        np.arange(-LAG_MAX_S, LAG_MAX_S + 1e-9, LAG_STEP_S))
    return out


def best_lag(fixed: np.ndarray, lagged: Callable[[float], np.ndarray],
             lags: np.ndarray) -> tuple[float | None, float | None]:
    """(the lag whose series `lagged(lag)` correlates best with `fixed`, that correlation); (None, None) when
    every lagged series is flat. The camera clock's and the command's timing checks."""
    best: tuple[float | None, float | None] = (None, None)
    for lag in lags:
        s = lagged(float(lag))
        if s.std() < 1e-9:
            continue
        r = float(np.corrcoef(fixed, s)[0, 1])
        if best[1] is None or r > best[1]:
            best = (float(lag), r)
    return best


def chatter(t: np.ndarray, crossings: list[int] | None, window_s: float) -> int:
    """The most gripper crossings (open or close, with hysteresis) within any window_s."""
    if not crossings:
        return 0
    at = t[np.asarray(crossings)]
    return int(max(np.searchsorted(at, a + window_s, side="right") - i for i, a in enumerate(at)))


def non_finite_notes(g: h5py.Group) -> list[str]:
    """The parts of the episode's ingest note about messages left out for non-finite values."""
    return [part for part in str(g.attrs.get("note", "")).split("; ") if NON_FINITE in part]


def signature(g: h5py.Group) -> np.ndarray:
    """What a recording saved twice keeps and two recordings never share: its frame count, the end effector at
    SIGNATURE_POINTS evenly spaced frames (sensor noise, or a scene that differs at all, moves it by far more) and
    a grey THUMBNAIL x THUMBNAIL thumbnail of the first frame (the same motion replayed in another scene differs)."""
    ee = g["frames/ee_pos"]
    picks = np.unique(np.linspace(0, len(ee) - 1, SIGNATURE_POINTS).round().astype(int)) if len(ee) else []
    path = np.zeros((SIGNATURE_POINTS, 3))
    path[:len(picks)] = ee[list(picks)] if len(picks) else 0.0
    grey = cv2.resize(g["rgb"][()].astype(np.float32).mean(2), (THUMBNAIL, THUMBNAIL), interpolation=cv2.INTER_AREA)
    return np.concatenate([[len(ee)], path.ravel(), grey.ravel() / 255.0])


def near_duplicates(names: list[str], signatures: np.ndarray, stamps: list[int], within_m: float,
                    image: float) -> dict[str, tuple[str, float]]:
    """Within one task: each episode with as many frames as an earlier recording, its end effector within within_m
    of it (RMS over the sampled frames) and its first frame within `image` (mean absolute grey level, 0-1) ->
    (that one, the RMS)."""
    n = 1 + 3 * SIGNATURE_POINTS
    rms = squareform(pdist(signatures[:, 1:n], "euclidean")) / np.sqrt(SIGNATURE_POINTS)
    grey = squareform(pdist(signatures[:, n:], "cityblock")) / (THUMBNAIL * THUMBNAIL)
    out = {}
    order = np.argsort(stamps, kind="stable")
    for a_pos, a in enumerate(order):
        for b in order[:a_pos]:
            if signatures[a, 0] == signatures[b, 0] and rms[a, b] < within_m and grey[a, b] < image:
                out[names[a]] = (names[b], float(rms[a, b]))
                break
    return out
