"""Per-episode quality figures a curator acts on, and the flags they raise (adlpipe.doctor is the stage).

Everything is read an episode at a time from its small arrays; frames are compared by their stored chunks (two
identical frames compress to the same bytes, so a frozen camera is found without decoding an image) and depth
holes from a few evenly spaced depth images. Memory stays flat in the number of episodes: what is kept per episode
is a few numbers.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import h5py
import numpy as np
from scipy.stats import median_abs_deviation

from ..dataset import schema
from ..dataset.frames import nearest_index
from ..geometry.transforms import path_at
from .doctor_checks import (
    Kinematics,
    affordance_on_path,
    by_task,
    camera_figures,
    dataset_flags,
    ee_in_image,
    end_speed,
    frame_figures,
    gripper_profile,
    image_figures,
    joint_units,
    kinematics,
    lens_figures,
    path_signature,
    registration,
)
from .doctor_signals import action_figures, chatter, joint_figures, near_duplicates, non_finite_notes, signature

RESAMPLE_HZ = 50.0  # the end-effector path is resampled at this rate for speed, jerk and idle time
DEPTH_SAMPLES = 8  # depth images per episode read for the share of holes
EE_MIN_FRAMES = 8  # frames that change with the end effector projected inside the image, to judge where it is (a
#                   camera that does not see the end effector, as some labs mount one, is not judged)
MIN_FOR_OUTLIERS = 3  # a task needs this many episodes before one of them is called an outlier (30 clean
#                       episodes, 3 per task: none called one)
OUTLIER_FIGURES = ("duration_s", "path_m", "peak_speed_mps", "fps")


@dataclass(frozen=True)
class Limits:
    """What counts as a problem (each is a flag's threshold, stated in the flag's reason)."""

    idle_speed_mps: float = 0.01  # the arm is idle while its end effector is slower than this
    idle_s: float = 1.0  # idle this long at the start or the end of an episode is flagged
    frozen_frames: int = 5  # this many identical consecutive camera frames: a frozen camera
    repeated_share: float = 0.3  # this share of the frames identical to the one before (in shorter runs): each
    #                              frame written more than once, the stamps running faster than the camera (clean:
    #                              none over 200 default and 106 bench recordings; written 3 times: 0.67)
    gap_factor: float = 3.0  # a frame interval this many times the median one: a dropped stretch
    max_speed_mps: float = 2.0  # an end effector faster than this is a tf glitch, not a motion
    max_tf_gap_s: float = 0.2  # a longer gap between end-effector tf samples
    depth_holes: float = 0.5  # a larger share of depth pixels without a return
    holes_excess: float = 0.1  # or this much more of them than the dataset's median (a lens smeared or a
    #                            projector failing in one episode; clean: within 0.019 of the median over 200
    #                            default and 106 bench recordings, whose background gives 26-29 % holes)
    z: float = 3.5  # robust z-score (median and scaled MAD within the task) beyond which a figure is an outlier
    outlier_share: float = 0.25  # ... and it must also lie this share of the median away (a task whose episodes
    #                              are nearly alike has a tiny MAD: 0.57 against 0.56 m/s is not a problem)
    joint_spike: float = 0.5  # a joint value this share of the joint's range off the median of it and its neighbours
    flatline_s: float = 1.0  # an arm joint (or the action stream) repeating one value this long ...
    flatline_moved_m: float = 0.05  # ... while the end effector moves this far: a stuck sensor or a stale command
    chatter: int = 4  # this many gripper crossings (open or close) within chatter_s: chatter
    chatter_s: float = 1.0
    duplicate_m: float = 1e-3  # as many frames as an earlier recording, the end effector within this of it (RMS)
    duplicate_image: float = 1e-4  # and the first frame within this mean grey level (0-1): the same demonstration
    #                                saved twice (200 clean demonstrations: pairs 0.3 mm apart, but their first
    #                                frames 3e-4 or more apart)
    # doctor_checks: cross-modal, per episode
    principal_share: float = 0.2  # the principal point this share of the image or more from its middle: a K for
    #                               another resolution (real cameras sit within a few percent of the middle)
    depth_max_m: float = 20.0  # a median depth beyond this at a manipulation camera: millimetres in a metres topic
    joint_max: float = 7.0  # a joint value beyond this (rad; 2 pi and a margin): degrees
    end_speed_mps: float = 0.08  # still moving this fast over the last 0.3 s, where the dataset's episodes end at
    #                              rest (3x its median end speed): cut off mid-motion (200 clean: at most 0.054)
    clock_lag_s: float = 0.1  # image motion this far behind (or ahead of) the end effector's speed ...
    clock_min_r: float = 0.5  # ... with at least this correlation: the camera's clock is off
    lens_shift: float = 0.5  # the lens model moving a point of the image by this share of its distance from the
    #                          principal point: distortion coefficients of no real polynomial lens
    command_lead_s: float = 0.05  # the measured end effector moving this long before the command that drives it
    #                               (at a correlation of clock_min_r or more): the command's values or stamps late
    frame_swap: float = 0.9  # the image change in the stored order over that with two frames swapped back below
    #                          this: two frames stored in the wrong order
    fk_m: float = 0.02  # with a robot model: its forward kinematics from the joints this far from the tf end
    #                     effector (median over the episode): names, order or units wrong (the ADL arm on its
    #                     200 recordings: at most 0.6 mm)
    registration_share: float = 0.03  # depth edges matching the colour edges this share of the image's width or
    #                                   more to the side: depth misregistered, an image mirrored, or a camera moved
    #                                   (200 clean at 128 px, 20 at 48 px: all at no shift; mirrored: 11 px or more)
    ee_motion_gap: float = 0.05  # the end effector's projection this share of the image's width (median over the
    #                              frames that change, EE_MIN_FRAMES of them in the image) from any pixel that
    #                              changed: K, extrinsics, the image or its focus disagree with tf (clean:
    #                              at most 0.018 over 200 recordings at 128 px and 104 at 64 px; planted: a camera
    #                              translation in mm 0.21, its rotation as wxyz 0.12, a mirrored image 0.10)
    affordance_dwell: float = 0.4  # the end effector's dwell frames on the affordance map's region in less than
    #                                this share: a map from another episode or task (clean: at least 0.55 over
    #                                200 recordings at 128 px, 0.56 over 106 at 64 px; another task's map: below
    #                                it in 79 % of pairs: bench/affordance_pairs.py)
    registration_gain: float = 0.05  # ... matching better there than at no shift by this much (planted: 0.074 or
    #                                  more; a colour image and a depth image with nothing in common: 0.031)
    # doctor_checks: against the dataset's medians (3 episodes per task are enough)
    colour_off: float = 0.05  # mean colour this far (sum over R G B, 0-1) from the dataset's ...
    swap_gain: float = 0.5  # ... and red and blue swapped this much nearer to it: BGR stored as RGB (the same
    #                         gain for a gripper reading upside down)
    gripper_off: float = 0.25  # the gripper's reading this far (share of its range, mean over the episode) from the
    #                            task's other episodes' median
    dark: float = 0.5  # mean brightness below this share of the dataset's median
    slow_camera: float = 0.6  # a frame rate below this share of the dataset's median
    label_ratio: float = 0.5  # the path this share nearer another task's episodes than its own: a wrong label
    reversed_m: float = 0.01  # another episode's path run backwards within this (RMS; and within a fifth of its
    #                           forward distance): a time-reversed copy


def episode_figures(g: h5py.Group, limits: Limits = Limits(), robot: Kinematics | None = None) -> dict:
    """The figures of one episode group, with its flags ("kind: reason"); with a robot model, its kinematics
    against the recording too."""
    fr = g["frames"]
    t = fr["t"][()]
    duration = float(g.attrs["duration_s"])
    dt = np.diff(t)
    fig: dict = {"task": str(g.attrs["task"]), "frames": len(t), "duration_s": duration,
                 "fps": float(1 / np.median(dt)) if len(dt) and np.median(dt) > 0 else 0.0,
                 "max_frame_gap_s": float(dt.max()) if len(dt) else 0.0,
                 "max_frame_gap_at_s": float(t[int(dt.argmax())]) if len(dt) else 0.0}
    fig.update(_frozen(fr["rgb"], t))
    ee_t, ee_pos = g["series/ee_t"][()], g["series/ee_pos"][()]  # read once for every check below
    fig.update(_sync(g, t, ee_t))
    fig.update(_motion(ee_t, ee_pos, duration, limits))
    grip = fr["gripper"][()]
    crossings = gripper_crossings(grip)
    fig["gripper_events"] = None if crossings is None else len(crossings)
    fig["gripper_chatter"] = chatter(t, crossings, limits.chatter_s)
    fig["gripper_profile"] = gripper_profile(grip)
    fig.update(joint_figures(g, json.loads(g.attrs.get("topic_map", "{}") or "{}").get("gripper_joint"), ee_t,
                             ee_pos))
    fig.update(action_figures(g, ee_t, ee_pos))
    fig["non_finite"] = non_finite_notes(g)
    fig["depth_holes"] = _depth_holes(fr)
    fig.update(camera_figures(g))
    fig.update(lens_figures(g))
    fig.update(image_figures(fr))
    fig.update(registration(g))
    fig.update(ee_in_image(g))
    fig.update(affordance_on_path(g))
    fig.update(kinematics(g, robot))
    fig.update(joint_units(g))
    fig["end_speed_mps"] = end_speed(ee_t, ee_pos, duration)
    fig.update(frame_figures(g, ee_t, ee_pos))
    fig["bridged_tf_gap"] = "bridged" in str(g.attrs.get("note", ""))
    fig["flags"] = flags(fig, float(fr.attrs.get("sync_tolerance_s", 0.05)), limits)
    return fig


def _frozen(rgb: h5py.Dataset, t: np.ndarray) -> dict:
    """Frames identical to the one before (compared by their stored chunk bytes) and the longest run of them."""
    repeats = longest = run = 0
    start = at = 0
    previous = None
    for i in range(rgb.shape[0]):
        chunk = rgb.id.read_direct_chunk((i, 0, 0, 0))[1]
        if chunk == previous:
            repeats += 1
            run += 1
            if run > longest:
                longest, at = run, start
        else:
            run, start = 0, i
        previous = chunk
    return {"repeated_frames": repeats, "frozen_run": longest + 1 if longest else 0,
            "frozen_at_s": float(t[at]) if longest else None}


def _nearest_gap(t: np.ndarray, stamps: np.ndarray) -> np.ndarray:
    """|t - the nearest of `stamps`| for each t (inf where there are none)."""
    if len(stamps) == 0:
        return np.full(len(t), np.inf)
    return np.abs(stamps[nearest_index(t, stamps, np.inf)] - t)


def _sync(g: h5py.Group, t: np.ndarray, ee_t: np.ndarray) -> dict:
    """Sync residuals of the other streams against the camera frames: the largest time from a frame to the
    nearest end-effector tf sample, joint state and (for frames that have one) its depth image."""
    fr = g["frames"]
    out = {"sync_tf_s": float(_nearest_gap(t, ee_t).max()) if len(t) else 0.0}
    joint_t = g["series/joint_t"][()]
    out["sync_joints_s"] = float(_nearest_gap(t, joint_t).max()) if len(joint_t) and len(t) else None
    if "depth_index" in fr and len(fr["depth_t"]):
        index = fr["depth_index"][()]
        ok = index >= 0
        out["sync_depth_s"] = float(np.abs(fr["depth_t"][()][index[ok]] - t[ok]).max()) if ok.any() else None
        out["frames_without_depth"] = int((~ok).sum())
    else:
        out["sync_depth_s"], out["frames_without_depth"] = None, None
    return out


def _motion(ee_t: np.ndarray, ee_pos: np.ndarray, duration: float, limits: Limits) -> dict:
    """Path length, peak speed (raw tf samples: a glitch is one sample), peak jerk, the largest tf gap and the idle
    time at the start and the end (the path resampled at RESAMPLE_HZ), over the episode's span."""
    inside = (ee_t >= 0) & (ee_t <= duration)
    t, p = ee_t[inside], ee_pos[inside]
    out = {"path_m": 0.0, "peak_speed_mps": 0.0, "peak_speed_at_s": 0.0, "peak_jerk": 0.0, "max_tf_gap_s": 0.0,
           "idle_start_s": duration, "idle_end_s": duration}
    if len(t) < 2:
        return out
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    dt = np.diff(t)
    moving = dt > 1e-6
    speed = np.where(moving, step / np.where(moving, dt, 1.0), 0.0)
    k = int(speed.argmax())
    out.update(path_m=float(step.sum()), peak_speed_mps=float(speed[k]), peak_speed_at_s=float(t[k + 1]),
               max_tf_gap_s=float(dt.max()))
    grid = np.arange(0.0, duration + 1e-9, 1 / RESAMPLE_HZ)
    q = path_at(grid, t, p[:, :3])
    v = np.linalg.norm(np.diff(q, axis=0), axis=1) * RESAMPLE_HZ
    fast = np.flatnonzero(v > limits.idle_speed_mps)
    if len(fast):
        out["idle_start_s"] = float(grid[fast[0]])
        out["idle_end_s"] = float(duration - grid[fast[-1] + 1])
    if len(q) >= 4:
        jerk = np.diff(q, n=3, axis=0) * RESAMPLE_HZ ** 3
        out["peak_jerk"] = float(np.linalg.norm(jerk, axis=1).max())
    return out


