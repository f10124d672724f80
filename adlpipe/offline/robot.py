"""A lab's robot as a MuJoCo model: inverse kinematics of predicted end-effector waypoints from the recorded joint
state, and whether the joint path is feasible (reach, joint limits, joint speed and acceleration at the waypoint
rate, self-collision), with MuJoCo's own kinematics, Jacobians and collision detection."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from ..plumbing.errors import AdlError


@dataclass(frozen=True)
class Tolerances:
    """What "feasible" means; every figure is reported beside its verdict."""

    reach_m: float = 0.01  # IK residual: the end effector within this of every waypoint
    max_speed: float = 2.0  # rad/s (m/s for a slide joint) between waypoints
    max_accel: float = 20.0  # rad/s^2 between waypoints
    limit_margin: float = 0.0  # rad inside the joint range


@dataclass
class Feasibility:
    q: np.ndarray  # (N, J) the joint path IK found
    residual_m: np.ndarray  # (N,) end-effector distance to each waypoint
    limit_violations: int  # waypoints with a joint outside its range
    max_speed: float
    max_accel: float
    self_collisions: int  # waypoints where two robot parts touch that do not touch at the recorded start
    feasible: bool
    why: list[str]


class Robot:
    """A MuJoCo model of the robot; `ee_site` is the end effector whose path the policies predict, in the model's
    world frame (the bags' base frame). Every geom is made to collide with every other for the self-collision
    check (MuJoCo still skips parent-child pairs)."""

    def __init__(self, xml: str | None = None, path: Path | None = None, ee_site: str = "tcp") -> None:
        try:
            self.model = (mujoco.MjModel.from_xml_path(str(path)) if path is not None
                          else mujoco.MjModel.from_xml_string(xml))
        except (ValueError, OSError) as exc:
            raise AdlError(f"{path or 'robot model'}: not a MuJoCo model ({' '.join(str(exc).split())[:160]})") \
                from None
        m = self.model
        self.site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, ee_site)
        if self.site < 0:
            sites = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(m.nsite)]
            raise AdlError(f"{path or 'robot model'}: no site {ee_site!r} for the end effector (sites: {sites})")
        m.geom_contype[:] = 1
        m.geom_conaffinity[:] = 1
        self.data = mujoco.MjData(m)
        self.joints = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(m.njnt)
                       if int(m.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))]
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in self.joints]
        self.qadr = np.array([m.jnt_qposadr[j] for j in ids])
        self.dadr = np.array([m.jnt_dofadr[j] for j in ids])
        self.limited = np.array([bool(m.jnt_limited[j]) for j in ids])
        self.range = np.array([m.jnt_range[j] for j in ids])
        self.geom_body = m.geom_bodyid.copy()

    def set_q(self, q: np.ndarray) -> None:
        self.data.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)

    def ee(self) -> np.ndarray:
        return self.data.site_xpos[self.site].copy()

    def start_q(self, names: list[str], values: np.ndarray) -> np.ndarray:
        """The model's joint vector from a recorded joint state (joints the recording lacks stay at the model's
        rest pose); one line when none of the model's joints is in the recording."""
        q = self.model.qpos0[self.qadr].copy()
        known = {n: float(v) for n, v in zip(names, values, strict=True) if np.isfinite(v)}
        hit = [i for i, j in enumerate(self.joints) if j in known]
        if not hit:
            raise AdlError(f"no joint of the robot model ({', '.join(self.joints)}) is in the recorded joint state "
                           f"({', '.join(names) or 'none'})")
        for i in hit:
            q[i] = known[self.joints[i]]
        return q

    def ik(self, target: np.ndarray, q: np.ndarray, iters: int = 200, damping: float = 0.02,
           tol: float = 1e-4) -> tuple[np.ndarray, float]:
        """Damped least squares on the end-effector position from q (MuJoCo's site Jacobian); returns the joints and
        the remaining distance. Joint limits are not enforced here: a solution outside them is reported, not
        hidden."""
        q = q.copy()
        jac = np.zeros((3, self.model.nv))
        for _ in range(iters):
            self.set_q(q)
            err = target - self.ee()
            if np.linalg.norm(err) < tol:
                break
            mujoco.mj_jacSite(self.model, self.data, jac, None, self.site)
            J = jac[:, self.dadr]
            q += J.T @ np.linalg.solve(J @ J.T + damping ** 2 * np.eye(3), err)
        self.set_q(q)
        return q, float(np.linalg.norm(target - self.ee()))

    def touching_pairs(self, q: np.ndarray) -> set[tuple[int, int]]:
        """Body pairs in contact at q (MuJoCo's collision detection over every geom pair it does not skip)."""
        self.set_q(q)
        mujoco.mj_collision(self.model, self.data)
        pairs = set()
        for c in self.data.contact[: self.data.ncon]:
            if c.dist < 0:
                a, b = int(self.geom_body[c.geom1]), int(self.geom_body[c.geom2])
                pairs.add((min(a, b), max(a, b)))
        return pairs

    def feasibility(self, waypoints: np.ndarray, q0: np.ndarray, dt: float, tol: Tolerances) -> Feasibility:
        """Joint path through the waypoints (each IK warm-started from the previous solution, the first from the
        recorded joint state) and its verdict."""
        qs, res = [], []
        q = q0
        for p in waypoints:
            q, r = self.ik(np.asarray(p, float), q)
            qs.append(q)
            res.append(r)
        Q, R = np.array(qs), np.array(res)
        lo, hi = self.range[:, 0] + tol.limit_margin, self.range[:, 1] - tol.limit_margin
        out = self.limited & ((Q < lo) | (Q > hi))
        limits = int(out.any(axis=1).sum())
        vel = np.abs(np.diff(Q, axis=0)) / dt if len(Q) > 1 else np.zeros((0, len(q0)))
        acc = np.abs(np.diff(Q, n=2, axis=0)) / dt ** 2 if len(Q) > 2 else np.zeros((0, len(q0)))
        structural = self.touching_pairs(q0)  # parts that touch in the recorded, real configuration
        collisions = sum(bool(self.touching_pairs(qi) - structural) for qi in Q)
        vmax, amax = float(vel.max(initial=0.0)), float(acc.max(initial=0.0))
        why = []
        if R.max() > tol.reach_m:
            why.append(f"out of reach by {R.max() * 100:.1f} cm (tolerance {tol.reach_m * 100:.1f} cm)")
        if limits:
            why.append(f"joint limits exceeded at {limits} waypoint(s)")
        if vmax > tol.max_speed:
            why.append(f"joint speed {vmax:.2f} (limit {tol.max_speed})")
        if amax > tol.max_accel:
            why.append(f"joint acceleration {amax:.1f} (limit {tol.max_accel})")
        if collisions:
            why.append(f"self-collision at {collisions} waypoint(s)")
        return Feasibility(Q, R, limits, vmax, amax, collisions, not why, why)

    def surface_points(self, q: np.ndarray, samples: dict[int, np.ndarray]) -> np.ndarray:
        """The robot's surface samples (geom id -> local points) in the world frame at q."""
        self.set_q(q)
        d = self.data
        return np.concatenate([d.geom_xpos[g] + pts @ d.geom_xmat[g].reshape(3, 3).T for g, pts in samples.items()])


