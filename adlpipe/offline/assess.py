"""Three answers per held-out recording and predicted trajectory, from what the recording holds (no simulated
world): feasible on the robot, safe in the scene the camera saw, and does what the demonstration did.

The demonstration itself is assessed first, on the same robot and scene: where its arm touched or went behind an
observed surface are the task's intended contacts, and its gripper events, first and last contact and end pose are
the key poses a prediction must reach in order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import h5py
import numpy as np
from scipy.spatial import cKDTree

from ..curation.doctor import gripper_crossings
from ..geometry.camera import read_lens
from .robot import Robot, Tolerances
from .scene import DepthScene


@dataclass(frozen=True)
class Criteria:
    """The stated tolerances of the three verdicts."""

    robot: Tolerances = field(default_factory=Tolerances)
    touch_m: float = 0.01  # a robot point this close to (or behind) an observed surface touches it
    penetration_m: float = 0.02  # deeper behind an observed surface, outside the intended contact: unsafe
    contact_margin_m: float = 0.03  # around the demonstration's own contact points, contact is intended
    affordance_level: float = 0.3  # pixels of the affordance map above this are intended contact too
    key_m: float = 0.03  # a key pose is reached when a waypoint comes this close


@dataclass
class Context:
    """What an episode's recording gives every assessment of it: the robot's start, the scene, the intended
    contact, the key poses."""

    q0: np.ndarray
    dt: float
    scene: DepthScene
    affordance: np.ndarray
    contact: cKDTree | None  # robot points where the demonstration touched, base frame
    keys: list[tuple[str, np.ndarray]]  # (what, position) in time order
    demo: dict
    seen: bool = True  # the recording has a depth image: without one, safety is not assessed (None), not "safe"


def _touches(robot: Robot, samples: dict, scene: DepthScene, Q: np.ndarray, crit: Criteria) -> list[np.ndarray]:
    """Per waypoint: the robot's surface points that touch or lie behind an observed surface."""
    out = []
    for q in Q:
        pts = robot.surface_points(q, samples)
        beh = scene.behind(pts)
        out.append(pts[np.nan_to_num(beh, nan=-np.inf) > -crit.touch_m])
    return out


def context(g: h5py.Group, robot: Robot, samples: dict, crit: Criteria) -> Context:
    """The episode's start state, scene and the demonstration's own contacts and key poses."""
    names = [str(n) for n in g["series/joint_pos"].attrs["joint_names"]]
    q0 = robot.start_q(names, g["frames/joint_pos"][0].astype(float))
    demo = np.asarray(g["traj3d"][()], float)
    dt = float(g.attrs["duration_s"]) / (len(demo) - 1)
    depth = g["depth"][()] if "depth" in g else np.full(g["rgb"].shape[:2], np.nan, np.float32)
    scene = DepthScene.from_depth(depth, g["K"][()], g["T_base_camera"][()], read_lens(g),
                                  robot.surface_points(q0, samples))
    feas = robot.feasibility(demo, q0, dt, crit.robot)
    touching = _touches(robot, samples, scene, feas.q, crit)
    in_contact = [i for i, t in enumerate(touching) if len(t)]
    contact = cKDTree(np.concatenate([touching[i] for i in in_contact])) if in_contact else None
    keys = [(f"gripper event at {t:.1f} s", p) for t, p in gripper_events(g)]
    if in_contact:
        keys += [("contact start", demo[in_contact[0]]), ("contact end", demo[in_contact[-1]])]
    keys = sorted(keys, key=lambda k: _time_of(demo, k[1]))
    keys.append(("end pose", demo[-1]))
    return Context(q0, dt, scene, g["affordance"][()], contact, keys,
                   {"feasible": feas.feasible, "contact_waypoints": len(in_contact)}, seen="depth" in g)


def _time_of(path: np.ndarray, p: np.ndarray) -> int:
    return int(np.linalg.norm(path - p, axis=1).argmin())


def gripper_events(g: h5py.Group) -> list[tuple[float, np.ndarray]]:
    """(time, end-effector position) where the recorded gripper crosses the middle of its range (grasp or release;
    doctor's gripper_crossings)."""
    fr = g["frames"]
    t, ee = fr["t"][()], fr["ee_pos"][()].astype(float)
    return [(float(t[k]), ee[k]) for k in gripper_crossings(fr["gripper"][()]) or []]


def assess(robot: Robot, samples: dict, ctx: Context, waypoints: np.ndarray, crit: Criteria) -> dict:
    """The three verdicts of one predicted trajectory (N, 3), with their figures."""
    feas = robot.feasibility(waypoints, ctx.q0, ctx.dt, crit.robot)
    clearances: list[float] = []
    worst, worst_at = 0.0, None
    for q in feas.q:
        pts = robot.surface_points(q, samples)
        clearances.append(float(ctx.scene.clearance(pts).min()))
        beh = ctx.scene.behind(pts)
        uv = ctx.scene.pixels(pts)
        allowed = ctx.affordance[uv[:, 1], uv[:, 0]] > crit.affordance_level
        if ctx.contact is not None:
            allowed |= ctx.contact.query(pts)[0] < crit.contact_margin_m
        unintended = ~allowed & np.isfinite(beh)
        if unintended.any() and beh[unintended].max() > worst:
            k = np.flatnonzero(unintended)[int(beh[unintended].argmax())]
            worst, worst_at = float(beh[k]), pts[k].round(3).tolist()
    reached, missed, start = [], [], 0
    for what, p in ctx.keys:
        d = np.linalg.norm(waypoints[start:] - p, axis=1)
        hit = np.flatnonzero(d < crit.key_m)
        if len(hit):
            start += int(hit[0])
            reached.append(what)
        else:
            missed.append(what)
    safe = worst <= crit.penetration_m if ctx.seen else None
    seen_worst = worst if ctx.seen else None  # no depth image: nothing was seen to be behind
    if not ctx.seen:
        worst_at = None
    return {"feasible": feas.feasible, "why_infeasible": feas.why, "reach_m": float(feas.residual_m.max()),
            "limit_violations": feas.limit_violations, "max_joint_speed": feas.max_speed,
            "max_joint_accel": feas.max_accel, "self_collisions": feas.self_collisions,
            "safe": safe, "penetration_m": seen_worst, "penetration_at": worst_at,
            "min_clearance_m": min(clearances) if ctx.seen else None,
            "does_what_demo_did": not missed, "key_poses": len(ctx.keys), "missed": missed,
            "pass": None if safe is None else feas.feasible and safe and not missed}