def gripper_crossings(grip: np.ndarray) -> list[int] | None:
    """Indices into `grip` (the gripper joint per frame) where it crosses the middle of its range, opening or
    closing, with hysteresis (a third of the range either side), so sensor noise is not an event. None: fewer than
    two finite values (no gripper joint)."""
    ok = np.flatnonzero(np.isfinite(grip))
    if len(ok) < 2:
        return None
    lo, hi = float(grip[ok].min()), float(grip[ok].max())
    if hi - lo < 1e-3:
        return []
    low, high = lo + (hi - lo) / 3, hi - (hi - lo) / 3
    state, out = None, []
    for k in ok:
        new = "high" if grip[k] >= high else "low" if grip[k] <= low else state
        if state is not None and new != state:
            out.append(int(k))
        state = new
    return out


def _depth_holes(fr: h5py.Group) -> float | None:
    """The share of depth pixels without a return, over a few evenly spaced depth images."""
    if "depth" not in fr or len(fr["depth"]) == 0:
        return None
    n = len(fr["depth"])
    picks = np.unique(np.linspace(0, n - 1, min(n, DEPTH_SAMPLES)).round().astype(int))
    return float(np.mean([(fr["depth"][int(i)] == 0).mean() for i in picks]))


def flags(fig: dict, tolerance: float, limits: Limits) -> list[str]:
    """The episode's problems, each with the figure and the threshold that raised it."""
    out = []
    share = fig["repeated_frames"] / max(fig["frames"], 1)
    if share > limits.repeated_share:
        out.append(f"repeated frames: {share:.0%} of the frames repeat the one before (limit "
                   f"{limits.repeated_share:.0%}): each camera frame written more than once?")
    if fig["frozen_run"] >= limits.frozen_frames:
        out.append(f"frozen camera: {fig['frozen_run']} identical frames in a row from {fig['frozen_at_s']:.2f} s "
                   f"(limit {limits.frozen_frames})")
    interval = 1 / fig["fps"] if fig["fps"] else 0.0
    if interval and fig["max_frame_gap_s"] > limits.gap_factor * interval:
        out.append(f"frame gap: {fig['max_frame_gap_s']:.2f} s without a camera frame after "
                   f"{fig['max_frame_gap_at_s']:.2f} s (median interval {interval:.3f} s)")
    if fig["peak_speed_mps"] > limits.max_speed_mps:
        out.append(f"tf glitch: the end effector moves at {fig['peak_speed_mps']:.1f} m/s at "
                   f"{fig['peak_speed_at_s']:.2f} s (limit {limits.max_speed_mps} m/s)")
    if fig["bridged_tf_gap"] or fig["max_tf_gap_s"] > limits.max_tf_gap_s:
        out.append(f"tf gap: {fig['max_tf_gap_s']:.2f} s between end-effector tf samples (limit "
                   f"{limits.max_tf_gap_s} s)")
    for end in ("start", "end"):
        if fig[f"idle_{end}_s"] > limits.idle_s:
            out.append(f"idle {end}: {fig[f'idle_{end}_s']:.1f} s with the end effector below "
                       f"{limits.idle_speed_mps} m/s (limit {limits.idle_s} s)")
    for stream in ("tf", "joints", "depth"):
        r = fig[f"sync_{stream}_s"]
        if r is not None and r > tolerance:
            out.append(f"sync: a frame is {r:.3f} s from the nearest {stream} sample (tolerance {tolerance} s)")
    if fig["depth_holes"] is not None and fig["depth_holes"] > limits.depth_holes:
        out.append(f"depth holes: {fig['depth_holes']:.0%} of depth pixels have no return (limit "
                   f"{limits.depth_holes:.0%})")
    return out + signal_flags(fig, limits) + unit_flags(fig, limits)


