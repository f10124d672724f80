"""The doctor's cross-modal and cross-episode checks: what a lab gets wrong once and loses weeks to (issue E2).

Per episode, from its own arrays: the camera model against the image (a principal point far from the image's
middle: K written for another resolution), depth and joint values against their units, the end effector still
and the camera's clock against the end effector's (image motion
cross-correlated with end-effector speed). Across episodes, against the dataset's own medians (3 episodes per task
are enough): the end effector still moving at the last frame where the others end at rest (cut off), colour
channels in the other order (BGR), images much darker, a camera at a fraction of the others'
rate, a gripper that never moves in a task whose other episodes grasp, a path nearer another task's episodes than
its own (a wrong label), and a time-reversed copy of another episode. The frames' order against their motion
(two frames swapped) and the lens model against the image (distortion no real lens has); the command's timing
against the arm's is doctor_signals.command_lag; the depth image's edges against the colour image's (registration);
the end effector projected by the camera model against where the image changes (ee_in_image); the affordance map
against where the end effector slows to act (affordance_on_path). Not caught: a camera
moved a few centimetres after calibration (stale extrinsics; docs/guide/curation.md). Each threshold is a field of
doctor.Limits.
"""

from __future__ import annotations

from collections import deque
from typing import Protocol

import cv2
import h5py
import numpy as np
from scipy.spatial.distance import cdist

from ..geometry.camera import distort, maps_outward, project, read_lens
from ..geometry.transforms import path_at
from .doctor_signals import best_lag

CLOCK_MAX_LAG_S = 0.5  # lags searched between image motion and end-effector speed
SAMPLES = 8  # frames read for colour and brightness
PATH_POINTS = 32  # the end-effector path resampled for cross-episode comparison
GRIPPER_POINTS = 32  # the gripper reading resampled over the episode for comparison within its task
LENS_GRID = 9  # points per side of the image grid the lens check moves through the lens
ORDER_MIN_MOTION = 1.0  # grey levels (0-255, mean over 32 x 32) of change over three steps below which the frame
#                         order is not judged (a still scene orders any way)


def camera_figures(g: h5py.Group) -> dict:
    """The principal point as a share of the stored image (K written for another resolution lies far out)."""
    K, size = g["K"][()], float(g["rgb"].shape[1])
    return {"principal_point": [float(K[0, 2] / size), float(K[1, 2] / size)], "image_px": int(size)}


