"""Franka Kitchen (gymnasium-robotics 1.4.2 FrankaKitchen-v1, the seed's Table 2 benchmark) and a scripted,
IK-driven demonstrator for the seed's four tasks: microwave, light switch, slide cabinet, then the kettle (the
environment counts them as a set; the kettle goes last because it alone needs the fingers pointing down, and
turning them forward again after it knocked the kettle or hit the open door in every try).

The environment is gymnasium-robotics' own: a 9-joint Franka (7 arm joints, 2 fingers) in the D4RL kitchen, 12.5 Hz
control (40 physics steps of 2 ms), actions = joint velocities in [-1, 1] (x 2 rad/s) that its position actuators
integrate, a 59-D observation (robot joint positions and velocities, the kitchen's joints, with sensor noise), and a
task counted done when its joints come within 0.3 of the goal. Initial conditions: the environment's start pose is
fixed, so a seed also turns the seven arm joints by up to INITIAL_JITTER rad (uniform), as a robot never starts
exactly where it stopped; the sensor noise is seeded by the same seed.

gymnasium-robotics 1.4.2 fails on mujoco 4.0: its get_joint_qpos/get_joint_qvel assert
`model.jnt_type[i] in (mjJNT_HINGE, mjJNT_SLIDE)`, and mujoco 4.0's joint types no longer compare equal inside a
tuple. `_patch_joint_readers` replaces the two readers (the same slices, joint type read as an int) only when the
installed version fails that check, so a fixed release runs untouched.

The demonstrator plans in Cartesian space and acts in joint space: each segment is a straight line (or an arc, for
the microwave door) of the end-effector site, solved by damped least-squares IK (joints at their limits dropped
from the solve) on a copy of the state, tracked with an integral term against the actuators' sag under gravity.
"""

from __future__ import annotations

import contextlib
import io
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache

import numpy as np

from ..plumbing.errors import AdlError

ENV_ID = "FrankaKitchen-v1"
TASKS = ("microwave", "kettle", "light switch", "slide cabinet")  # the seed's (and D4RL's kitchen-complete) order
MAX_STEPS = 280  # the environment's episode limit (22.4 s), for demonstrations and policies alike
CONTROL_HZ = 12.5
INITIAL_JITTER = 0.05  # rad per arm joint
ARM_LO = np.array([-2.9, -1.8, -2.9, -3.1, -2.9, 0.0, -2.9])  # the robot's configured position bounds
ARM_HI = np.array([2.9, 1.8, 2.9, 0.0, 2.9, 3.8, 2.9])
VELOCITY_SCALE = 2.0  # rad/s per unit of action (the environment's act_rng)
DT = 1.0 / CONTROL_HZ
KETTLE_GOAL = np.array([-0.23, 0.75, 1.62])
_NDIM = {0: (7, 6), 1: (4, 3), 2: (1, 1), 3: (1, 1)}  # mjtJoint free, ball, slide, hinge: (qpos, qvel) sizes


@cache  # once per process: the probe compiles a model
def _patch_joint_readers() -> None:
    import mujoco
    from gymnasium_robotics.utils import mujoco_utils as mu

    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><body><joint name='probe' type='hinge'/>"
                                           "<geom size='.1'/></body></worldbody></mujoco>")
    try:
        mu.get_joint_qpos(model, mujoco.MjData(model), model.joint(0).name)
        return  # the installed version reads hinge joints: nothing to patch
    except AssertionError:
        pass

    def reader(kind: int) -> object:
        def read(m: object, d: object, name: str) -> np.ndarray:
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            if j < 0:
                raise AdlError(f"Franka Kitchen: no joint {name!r} in the model")
            size = _NDIM[int(m.jnt_type[j])][kind]
            start = (m.jnt_qposadr if kind == 0 else m.jnt_dofadr)[j]
            return (d.qpos if kind == 0 else d.qvel)[start:start + size].copy()
        return read

    mu.get_joint_qpos, mu.get_joint_qvel = reader(0), reader(1)