def unit_flags(fig: dict, limits: Limits) -> list[str]:
    """The camera model, the units and the clock (doctor_checks), each against its limit."""
    out = []
    pp = fig["principal_point"]
    if max(abs(pp[0] - 0.5), abs(pp[1] - 0.5)) > limits.principal_share:
        out.append(f"camera intrinsics: the principal point lies at ({pp[0]:.2f}, {pp[1]:.2f}) of the image "
                   f"(limit {limits.principal_share:.0%} from its middle): camera_info K of another resolution?")
    if fig["depth_median_m"] is not None and fig["depth_median_m"] > limits.depth_max_m:
        out.append(f"depth units: median depth {fig['depth_median_m']:.1f} m (limit {limits.depth_max_m} m): "
                   "millimetres in a metres (32FC1) topic?")
    if fig["joint_abs_max"] is not None and fig["joint_abs_max"] > limits.joint_max:
        out.append(f"joint units: a joint reads {fig['joint_abs_max']:.1f} (limit {limits.joint_max} rad): "
                   "degrees?")
    if fig["lens_shift"] is not None and (fig["lens_shift"] > limits.lens_shift or fig["lens_folds"]):
        out.append(f"camera lens: the distortion model moves points of the image by up to "
                   f"{fig['lens_shift']:.0%} of their distance from the principal point (limit "
                   f"{limits.lens_shift:.0%}){' and folds back inside it' if fig['lens_folds'] else ''}: "
                   "camera_info distortion coefficients of no real lens?")
    fk = fig["fk_residual_m"]
    if fk is not None and fk > limits.fk_m:
        out.append(f"kinematics: the joints put the end effector {100 * fk:.1f} cm from where tf says (median over "
                   f"the episode; limit {100 * limits.fk_m:.0f} cm): joint names, order or units other than the "
                   "robot model's?")
    shift, width = fig["registration_px"], fig["image_px"]
    if shift is not None and shift > limits.registration_share * width and \
            fig["registration_gain"] >= limits.registration_gain:
        out.append(f"depth registration: the depth image's edges match the colour image's {shift:.0f} px to the side "
                   f"(limit {limits.registration_share:.0%} of {width} px), {fig['registration_gain']:.2f} better "
                   "than in place: depth offset from colour, an image mirrored, or a camera moved after calibration?")
    gap, seen = fig["ee_motion_gap"], fig["ee_motion_frames"]
    if gap is not None and seen >= EE_MIN_FRAMES and gap > limits.ee_motion_gap:
        out.append(f"end effector not in image: the camera model puts it {gap * width:.1f} px from any pixel that "
                   f"changed (median of {seen} frames; limit {limits.ee_motion_gap:.0%} of {width} px): K, "
                   "extrinsics (rotation order, units), the image's orientation or its focus disagree with tf?")
    aff = fig["affordance_dwell"]
    if aff is not None and aff < limits.affordance_dwell:
        out.append(f"affordance map: the end effector acts on the map's marked region in {aff:.0%} of the frames "
                   f"where it slows (limit {limits.affordance_dwell:.0%}): a map from another episode or task?")
    if fig["order_ratio"] is not None and fig["order_ratio"] < limits.frame_swap:
        out.append(f"frame order: the frames at {fig['order_at_s']:.2f} s change the image {fig['order_ratio']:.2f}x "
                   f"as much swapped back as stored (limit {limits.frame_swap}): two frames stored out of order?")
    lag, r = fig["clock_lag_s"], fig["clock_r"]
    if lag is not None and abs(lag) > limits.clock_lag_s and r >= limits.clock_min_r:
        out.append(f"camera clock: image motion follows the end effector's speed {1000 * lag:+.0f} ms later "
                   f"(correlation {r:.2f}; limit {1000 * limits.clock_lag_s:.0f} ms)")
    return out