def image_figures(fr: h5py.Group) -> dict:
    """Mean colour (0-1, R G B as stored) over SAMPLES evenly spaced frames, and the median valid depth (m)."""
    n = fr["rgb"].shape[0]
    picks = np.unique(np.linspace(0, n - 1, min(n, SAMPLES)).round().astype(int))
    rgb = np.mean([fr["rgb"][int(i)].reshape(-1, 3).mean(0) for i in picks], 0) / 255.0
    out: dict = {"mean_rgb": [float(x) for x in rgb], "depth_median_m": None}
    if "depth" in fr and len(fr["depth"]):
        d = fr["depth"][int(len(fr["depth"]) // 2)]
        valid = d[d > 0]
        out["depth_median_m"] = float(np.median(valid)) / 1000.0 if len(valid) else None
    return out


MOTION_GREY = 0.08  # a pixel changed between a frame's neighbours by this much (0-1 grey) moved
MOTION_MIN_PIXELS = 4  # a frame with fewer moving pixels says nothing about where the arm is


def ee_in_image(g: h5py.Group) -> dict:
    """Where the camera model puts the end effector against where the image changes: at each frame whose neighbours
    differ, the distance from the end effector's projection (tf, K, extrinsics, lens) to the nearest pixel that
    changed, as a share of the image's width. Returns the median over the frames where the projection falls inside
    the image, how many those are, and the share of changing frames where it falls outside. The end effector moves
    in the image where the camera model says, so a wrong K, extrinsics (rotation order, units), a mirrored image or
    a camera out of focus moves the figure off 0."""
    fr = g["frames"]
    n = len(fr["t"])
    out: dict = {"ee_motion_gap": None, "ee_motion_frames": 0, "ee_outside": None}
    if n < 3:
        return out
    h, w = fr["rgb"].shape[1:3]
    uv = project(fr["ee_pos"][()].astype(float), g["K"][()], g["T_base_camera"][()], read_lens(g), (w, h))
    grey = deque((fr["rgb"][i].astype(np.float32).mean(-1) / 255.0 for i in range(2)), maxlen=3)  # k-1, k, k+1
    gaps, outside = [], 0
    for k in range(1, n - 1):
        grey.append(fr["rgb"][k + 1].astype(np.float32).mean(-1) / 255.0)
        moved = np.abs(grey[2] - grey[0]) > MOTION_GREY
        if moved.sum() < MOTION_MIN_PIXELS:
            continue
        u, v = np.round(uv[k]).astype(int) if np.isfinite(uv[k]).all() else (-1, -1)
        if not (0 <= u < w and 0 <= v < h):
            outside += 1
            continue
        still = cv2.distanceTransform((~moved).astype(np.uint8), cv2.DIST_L2, 3)
        gaps.append(float(still[v, u]) / w)
    out["ee_motion_frames"] = len(gaps)
    if gaps or outside:
        out["ee_outside"] = outside / (len(gaps) + outside)
    if gaps:
        out["ee_motion_gap"] = float(np.median(gaps))
    return out


AFFORDANCE_REGION = 0.5  # the map's region: its pixels at this share of its peak or more
AFFORDANCE_NEAR = 0.04  # an end-effector point this share of the image's width from the region is on it
DWELL_SPEED = 0.3  # the end effector slower than this share of its peak speed, away from the episode's first and
DWELL_EDGE = 0.1  # last tenth (the arm at rest before and after), is where it acts
AFFORDANCE_MIN_DWELL = 3  # dwell frames in the image needed to judge the map


def affordance_on_path(g: h5py.Group) -> dict:
    """The affordance map against the demonstration: the share of the frames where the end effector slows to act
    (below DWELL_SPEED of its peak speed, the first and last tenth of the episode aside) whose projection lies on the
    map's marked region. A map marks where the action touches, so a demonstration works inside it; a map from
    another task's episode (another part of the manikin, another object) leaves most of them outside. None without
    a map, or with fewer than AFFORDANCE_MIN_DWELL such frames in the image."""
    out: dict = {"affordance_dwell": None}
    m = g["affordance"][()] if "affordance" in g and g.attrs.get("has_affordance", True) else None
    fr = g["frames"]
    if m is None or not np.isfinite(m).all() or m.max() <= 0 or len(fr["t"]) < 5:
        return out
    t, ee = fr["t"][()], fr["ee_pos"][()].astype(float)
    speed = np.r_[0.0, np.linalg.norm(np.diff(ee, axis=0), axis=1) / np.maximum(np.diff(t), 1e-6)]
    speed = np.convolve(speed, np.ones(3) / 3, "same")
    span = t[-1] - t[0]
    mid = (t > t[0] + DWELL_EDGE * span) & (t < t[-1] - DWELL_EDGE * span)
    if not mid.any() or speed[mid].max() <= 0:
        return out
    dwell = mid & (speed < DWELL_SPEED * speed[mid].max())
    h, w = fr["rgb"].shape[1:3]
    uv = project(ee[dwell], g["K"][()], g["T_base_camera"][()], read_lens(g), (w, h))
    uv = uv[np.isfinite(uv).all(1)] * [m.shape[1] / w, m.shape[0] / h]
    u, v = np.round(uv).astype(int).T
    inside = (u >= 0) & (u < m.shape[1]) & (v >= 0) & (v < m.shape[0])
    if inside.sum() < AFFORDANCE_MIN_DWELL:
        return out
    region = (m >= AFFORDANCE_REGION * m.max()).astype(np.uint8)
    dist = cv2.distanceTransform(1 - region, cv2.DIST_L2, 3) / m.shape[1]
    out["affordance_dwell"] = float((dist[v[inside], u[inside]] <= AFFORDANCE_NEAR).mean())
    return out


def _edges(image: np.ndarray) -> np.ndarray:
    gx, gy = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3)
    return np.hypot(gx, gy)


def registration(g: h5py.Group) -> dict:
    """Where the depth image's edges lie against the colour image's, on the first frame: the sideways shift (stored
    pixels) at which the middle half of the depth edges matches the colour edges best (OpenCV's normalised
    cross-correlation, searched a quarter of the image each way along the rows, where an RGB-D head's two lenses
    sit apart; a vertical search matched repeated edges of the clean cover-the-food scenes at 48 px), and that
    match's gain over no shift. A registered pair matches at no shift (200 clean demonstrations at 128 px and 20 at
    48 px: all at 0); depth offset from colour, a colour image mirrored, or one of the two cameras moved sideways
    after calibration does not, and matches better elsewhere by 0.07 or more; images with nothing in common (noise
    against a depth ramp) match about as well anywhere (gain 0.03)."""
    out: dict = {"registration_px": None, "registration_gain": None}
    size = g["rgb"].shape[1]
    if "depth" not in g or size < 16:
        return out
    grey = cv2.cvtColor(np.ascontiguousarray(g["rgb"][()]), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    colour, depth = _edges(grey), _edges(np.nan_to_num(g["depth"][()].astype(np.float32)))
    if colour.max() <= 0 or depth.max() <= 0 or depth.shape != colour.shape:  # nothing to align
        return out
    m = size // 4
    scores = cv2.matchTemplate(colour, np.ascontiguousarray(depth[:, m:size - m]), cv2.TM_CCORR_NORMED)[0]
    out.update(registration_px=float(abs(int(scores.argmax()) - m)), registration_gain=float(scores.max() - scores[m]))
    return out


class Kinematics(Protocol):
    """A robot model's forward kinematics (adlpipe.offline.robot.Robot is one): its joints by name, a joint vector
    from a recorded joint state, and the end effector's position once the vector is set."""

    joints: list[str]

    def start_q(self, names: list[str], values: np.ndarray) -> np.ndarray: ...

    def set_q(self, q: np.ndarray) -> None: ...

    def ee(self) -> np.ndarray: ...


def kinematics(g: h5py.Group, robot: Kinematics | None, instants: int = 16) -> dict:
    """Where the recorded joints put the end effector by the robot model's forward kinematics (MuJoCo), against
    where tf says it is: the median distance over `instants` evenly spaced times (m). None without a model, or
    when the recording names none of the model's joints. A model that fits its recordings lands within millimetres
    (the ADL arm on its own 200 recordings: at most 0.4 mm); joint names swapped, another joint order or other
    units do not."""
    if robot is None or "series/joint_pos" not in g:
        return {"fk_residual_m": None}
    names = [str(n) for n in g["series/joint_pos"].attrs.get("joint_names", [])]
    q_t, q, ee_t, ee = g["series/joint_t"][()], g["series/joint_pos"][()], g["series/ee_t"][()], g["series/ee_pos"][()]
    if not set(names) & set(robot.joints) or len(q_t) < 2 or len(ee_t) < 2:
        return {"fk_residual_m": None}
    times = np.linspace(max(q_t[0], ee_t[0]), min(q_t[-1], ee_t[-1]), instants)
    joints, where = path_at(times, q_t, q), path_at(times, ee_t, ee)
    off = []
    for values, tf in zip(joints, where, strict=True):
        robot.set_q(robot.start_q(names, values))
        off.append(float(np.linalg.norm(robot.ee() - tf)))
    return {"fk_residual_m": float(np.median(off))}


def joint_units(g: h5py.Group) -> dict:
    """The largest |value| of any joint (rad for a revolute joint: beyond 2 pi it is degrees)."""
    q = g["series/joint_pos"][()]
    return {"joint_abs_max": float(np.nanmax(np.abs(q))) if q.size else None}


def end_speed(ee_t: np.ndarray, ee_pos: np.ndarray, duration: float, window_s: float = 0.3) -> float:
    """Mean end-effector speed over the last window_s of the episode (m/s): a demonstration ends at rest."""
    inside = (ee_t >= duration - window_s) & (ee_t <= duration)
    if inside.sum() < 2:
        return 0.0
    t, p = ee_t[inside], ee_pos[inside]
    return float(np.linalg.norm(p[-1] - p[0]) / max(t[-1] - t[0], 1e-6))


def lens_figures(g: h5py.Group) -> dict:
    """How far the stored lens model moves points of the image from where the pinhole puts them, as a share of
    their distance from the principal point (the largest over a grid of the image), and whether it folds back
    inside the image (a ray further out landing nearer the middle). A real polynomial lens moves points a few
    tens of percent at most; nonsense coefficients (k1 = 3) move them several times over. Fisheye (equidistant)
    lenses compress the image by design and are left alone."""
    lens, K, size = read_lens(g), g["K"][()], int(g["rgb"].shape[1])
    out: dict = {"lens_shift": None, "lens_folds": None}
    if not lens.distorts or lens.model == "equidistant":
        return out
    u, v = np.meshgrid(np.linspace(0, size - 1, LENS_GRID), np.linspace(0, size - 1, LENS_GRID))
    rays = np.linalg.solve(K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))  # pinhole rays, z = 1
    centre = K[:2, 2]
    pin = np.stack([u.ravel(), v.ravel()], 1)
    dist = distort(rays.T, K, lens)
    r_pin = np.linalg.norm(pin - centre, axis=1)
    far = r_pin > 0.05 * size
    folds = ~maps_outward(rays.T, K, lens, dist)
    out["lens_shift"] = float((np.linalg.norm(dist - pin, axis=1)[far] / r_pin[far]).max()) if far.any() else 0.0
    out["lens_folds"] = bool(folds[far].any())
    return out


def frame_order(small: list[np.ndarray], k: int) -> float | None:
    """Frames k and k + 1 against the four around them: the image change in the stored order over the change with
    the two swapped (d(k-1, k+1) + d(k+1, k) + d(k, k+2) against d(k-1, k) + d(k, k+1) + d(k+1, k+2)). In a moving
    scene a swapped pair makes two double steps of the stored order (about 5 single steps against 3 swapped back);
    a clean pair about 3 against 5. None without motion."""
    d = lambda a, b: float(np.abs(small[a] - small[b]).mean())  # noqa: E731
    stored = d(k - 1, k) + d(k, k + 1) + d(k + 1, k + 2)
    if stored < ORDER_MIN_MOTION:
        return None
    return (d(k - 1, k + 1) + d(k + 1, k) + d(k, k + 2)) / stored


def frame_figures(g: h5py.Group, ee_t: np.ndarray, ee_pos: np.ndarray) -> dict:
    """Image motion (mean absolute grey change between consecutive frames, one frame at a time: memory flat)
    against end-effector speed: the lag that correlates them best (a camera clock behind the robot's shows motion
    late) and that correlation; and the frame order against the motion (frame_order: the lowest ratio over the
    episode, and where)."""
    fr = g["frames"]
    t = fr["t"][()]
    out: dict = {"clock_lag_s": None, "clock_r": None, "order_ratio": None, "order_at_s": None}
    if len(t) < 8 or len(ee_t) < 8:
        return out
    prev, motion = None, []
    small: list[np.ndarray] = []  # the last 4 frames at 32 px: all the order check needs
    for i in range(len(t)):
        grey = fr["rgb"][i].mean(2, dtype=np.float32)
        small = [*small[-3:], cv2.resize(grey, (32, 32), interpolation=cv2.INTER_AREA)]
        if len(small) == 4:
            r = frame_order(small, 1)
            if r is not None and (out["order_ratio"] is None or r < out["order_ratio"]):
                out["order_ratio"], out["order_at_s"] = r, float(t[i - 2])
        if prev is not None:
            motion.append(float(np.abs(grey - prev).mean()))
        prev = grey
    m = np.asarray(motion)
    if m.std() < 1e-6:
        return out
    mid = (t[1:] + t[:-1]) / 2
    speed_t = (ee_t[1:] + ee_t[:-1]) / 2
    speed = np.linalg.norm(np.diff(ee_pos, axis=0), axis=1) / np.maximum(np.diff(ee_t), 1e-6)
    step = float(np.median(np.diff(t))) / 4
    if step <= 0:  # image stamps that do not advance: no clock to compare (the frame rate check names them)
        return out
    out["clock_lag_s"], out["clock_r"] = best_lag(m, lambda lag: np.interp(mid - lag, speed_t, speed),
                                                  np.arange(-CLOCK_MAX_LAG_S, CLOCK_MAX_LAG_S + 1e-9, step))
    return out


def path_signature(ee_t: np.ndarray, ee_pos: np.ndarray, duration: float) -> np.ndarray:
    """The end-effector path resampled at PATH_POINTS instants evenly over the episode (PATH_POINTS, 3)."""
    grid = np.linspace(0.0, duration, PATH_POINTS)
    return path_at(grid, ee_t, ee_pos[:, :3])


def by_task(figs: dict[str, dict], names: list[str] | None = None) -> dict[str, list[str]]:
    """Episode names (all, or `names`) grouped by their task, each group in the given order."""
    out: dict[str, list[str]] = {}
    for n in figs if names is None else names:
        out.setdefault(figs[n]["task"], []).append(n)
    return out


def dataset_flags(figs: dict[str, dict], paths: dict[str, np.ndarray], limits) -> None:  # noqa: ANN001 - Limits
    """The flags that compare an episode with the dataset's others, added to each episode's list of flags."""
    names = list(figs)
    if len(names) < 3:
        return
    rgb = np.array([figs[n]["mean_rgb"] for n in names])
    med_rgb = np.median(rgb, 0)
    bright = rgb.mean(1)
    fps = np.array([figs[n]["fps"] for n in names])
    end = np.array([figs[n]["end_speed_mps"] for n in names])
    med_bright, med_fps, med_end = float(np.median(bright)), float(np.median(fps)), float(np.median(end))
    holes = [figs[n]["depth_holes"] for n in names if figs[n]["depth_holes"] is not None]
    med_holes = float(np.median(holes)) if len(holes) >= 3 else None
    for k, n in enumerate(names):
        f = figs[n]
        as_is, swapped = np.abs(rgb[k] - med_rgb).sum(), np.abs(rgb[k][::-1] - med_rgb).sum()
        if as_is > limits.colour_off and swapped < limits.swap_gain * as_is:
            f["flags"].append(f"colour order: red and blue swapped match the dataset's mean colour "
                              f"{swapped:.3f} against {as_is:.3f} as stored (BGR stored as RGB?)")
        if bright[k] < limits.dark * med_bright:
            f["flags"].append(f"dark images: mean brightness {bright[k]:.2f} against the dataset's median "
                              f"{med_bright:.2f} (limit {limits.dark:.0%} of it)")
        if end[k] > limits.end_speed_mps and end[k] > 3 * med_end:
            f["flags"].append(f"cut off: the end effector still moves at {end[k]:.2f} m/s over the last 0.3 s, where "
                              f"the dataset's episodes end at {med_end:.2f} m/s (median; limit "
                              f"{limits.end_speed_mps} m/s and 3x the median)")
        h = f["depth_holes"]
        if med_holes is not None and h is not None and limits.depth_holes >= h > med_holes + limits.holes_excess:
            f["flags"].append(f"depth holes: {h:.0%} of depth pixels have no return against the dataset's median "
                              f"{med_holes:.0%} (limit {limits.holes_excess:.0%} more)")
        if fps[k] < limits.slow_camera * med_fps:
            f["flags"].append(f"camera rate: {fps[k]:.1f} fps against the dataset's median {med_fps:.1f} "
                              f"(limit {limits.slow_camera:.0%} of it)")
    _gripper_flags(figs, names, limits)
    _path_flags(figs, names, paths, limits)


def gripper_profile(grip: np.ndarray) -> list[float] | None:
    """The gripper joint at GRIPPER_POINTS instants evenly over the episode's frames, as a share of its own range
    (0 its lowest reading, 1 its highest); None without a moving gripper reading."""
    ok = np.flatnonzero(np.isfinite(grip))
    if len(ok) < 2 or np.ptp(grip[ok]) < 1e-6:
        return None
    g = grip[ok].astype(float)
    at = np.interp(np.linspace(0, len(g) - 1, GRIPPER_POINTS), np.arange(len(g)), g)
    return [float(x) for x in (at - g.min()) / np.ptp(g)]


def _gripper_flags(figs: dict[str, dict], names: list[str], limits) -> None:  # noqa: ANN001 - Limits
    for members in by_task(figs, names).values():
        grasping = [n for n in members if (figs[n]["gripper_events"] or 0) > 0]
        if len(grasping) < 2:
            continue
        for n in members:
            if figs[n]["gripper_events"] == 0:
                figs[n]["flags"].append(f"stuck gripper: it never opens or closes, while {len(grasping)} of the "
                                        f"task's {len(members)} episodes do")
        profiled = [n for n in members if figs[n].get("gripper_profile")]
        if len(profiled) < 3:
            continue
        for n in profiled:  # against the others' median: an inverted reading matches it upside down
            others = np.median([figs[m]["gripper_profile"] for m in profiled if m != n], 0)
            p = np.asarray(figs[n]["gripper_profile"])
            as_is, inverted = float(np.abs(p - others).mean()), float(np.abs(1 - p - others).mean())
            if as_is > limits.gripper_off and inverted < limits.swap_gain * as_is:
                figs[n]["flags"].append(f"gripper inverted: its reading upside down matches the task's other "
                                        f"episodes {inverted:.2f} against {as_is:.2f} as stored (share of its range; "
                                        f"open read as closed?)")


def _path_flags(figs: dict[str, dict], names: list[str], paths: dict[str, np.ndarray], limits) -> None:  # noqa: ANN001
    """Wrong task label (the path nearer another task's episodes than its own) and time-reversed copies. One
    episode's RMS distances to every path, forwards and run backwards, at a time (scipy's cdist): linear memory."""
    forward = np.stack([paths[n].ravel() for n in names])
    backward = np.stack([paths[n][::-1].ravel() for n in names])
    groups = {task: np.array([names.index(m) for m in members]) for task, members in by_task(figs, names).items()}
    for k, n in enumerate(names):
        fwd = cdist(forward[k:k + 1], forward)[0] / np.sqrt(PATH_POINTS)  # RMS over the path's points
        back = cdist(forward[k:k + 1], backward)[0] / np.sqrt(PATH_POINTS)
        own = figs[n]["task"]
        mean_to = {task: float(fwd[idx[idx != k]].mean()) for task, idx in groups.items() if (idx != k).sum() >= 2}
        if own in mean_to and len(mean_to) > 1:
            other = min((t for t in mean_to if t != own), key=lambda t: mean_to[t])
            if mean_to[other] < limits.label_ratio * mean_to[own]:
                figs[n]["flags"].append(f"task label: its path is {100 * mean_to[other]:.1f} cm (RMS) from the "
                                        f"episodes of {other!r} and {100 * mean_to[own]:.1f} cm from those of its own "
                                        f"task {own!r} (limit {limits.label_ratio:.0%})")
        # much nearer backwards than forwards: not a path that returns the way it came
        copies = np.flatnonzero((back < limits.reversed_m) & (back < 0.2 * fwd) & (np.arange(len(names)) != k))
        if len(copies):
            m = int(copies[0])
            figs[n]["flags"].append(f"time-reversed: its path is {names[m]}'s run backwards ({1000 * back[m]:.1f} mm "
                                    f"RMS, limit {1000 * limits.reversed_m:.0f} mm)")