def surface_samples(model: mujoco.MjModel, spacing: float = 0.015) -> dict[int, np.ndarray]:
    """Points on the surface of every visible geom of the model, in its own frame, about `spacing` apart: spheres,
    capsules, cylinders and boxes sampled on their surface, meshes by their vertices."""
    out = {}
    for g in range(model.ngeom):
        if model.geom_rgba[g, 3] == 0:
            continue
        kind, size = model.geom_type[g], model.geom_size[g]
        pts = _primitive_points(int(kind), size, spacing)
        if int(kind) == int(mujoco.mjtGeom.mjGEOM_MESH):
            mesh = model.geom_dataid[g]
            start, n = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
            pts = model.mesh_vert[start:start + n][:: max(1, n // 400)].astype(float)
        if pts is not None and len(pts):
            out[g] = pts
    return out


def _primitive_points(kind: int, size: np.ndarray, spacing: float) -> np.ndarray | None:
    G = mujoco.mjtGeom
    if kind == int(G.mjGEOM_SPHERE):
        return _sphere(size[0], spacing)
    if kind in (int(G.mjGEOM_CAPSULE), int(G.mjGEOM_CYLINDER)):
        r, h = size[0], size[1]
        n_ring = max(8, int(2 * np.pi * r / spacing))
        a = np.linspace(0, 2 * np.pi, n_ring, endpoint=False)
        z = np.linspace(-h, h, max(2, int(2 * h / spacing) + 1))
        side = np.stack([np.repeat(r * np.cos(a)[None], len(z), 0).ravel(),
                         np.repeat(r * np.sin(a)[None], len(z), 0).ravel(), np.repeat(z, n_ring)], 1)
        if kind == int(G.mjGEOM_CAPSULE):
            cap = _sphere(r, spacing)
            ends = np.concatenate([cap[cap[:, 2] > 0] + [0, 0, h], cap[cap[:, 2] < 0] - [0, 0, h]])
        else:
            disc = _disc(r, spacing)
            ends = np.concatenate([disc + [0, 0, h], disc - [0, 0, h]])
        return np.concatenate([side, ends])
    if kind == int(G.mjGEOM_BOX):
        axes = [np.linspace(-s, s, max(2, int(2 * s / spacing) + 1)) for s in size[:3]]
        faces = []
        for k in range(3):
            i, j = [a for a in range(3) if a != k]
            u, v = np.meshgrid(axes[i], axes[j], indexing="ij")
            for sign in (-1, 1):
                f = np.zeros((u.size, 3))
                f[:, i], f[:, j], f[:, k] = u.ravel(), v.ravel(), sign * size[k]
                faces.append(f)
        return np.concatenate(faces)
    return None


def _sphere(r: float, spacing: float) -> np.ndarray:
    n = max(12, int(4 * np.pi * r * r / spacing ** 2))
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = np.pi * (1 + 5 ** 0.5) * k
    return r * np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


def _disc(r: float, spacing: float) -> np.ndarray:
    pts = [np.zeros(3)]
    for rr in np.arange(spacing, r + 1e-9, spacing):
        a = np.linspace(0, 2 * np.pi, max(6, int(2 * np.pi * rr / spacing)), endpoint=False)
        pts += list(np.stack([rr * np.cos(a), rr * np.sin(a), np.zeros_like(a)], 1))
    return np.array(pts)