def make_env() -> object:
    """FrankaKitchen-v1 with the seed's four tasks (one line if the optional extra is missing)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import gymnasium as gym

        with contextlib.redirect_stderr(io.StringIO()):  # its import prints a notice about the Adroit environments
            import gymnasium_robotics
    except ImportError as exc:
        raise AdlError(f"Franka Kitchen needs gymnasium-robotics ({exc.name} is missing): "
                       "pip install -e '.[kitchen]'") from None
    _patch_joint_readers()
    gym.register_envs(gymnasium_robotics)
    return gym.make(ENV_ID, tasks_to_complete=list(TASKS), max_episode_steps=MAX_STEPS, disable_env_checker=True)


def reset(env: object, seed: int) -> np.ndarray:
    """Reset to initial condition `seed`: the environment's start, arm joints turned by the seeded jitter. Returns
    the 59-D observation."""
    import mujoco

    env.reset(seed=seed)
    u = env.unwrapped
    rng = np.random.default_rng([seed, 7])
    u.data.qpos[:7] += rng.uniform(-INITIAL_JITTER, INITIAL_JITTER, 7)
    mujoco.mj_forward(u.model, u.data)
    return u._get_obs(u.robot_env._get_obs())["observation"].copy()


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _axis_angle(R: np.ndarray) -> tuple[np.ndarray, float]:
    angle = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    n = np.linalg.norm(axis)
    return (axis / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])), angle


def _rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _rot_error(R: np.ndarray, goal: np.ndarray) -> np.ndarray:
    return 0.5 * sum(np.cross(R[:, i], goal[:, i]) for i in range(3))


class ArmIK:
    """Damped least-squares IK of the end-effector site over the seven arm joints, on a scratch copy of the state."""

    def __init__(self, model: object, data: object) -> None:
        import mujoco

        self.mj, self.model, self.data = mujoco, model, data
        self.scratch = mujoco.MjData(model)
        self.site = model.site("end_effector").id
        self.rest = data.qpos[:7].copy()

    def pose(self, d: object | None = None) -> tuple[np.ndarray, np.ndarray]:
        d = d or self.data
        return d.site_xpos[self.site].copy(), d.site_xmat[self.site].reshape(3, 3).copy()

    def solve(self, p_goal: np.ndarray, R_goal: np.ndarray, q_start: np.ndarray, iters: int = 100,
              w_rot: float = 0.5) -> np.ndarray:
        d = self.scratch
        d.qpos[:] = self.data.qpos
        d.qpos[:7] = q_start
        for _ in range(iters):
            self.mj.mj_kinematics(self.model, d)
            self.mj.mj_comPos(self.model, d)
            p, R = self.pose(d)
            err = np.concatenate([p_goal - p, w_rot * _rot_error(R, R_goal)])
            if np.linalg.norm(err) < 1e-4:
                break
            jp, jr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
            self.mj.mj_jacSite(self.model, d, jp, jr, self.site)
            J = np.vstack([jp[:, :7], w_rot * jr[:, :7]])
            q, free = d.qpos[:7].copy(), np.ones(7, bool)
            for _pass in range(3):  # a joint at its limit that the step would push further leaves the solve
                Jf = J * free
                dq = Jf.T @ np.linalg.solve(Jf @ Jf.T + 1e-3 * np.eye(6), err)
                dq += (np.eye(7) - np.linalg.pinv(Jf) @ Jf) @ (0.02 * (self.rest - q)) * free
                blocked = ((q <= ARM_LO + 0.021) & (dq < 0)) | ((q >= ARM_HI - 0.021) & (dq > 0))
                if not (blocked & free).any():
                    break
                free &= ~blocked
            d.qpos[:7] = np.clip(q + np.clip(dq, -0.1, 0.1), ARM_LO + 0.02, ARM_HI - 0.02)
        return d.qpos[:7].copy()


@dataclass
class Segment:
    """Move the end-effector site to `goal(now)` with orientation R in `steps` control steps (then let the arm
    settle, up to `settle` more), the fingers open or closed; `arc` (hinge point, angle): turn about a vertical
    axis instead of a straight line."""
    goal: object  # callable (KitchenScript) -> target position, evaluated when the segment starts
    R: np.ndarray
    grip: bool  # closed
    steps: int
    settle: int = 0
    smooth: bool = False
    arc: tuple[np.ndarray, float] | None = None


class KitchenScript:
    """The demonstrator: act() -> the next 9-D action, until the script ends (then it holds still)."""

    def __init__(self, env: object) -> None:
        u = env.unwrapped
        self.data = u.data
        self.ik = ArmIK(u.model, u.data)
        self.q_ref = self.data.qpos[:7].copy()
        self.integral = np.zeros(7)
        self.R_forward = self.ik.pose()[1]  # the start orientation: fingers forward (+y), opening along x
        self.R_down = np.array([[-1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])  # fingers down, opening along y
        self.plan = iter(self._script())

    def site(self, name: str) -> np.ndarray:
        return self.data.site(name).xpos.copy()

    def body(self, name: str) -> np.ndarray:
        return self.data.body(name).xpos.copy()

    def kettle(self) -> np.ndarray:
        return self.body("kettleroot")

    def _script(self) -> Iterator[tuple[np.ndarray, bool]]:
        """(joint target, fingers closed) per control step."""
        fwd, down = self.R_forward, self.R_down
        here = lambda s: self.ik.pose()[0]  # noqa: E731
        handle = self.site("microhandle_site")
        hinge = self.body("microdoorroot")
        segments = [
            # microwave: grasp the handle, swing it open about the door's hinge, let go, back off
            Segment(lambda s: handle + [0, -0.12, 0], fwd, False, 14, settle=8),
            Segment(lambda s: handle, fwd, False, 6, settle=10),
            Segment(here, fwd, True, 4),
            Segment(here, fwd, True, 6),
            Segment(here, fwd, True, 56, arc=(hinge, -1.0)),  # slowly: a faster swing slips out of the grasp
            Segment(here, None, False, 3),
            Segment(lambda s: here(s) + [0, -0.1, 0.1], None, False, 6),
            # light switch: fingers closed, push the lever from its right towards -x
            Segment(lambda s: s.site("light_site") + [0.08, -0.1, 0], fwd, True, 14, settle=8),
            Segment(lambda s: s.site("light_site") + [0.08, 0.015, 0.01], fwd, True, 6, settle=8),
            Segment(lambda s: s.site("light_site") + [-0.18, 0.015, 0.01], fwd, True, 12),
            Segment(lambda s: here(s) + [0, -0.1, 0], fwd, True, 4),
            # slide cabinet: push the handle from its left towards +x
            Segment(lambda s: s.site("slide_site") + [-0.08, -0.02, 0], fwd, True, 8, settle=6),
            Segment(lambda s: s.site("slide_site") + [0.3, -0.02, 0], fwd, True, 14),
            Segment(lambda s: here(s) + [0, -0.1, 0], fwd, True, 5),
            # kettle: turn the fingers down high above the stove, grasp the handle from above, lift, carry it to
            # the top burner, set it down
            Segment(lambda s: s.site("kettle_site") + [0, -0.1, 0.3], down, False, 14, settle=8),
            Segment(lambda s: s.site("kettle_site") + [0, 0, 0.12], down, False, 8, settle=8),
            Segment(lambda s: s.site("kettle_site"), down, False, 6, settle=10),
            Segment(here, down, True, 4),
            Segment(lambda s: here(s) + [0, 0, 0.08], down, True, 6),
            Segment(lambda s: here(s) + (KETTLE_GOAL - s.kettle()) * [1, 1, 0], down, True, 28, smooth=True),
            Segment(lambda s: here(s) - [0, 0, 0.07], down, True, 5),
            Segment(here, down, False, 3),
            Segment(lambda s: here(s) + [0, 0, 0.15], down, False, 6),
        ]
        for seg in segments:
            start, R_now = self.ik.pose()
            R = R_now if seg.R is None else seg.R
            goal = seg.goal(self)
            axis, angle = _axis_angle(R_now.T @ R)
            for k in range(1, seg.steps + 1):
                a = k / seg.steps
                a = a * a * (3 - 2 * a) if seg.smooth else a
                if seg.arc is not None:
                    centre, swing = seg.arc
                    turn = rot_z(swing * a)
                    p, Rk = centre + turn @ (start - centre), turn @ R
                else:  # position along the line, orientation turned by the same share
                    p, Rk = start + (goal - start) * a, R_now @ _rodrigues(axis, angle * a)
                self.q_ref = self.ik.solve(p, Rk, self.q_ref)
                yield self.q_ref, seg.grip
            for _ in range(seg.settle):
                if np.abs(self.q_ref - self.data.qpos[:7]).max() < 0.01:
                    break
                yield self.q_ref, seg.grip

    def act(self) -> np.ndarray:
        q_goal, closed = next(self.plan, (self.q_ref, False))
        err = q_goal - self.data.qpos[:7]
        self.integral = np.clip(self.integral + 0.3 * err, -0.1, 0.1)
        action = np.empty(9)
        action[:7] = np.clip((err + self.integral) / (DT * VELOCITY_SCALE), -1.0, 1.0)
        action[7:] = -1.0 if closed else 1.0
        return action


@dataclass
class Step:
    obs: np.ndarray  # the 59-D observation the action was chosen on
    action: np.ndarray
    info: dict  # after the action: tasks completed so far


def demonstrate(env: object, seed: int, max_steps: int = MAX_STEPS,
                sense: Callable[[], None] | None = None) -> Iterator[Step]:
    """Run the scripted demonstrator from initial condition `seed` until all four tasks are done or the limit;
    `sense()` is called on the scene each action is chosen on (the recorder's sensors)."""
    obs = reset(env, seed)
    script = KitchenScript(env)
    for _ in range(max_steps):
        if sense is not None:
            sense()
        action = script.act()
        nxt, _r, done, _trunc, info = env.step(action)
        yield Step(obs, action, info)
        obs = nxt["observation"].copy()
        if done:
            return


def completed(info: dict) -> set[str]:
    return set(info.get("episode_task_completions", []))


TASK = "franka kitchen"
CAMERA = {"distance": 2.2, "azimuth": 70.0, "elevation": -35.0, "lookat": (-0.2, 0.5, 2.0)}  # gymnasium-robotics'


def camera_model(model: object, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(K, T_base_camera) of the free camera the environment renders with (its DEFAULT_CAMERA_CONFIG, MuJoCo's
    vertical field of view), as a ROS optical frame (x right, y down, z forward) in the kitchen's world frame."""
    az, el = np.deg2rad(CAMERA["azimuth"]), np.deg2rad(CAMERA["elevation"])
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([right, np.cross(forward, right), forward])
    T[:3, 3] = np.asarray(CAMERA["lookat"]) - CAMERA["distance"] * forward
    f = 0.5 * size / np.tan(np.deg2rad(model.vis.global_.fovy) / 2)
    return np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]]), T


