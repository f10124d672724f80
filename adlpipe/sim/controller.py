"""Arm control: damped-least-squares IK on the tcp (position + fixed downward orientation) feeding the joint PD
position actuators, plus the grasp rule shared by the demonstrator and the replay of predicted trajectories."""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from .world import ARM_JOINTS, GRASPABLE, HOME_Q, HOME_TCP

GRASP_RADIUS = 0.01  # the fingers close on an object only with the tcp within 1 cm of its grasp site
TARGET_ROT = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # hand z down, x along world x


class ArmController:
    """Tracks tcp targets with the 7-DoF arm; closes/opens the gripper with a weld that holds the object."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        self.m, self.d = model, data
        self.qadr = np.array([model.jnt_qposadr[model.joint(j).id] for j in ARM_JOINTS])
        self.dadr = np.array([model.jnt_dofadr[model.joint(j).id] for j in ARM_JOINTS])
        self.tcp = model.site("tcp").id
        self.hand = model.body("hand").id
        self.q_des = HOME_Q.copy()
        self.target = HOME_TCP.copy()  # the last tcp setpoint commanded (what a robot's command topic carries)
        self.held: str | None = None
        self.released: set[str] = set()
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))
        # Grasp sites are named <object>_grasp, or <object>_grasp_<side> where an object has several.
        self._grasp_sites: dict[str, list[int]] = {}
        for i in range(model.nsite):
            obj, sep, _side = model.site(i).name.partition("_grasp")
            if sep:
                self._grasp_sites.setdefault(obj, []).append(i)
        self._prev_dist: dict[str, float] = {}
        self.person: Callable[[mujoco.MjData, float], None] | None = None  # moves the person (sim.person.mover)

    def step(self) -> None:
        """One physics step, the person (when one moves) first put where they are at this time."""
        if self.person is not None:
            self.person(self.d, self.d.time)
        mujoco.mj_step(self.m, self.d)

    def reset_home(self, tcp_target: np.ndarray = HOME_TCP) -> None:
        """Put the arm (kinematically) at the posture whose tcp is at tcp_target, hand pointing down."""
        m, d = self.m, self.d
        d.qpos[self.qadr] = HOME_Q
        for _ in range(300):
            mujoco.mj_forward(m, d)
            self.set_target(tcp_target)
            d.qpos[self.qadr] = self.q_des
        mujoco.mj_forward(m, d)
        self.target = self.tcp_pos
        d.qvel[:] = 0.0
        d.ctrl[: len(ARM_JOINTS)] = d.qpos[self.qadr]
        d.ctrl[len(ARM_JOINTS):] = 0.04

    @property
    def tcp_pos(self) -> np.ndarray:
        return self.d.site_xpos[self.tcp].copy()

    @property
    def gripper_command(self) -> float:
        """The fingers' position command: 0.04 open, 0 closed (a grasp)."""
        return float(self.d.ctrl[len(ARM_JOINTS)])

    @property
    def gripper_pos(self) -> float:
        """The measured opening of one finger (what the joint state reports as the gripper joint)."""
        return float(self.d.qpos[self.m.jnt_qposadr[self.m.joint("finger_left").id]])

    def set_target(self, target: np.ndarray) -> None:
        """One resolved-rate IK step towards the tcp target; writes the joint position commands."""
        m, d = self.m, self.d
        self.target = np.array(target, float)
        mujoco.mj_jacSite(m, d, self._jacp, self._jacr, self.tcp)
        J = np.vstack([self._jacp[:, self.dadr], self._jacr[:, self.dadr]])
        err_p = target - d.site_xpos[self.tcp]
        R = d.site_xmat[self.tcp].reshape(3, 3)
        err_r = 0.5 * (np.cross(R[:, 0], TARGET_ROT[:, 0]) + np.cross(R[:, 1], TARGET_ROT[:, 1])
                       + np.cross(R[:, 2], TARGET_ROT[:, 2]))
        err = np.concatenate([np.clip(err_p, -0.05, 0.05), 0.5 * err_r])
        lam = 1e-2
        JJt = J @ J.T + lam * np.eye(6)
        J_pinv = J.T @ np.linalg.solve(JJt, np.eye(6))
        q = d.qpos[self.qadr]
        # Null-space pull towards home keeps the redundant DoF (elbow) from drifting.
        null = (np.eye(7) - J_pinv @ J) @ (0.05 * (HOME_Q - q))
        self.q_des = q + J_pinv @ err + null
        d.ctrl[: len(ARM_JOINTS)] = self.q_des

    # -- gripper -------------------------------------------------------------------------------------------
    def _weld_id(self, obj: str) -> int:
        return self.m.equality(f"grasp_{obj}").id

    def grasp(self, obj: str) -> None:
        """Close the fingers and weld the object to the hand at its current relative pose."""
        m, d = self.m, self.d
        b = m.body(obj).id
        R1 = d.xmat[self.hand].reshape(3, 3)
        relpos = R1.T @ (d.xpos[b] - d.xpos[self.hand])
        q1inv = np.zeros(4)
        mujoco.mju_negQuat(q1inv, d.xquat[self.hand])
        relquat = np.zeros(4)
        mujoco.mju_mulQuat(relquat, q1inv, d.xquat[b])
        eq = self._weld_id(obj)
        m.eq_data[eq, 0:3] = 0.0
        m.eq_data[eq, 3:6] = relpos
        m.eq_data[eq, 6:10] = relquat
        d.eq_active[eq] = 1
        d.ctrl[len(ARM_JOINTS):] = 0.0
        self.held = obj

    def release(self) -> None:
        if self.held is not None:
            self.d.eq_active[self._weld_id(self.held)] = 0
            self.released.add(self.held)
            self.held = None
        self.d.ctrl[len(ARM_JOINTS):] = 0.04

    def auto_grasp(self) -> None:
        """The grasp rule: an open gripper takes an unreleased object once its tcp is within GRASP_RADIUS of the
        object's grasp site and has stopped getting closer (so a tcp still descending onto it does not grasp early).
        """
        if self.held is not None:
            return
        for obj in GRASPABLE:
            if obj in self.released or obj not in self._grasp_sites:
                continue
            dist = min(float(np.linalg.norm(self.d.site_xpos[i] - self.tcp_pos)) for i in self._grasp_sites[obj])
            prev = self._prev_dist.get(obj, np.inf)
            self._prev_dist[obj] = dist
            if dist < GRASP_RADIUS and dist >= prev - 1e-5:
                self.grasp(obj)
                return