def signal_flags(fig: dict, limits: Limits) -> list[str]:
    """The flags of the joints, the action stream and the gripper (doctor_signals)."""
    out = [f"non-finite values: {note}" for note in fig["non_finite"]]
    if fig["joint_spike_share"] > limits.joint_spike:
        out.append(f"joint spike: {fig['joint_spike_joint']} is {fig['joint_spike']:.3g} "
                   f"({fig['joint_spike_share']:.0%} of its range) off its neighbours at "
                   f"{fig['joint_spike_at_s']:.2f} s (limit {limits.joint_spike:.0%})")
    if fig["joint_flat_s"] > limits.flatline_s and fig["joint_flat_moved_m"] > limits.flatline_moved_m:
        out.append(f"joint flatline: {fig['joint_flat_joint']} repeats one value for {fig['joint_flat_s']:.1f} s while "
                   f"the end effector moves {fig['joint_flat_moved_m']:.2f} m (limits {limits.flatline_s} s, "
                   f"{limits.flatline_moved_m} m)")
    frozen = fig["action_frozen_s"]
    if frozen is not None and frozen > limits.flatline_s and fig["action_frozen_moved_m"] > limits.flatline_moved_m:
        out.append(f"action frozen: the action stream repeats one value for {frozen:.1f} s from "
                   f"{fig['action_frozen_at_s']:.2f} s while the end effector moves {fig['action_frozen_moved_m']:.2f}"
                   f" m (limits {limits.flatline_s} s, {limits.flatline_moved_m} m)")
    lag, r = fig["command_lag_s"], fig["command_r"]
    if lag is not None and lag < -limits.command_lead_s and r >= limits.clock_min_r:
        out.append(f"command timing: the measured end effector moves {1000 * -lag:.0f} ms before the command that "
                   f"drives it (correlation {r:.2f}; an arm follows its command, limit "
                   f"{1000 * limits.command_lead_s:.0f} ms): the action stream's values or stamps late?")
    if fig["gripper_chatter"] >= limits.chatter:
        out.append(f"gripper chatter: {fig['gripper_chatter']} opening or closing crossings within "
                   f"{limits.chatter_s} s (limit {limits.chatter})")
    return out