class KitchenCamera:
    """The environment's view (CAMERA) rendered with MuJoCo's Renderer without shadows, reflections and
    multisampling: 37 ms a 64 px frame on a CPU-only machine instead of 500 ms (the kitchen's meshes under
    software GL)."""

    def __init__(self, model: object, size: int) -> None:
        import mujoco

        model.vis.quality.shadowsize, model.vis.quality.offsamples = 0, 0  # visual only: physics is untouched
        self.renderer = mujoco.Renderer(model, size, size)
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                     mujoco.mjtRndFlag.mjRND_SKYBOX):
            self.renderer.scene.flags[flag] = 0
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.distance, self.camera.azimuth = CAMERA["distance"], CAMERA["azimuth"]
        self.camera.elevation, self.camera.lookat[:] = CAMERA["elevation"], CAMERA["lookat"]

    def render(self, data: object) -> np.ndarray:
        self.renderer.update_scene(data, camera=self.camera)
        return self.renderer.render().copy()

    def close(self) -> None:
        self.renderer.close()


def robot_joint_names(model: object) -> list[str]:
    return [model.joint(i).name.split(":")[-1] for i in range(9)]


def observation_names(model: object) -> list[str]:
    """Names of the 59 observation dimensions: robot joint positions and velocities, then the kitchen's."""
    robot = robot_joint_names(model)
    qpos, qvel = [], []
    for j in range(9, model.njnt):
        name = model.joint(j).name
        free = int(model.jnt_type[j]) == 0
        qpos += [f"{name}_{a}" for a in ("x", "y", "z", "qw", "qx", "qy", "qz")] if free else [name]
        qvel += [f"{name}_{a}" for a in ("vx", "vy", "vz", "wx", "wy", "wz")] if free else [f"{name}_vel"]
    return [f"{n}_pos" for n in robot] + [f"{n}_vel" for n in robot] + qpos + qvel