def track_path(ctrl: ArmController, path_fn: Callable[[float], np.ndarray], duration: float,
               on_step: Callable[[float], None] | None = None, control_hz: float = 250.0,
               t_offset: float = 0.0) -> None:
    """Track tcp(t) for `duration` seconds (the grasp rule active); on_step(t) after every physics step, with
    t counted from t_offset (the start of the whole execution)."""
    m, d = ctrl.m, ctrl.d
    n_sub = max(1, round(1.0 / (control_hz * m.opt.timestep)))
    t0 = d.time
    for i in range(int(round(duration / m.opt.timestep))):
        if i % n_sub == 0:
            ctrl.set_target(path_fn(min(d.time - t0, duration)))
            ctrl.auto_grasp()
        ctrl.step()
        if on_step is not None:
            on_step(t_offset + d.time - t0)


def release_and_settle(ctrl: ArmController, hold: np.ndarray, settle: float = 0.4,
                       on_step: Callable[[float], None] | None = None, t_offset: float = 0.0) -> None:
    """Open the gripper (releasing what is held), hold the tcp at `hold` and let the scene settle."""
    m, d = ctrl.m, ctrl.d
    ctrl.release()
    t0 = d.time
    for i in range(int(round(settle / m.opt.timestep))):
        if i % 8 == 0:
            ctrl.set_target(hold)
        ctrl.step()
        if on_step is not None:
            on_step(t_offset + d.time - t0)


def execute_path(
    ctrl: ArmController,
    path_fn: Callable[[float], np.ndarray],
    duration: float,
    on_step: Callable[[float], None] | None = None,
    settle: float = 0.4,
    control_hz: float = 250.0,
) -> None:
    """Track tcp(t) for `duration` seconds, release what is held at the end and let the scene settle.

    on_step(t) is called after every physics step (recording, success bookkeeping).
    """
    ctrl.d.ctrl[len(ARM_JOINTS):] = 0.04  # start open
    track_path(ctrl, path_fn, duration, on_step, control_hz)
    release_and_settle(ctrl, path_fn(duration), settle, on_step, t_offset=duration)