def outlier_flags(figs: dict[str, dict], limits: Limits = Limits()) -> None:
    """Add an outlier flag to every episode whose duration, path length, peak speed or frame rate lies beyond
    limits.z robust z-scores (median and normal-scaled MAD, scipy) of its task's episodes and more than
    limits.outlier_share of the median from it; tasks with fewer than MIN_FOR_OUTLIERS episodes are left alone."""
    for names in by_task(figs).values():
        if len(names) < MIN_FOR_OUTLIERS:
            continue
        for key in OUTLIER_FIGURES:
            v = np.array([figs[n][key] for n in names], float)
            med, mad = float(np.median(v)), float(median_abs_deviation(v, scale="normal"))
            if mad <= 0:
                continue
            for n, x in zip(names, v, strict=True):
                z = (x - med) / mad
                if abs(z) > limits.z and abs(x - med) > limits.outlier_share * abs(med):
                    figs[n]["flags"].append(f"outlier: {key} {x:.3g} against the task's median {med:.3g} (robust z "
                                            f"{z:+.1f}, limit {limits.z}, {len(names)} episodes)")


def duplicate_flags(figs: dict[str, dict], signatures: dict[str, np.ndarray], stamps: dict[str, int],
                    limits: Limits) -> None:
    """Flag each episode that nearly repeats an earlier recording of its task (doctor_signals.near_duplicates)."""
    for names in by_task(figs).values():
        if len(names) < 2:
            continue
        found = near_duplicates(names, np.stack([signatures[n] for n in names]), [stamps[n] for n in names],
                                limits.duplicate_m, limits.duplicate_image)
        for name, (other, rms) in found.items():
            figs[name]["flags"].append(f"near duplicate: of {other} (recorded before it): as many frames, the end "
                                       f"effector {1e6 * rms:.1f} um from it (RMS; limit {1e6 * limits.duplicate_m:.0f}"
                                       " um)")