def record(seed: int, size: int = 64) -> object:
    """One demonstration from initial condition `seed` as sensor streams (adlpipe.sim.episode.Streams): the rendered
    image, the robot's 9 joints, the end-effector site as tf, the kettle's pose, the 59-D observation as the state
    and the 9-D joint-velocity action, all at the control rate. success: all four tasks done."""
    from ..geometry.transforms import matrix_to_quat
    from ..sim.episode import Streams
    from ..sim.world import SceneSpec

    env = make_env()
    u = env.unwrapped
    m, d = u.model, u.data
    camera = KitchenCamera(m, size)
    try:
        K, T = camera_model(m, size)
        site, kettle = m.site("end_effector").id, m.body("kettleroot").id
        st = Streams(TASK, SceneSpec(task=TASK, poses={}), size, size, K, T, joint_names=robot_joint_names(m),
                     state_names=observation_names(m), action_names=[m.actuator(i).name for i in range(9)])

        def sense() -> None:  # stamped at the control step whose action is chosen on this scene
            t = len(st.camera) / CONTROL_HZ
            st.camera.append((t, camera.render(d), None))
            st.joints.append((t, d.qpos[:9].copy(), d.qvel[:9].copy()))
            st.ee.append((t, d.site_xpos[site].copy(), matrix_to_quat(d.site_xmat[site].reshape(3, 3))))
            st.objects.append((t, {"kettle": (d.xpos[kettle].copy(), d.xquat[kettle].copy())}))

        info: dict = {}
        for i, step in enumerate(demonstrate(env, seed, sense=sense)):
            st.states.append((i / CONTROL_HZ, step.obs))
            st.actions.append((i / CONTROL_HZ, step.action))
            info = step.info
    finally:
        camera.close()
        env.close()
    st.success = completed(info) == set(TASKS)
    st.duration = len(st.camera) / CONTROL_HZ
    return st