def examine(path: str, names: list[str] | None = None, limits: Limits = Limits(),
            robot: Kinematics | None = None) -> dict[str, dict]:
    """Figures and flags of every named episode (all if None) of a dataset, an episode at a time; `robot`: the
    robot model the joints are checked against (none: not checked)."""
    figs: dict[str, dict] = {}
    signatures: dict[str, np.ndarray] = {}  # a few hundred numbers per episode
    paths: dict[str, np.ndarray] = {}
    stamps: dict[str, int] = {}
    with schema.open_dataset(path, names) as f:
        for n in names if names is not None else schema.episode_names(f):
            g = f[schema.EPISODES][n]
            figs[n] = episode_figures(g, limits, robot)
            signatures[n], stamps[n] = signature(g), int(g.attrs.get("stamp0_ns", 0))
            paths[n] = path_signature(g["series/ee_t"][()], g["series/ee_pos"][()], figs[n]["duration_s"])
    outlier_flags(figs, limits)
    duplicate_flags(figs, signatures, stamps, limits)
    dataset_flags(figs, paths, limits)
    return figs


def summary_table(figs: dict[str, dict]) -> str:
    """Markdown: per task, the episodes, how many are flagged, and the medians a curator compares."""
    lines = ["| task | episodes | flagged | fps | duration s | path m | peak speed m/s | idle start s | idle end s | "
             "repeated frames |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    tasks = sorted({f["task"] for f in figs.values()})
    for task in tasks:
        rows = [f for f in figs.values() if f["task"] == task]

        def med(key: str, rows: list[dict] = rows) -> float:
            return float(np.median([r[key] for r in rows]))

        lines.append(f"| {task} | {len(rows)} | {sum(bool(r['flags']) for r in rows)} | {med('fps'):.1f} | "
                     f"{med('duration_s'):.1f} | {med('path_m'):.2f} | {med('peak_speed_mps'):.2f} | "
                     f"{med('idle_start_s'):.1f} | {med('idle_end_s'):.1f} | "
                     f"{sum(r['repeated_frames'] for r in rows)} |")
    return "\n".join(lines) + "\n"


def flag_lines(figs: dict[str, dict]) -> list[str]:
    return [f"{name}: {flag}" for name, f in figs.items() for flag in f["flags"]]