REFERENCES = ("demonstrator",)  # holding still completes nothing: no reference needed for the bottom of the scale


def _outcome(done: set[str]) -> dict:
    """An episode's score: the share of the four tasks done; success: all four."""
    return {"score": len(done) / len(TASKS), "success": done == set(TASKS), "tasks": sorted(done)}


def run_policy(plan: Callable[[None, np.ndarray], np.ndarray], seed: int, execute: int, n_obs: int,
               max_steps: int = MAX_STEPS, state_only: bool = True) -> dict:
    """The seed's closed loop on Franka Kitchen from initial condition `seed`: plan(None, states) -> actions (Tp, 9)
    from the last n_obs 59-D observations (the first repeated before the start; a state-only policy sees no image),
    execute the first `execute`, re-plan, until all four tasks are done or the 280-step limit. (Its policies are
    state-only: state_only is there for the benchmark's one call signature.)"""
    if not state_only:
        raise ValueError("Franka Kitchen runs state-only policies")
    env = make_env()
    try:
        history = [reset(env, seed)] * n_obs
        done_tasks: set[str] = set()
        plans, steps, done = 0, 0, False
        while steps < max_steps and not done:
            actions = np.asarray(plan(None, np.stack(history)))
            plans += 1
            for a in actions[:execute]:
                obs, _r, done, _trunc, info = env.step(np.clip(a, -1.0, 1.0))
                history = history[1:] + [obs["observation"].copy()]
                done_tasks |= completed(info)
                steps += 1
                if done or steps >= max_steps:
                    break
        return {**_outcome(done_tasks), "plans": plans}
    finally:
        env.close()


def reference(kind: str, seed: int) -> dict:
    """The scripted demonstrator from one initial condition, scored as run_policy scores a policy."""
    if kind != "demonstrator":
        raise ValueError(f"no kitchen reference {kind!r}")
    env = make_env()
    try:
        done: set[str] = set()
        for step in demonstrate(env, seed):
            done |= completed(step.info)
        return _outcome(done)
    finally:
        env.close()
