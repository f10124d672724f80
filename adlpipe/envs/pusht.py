"""Push-T (gym-pusht 0.1.8, the seed's Table 2 benchmark) and a scripted demonstrator that plans its contacts.

The environment is gym-pusht's own: pymunk physics at 100 Hz, a PD-controlled disc (the agent) driven towards the
action (a target position in the 512 x 512 workspace, 10 Hz), the T block, and coverage of the goal pose as reward
(success above 0.95). gym-pusht declares opencv-python, which must not sit beside adlpipe's opencv-python-headless
(both own the cv2 module): the `pusht` extra installs its other requirements and gym-pusht itself goes in with
`pip install --no-deps gym-pusht==0.1.8` (Makefile); its cv2 calls work with the headless build.

The demonstrator: the block moves only while pushed (the space's damping of 0 removes all velocity every step), so
a push's effect can be simulated exactly. Before each push it simulates candidates in a copy of the physics (the
agent set at the pre-contact point, every contact point round the T's outline: straight pushes along the inward
normal, and arcs that turn the contact point about the block's centre of mass), and takes the one that lowers the
pose error most per control step, the approach included. The approach goes round the T when the straight way would
touch it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..plumbing.errors import AdlError

ENV_ID = "gym_pusht/PushT-v0"
MAX_STEPS = 300  # gym-pusht's episode limit (30 s at 10 Hz), for demonstrations and policies alike
AGENT_RADIUS = 15.0
RAD_WEIGHT = 60.0  # pose error: pixels of position + this many per radian of orientation
STRAIGHT_PUSHES = (10.0, 30.0, 70.0, 130.0)  # pixels beyond the contact point
ARC_TURNS = (-1.2, -0.6, -0.3, 0.3, 0.6, 1.2)  # radians about the centre of mass
CONTACT_POINTS = 20
MAX_APPROACH = 30  # control steps


def make_env(observation_size: int = 96, obs_type: str = "pixels_agent_pos") -> object:
    """gym-pusht's environment with pixel and agent-position observations, or another of its observation types
    (one line if the extra is missing)."""
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame draws off screen
    try:
        import gym_pusht  # noqa: F401 - registers the environment
        import gymnasium as gym
    except ImportError as exc:
        raise AdlError(f"Push-T needs gym-pusht ({exc.name} is missing): pip install -e '.[pusht]' && "
                       "pip install --no-deps gym-pusht==0.1.8") from None
    return gym.make(ENV_ID, obs_type=obs_type, render_mode="rgb_array",
                    observation_width=observation_size, observation_height=observation_size,
                    max_episode_steps=MAX_STEPS)


def wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def block_pose(u: object) -> np.ndarray:
    """(x, y, angle) of the T block of the unwrapped environment `u`."""
    return np.array([*u.block.position, u.block.angle])


def keypoint_state(u: object) -> np.ndarray:
    """gym-pusht's low-dimensional observation (its obs_type "environment_state_agent_pos", Diffusion Policy's
    low-dimensional Push-T): the T's 8 keypoints (x0, y0, .. x7, y7) and the agent's position, 18 values in pixels.
    Computed from the unwrapped environment `u` as gym-pusht computes it, so the recorder and the closed loop give a
    policy the same numbers whatever observation type the environment renders."""
    keypoints = u.get_keypoints(u._block_shapes).flatten()
    return np.concatenate([keypoints, np.asarray(u.agent.position, float)]).astype(np.float64)


KEYPOINT_NAMES = [f"keypoint{i}_{axis}" for i in range(8) for axis in "xy"] + ["agent_x", "agent_y"]


def pose_error(pose: np.ndarray, goal: np.ndarray) -> float:
    return float(np.linalg.norm(pose[:2] - goal[:2]) + RAD_WEIGHT * abs(wrap(pose[2] - goal[2])))


def _rotation(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


class Physics:
    """A copy of the environment's physics (walls, agent, block, PD control) that can be stepped ahead."""

    def __init__(self, u: object) -> None:
        import pymunk
        from gym_pusht.envs.pusht import PushTEnv

        self.space = pymunk.Space()
        self.space.gravity = 0, 0
        self.space.damping = u.space.damping
        walls = [((5, 506), (5, 5)), ((5, 5), (506, 5)), ((506, 5), (506, 506)), ((5, 506), (506, 506))]
        self.space.add(*[PushTEnv.add_segment(self.space, a, b, 2) for a, b in walls])
        self.agent = PushTEnv.add_circle(self.space, tuple(u.agent.position), AGENT_RADIUS)
        self.agent.velocity = tuple(u.agent.velocity)
        self.block, _ = PushTEnv.add_tee(self.space, tuple(u.block.position), u.block.angle)
        self.block.velocity = tuple(u.block.velocity)
        self.block.angular_velocity = u.block.angular_velocity
        self.k_p, self.k_v, self.dt = u.k_p, u.k_v, u.dt
        self.substeps = int(1 / (u.dt * u.control_hz))

    def step(self, action: np.ndarray) -> None:
        """One control step, as PushTEnv.step does it."""
        for _ in range(self.substeps):
            acc = (self.k_p * (np.asarray(action) - np.asarray(self.agent.position))
                   - self.k_v * np.asarray(self.agent.velocity))
            self.agent.velocity = tuple(np.asarray(self.agent.velocity) + acc * self.dt)
            self.space.step(self.dt)


@dataclass
class Push:
    approach: list[np.ndarray]
    contact: list[np.ndarray]

    @property
    def actions(self) -> list[np.ndarray]:
        return self.approach + self.contact


class PushPlanner:
    """The scripted demonstrator: plan(u) -> the next push's actions, or None when no push lowers the error."""

    def __init__(self, goal: np.ndarray) -> None:
        self.goal = np.asarray(goal, float)

    def outline(self, u: object) -> object:
        from gym_pusht.envs.pusht import pymunk_to_shapely
        from shapely.ops import unary_union

        return unary_union(list(pymunk_to_shapely(u.block, u.block.shapes).geoms)).buffer(0.5)

    def path(self, u: object, a: np.ndarray, b: np.ndarray, step: float = 30.0) -> list[np.ndarray]:
        """Targets from a to b at most `step` apart, round the T when the straight way would touch it."""
        from shapely.geometry import LineString

        body = self.outline(u).buffer(AGENT_RADIUS + 4)
        pts = [np.asarray(a, float)]
        if LineString([a, b]).intersects(body):
            c = np.array(body.centroid.coords[0])
            radius = float(np.max(np.linalg.norm(np.array(body.exterior.coords) - c, axis=1))) + 6
            start, turn = math.atan2(a[1] - c[1], a[0] - c[0]), wrap(math.atan2(b[1] - c[1], b[0] - c[0])
                                                                    - math.atan2(a[1] - c[1], a[0] - c[0]))
            pts += [c + radius * np.array([math.cos(start + turn * k / 6), math.sin(start + turn * k / 6)])
                    for k in range(7)]
        pts.append(np.asarray(b, float))
        out = []
        for p, q in zip(pts[:-1], pts[1:], strict=True):
            n = max(1, int(np.ceil(np.linalg.norm(q - p) / step)))
            out += [p + (q - p) * (i + 1) / n for i in range(n)]
        return [np.clip(o, 20.0, 492.0) for o in out]

    def candidates(self, u: object) -> Iterator[tuple[np.ndarray, list[np.ndarray]]]:
        """(pre-contact point, the agent's targets while in contact) for each contact point round the outline."""
        from shapely.geometry import Point

        poly = self.outline(u)
        ring = poly.exterior
        com = np.array(u.block.local_to_world(u.block.center_of_gravity))
        for s in np.linspace(0, ring.length, CONTACT_POINTS, endpoint=False):
            p = np.array(ring.interpolate(s).coords[0])
            tangent = np.array(ring.interpolate(s + 1).coords[0]) - p
            normal = np.array([tangent[1], -tangent[0]]) / (np.linalg.norm(tangent) + 1e-9)
            if poly.contains(Point(*(p + 3 * normal))):
                normal = -normal  # outward
            pre = p + (AGENT_RADIUS + 6) * normal
            for length in STRAIGHT_PUSHES:
                yield pre, self.path(u, pre, p - length * normal, step=10.0)
            arm = p + (AGENT_RADIUS - 2) * normal - com
            for turn in ARC_TURNS:
                yield pre, [pre] + [com + _rotation(turn * k / 8) @ arm for k in range(1, 9)]

    def plan(self, u: object) -> Push | None:
        now = pose_error(block_pose(u), self.goal)
        agent = np.array(u.agent.position)
        best, best_gain = None, 0.0
        for pre, contact in self.candidates(u):
            approach = self.path(u, agent, pre)
            if len(approach) > MAX_APPROACH:
                continue
            sim = Physics(u)
            sim.agent.position, sim.agent.velocity = tuple(pre), (0.0, 0.0)
            for a in contact:
                sim.step(a)
            gain = (now - pose_error(block_pose(sim), self.goal)) / (len(approach) + len(contact) + 5)
            if gain > best_gain:
                best, best_gain = Push(approach, contact), gain
        return best


TASK = "push the T"
KEYPOINT_TOPIC = "/pusht/keypoint_state"  # the low-dimensional state (pipelines/pusht/topics_state.yaml)
CONTROL_HZ = 10.0
WORKSPACE_M = 0.512  # the 512-pixel workspace as metres in the bag's base frame (1 px = 1 mm)


def camera_model(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(K, T_base_camera) of the top-down view gym-pusht renders: an optical frame whose x, y are the workspace's
    x, y, 1 m from the plane, so that the pinhole projection of a point on the plane is the rendered pixel."""
    f = size / WORKSPACE_M
    c = (size - 1) / 2.0
    K = np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, 3] = [WORKSPACE_M / 2, WORKSPACE_M / 2, -1.0]
    return K, T


def record(seed: int, size: int = 96) -> object:
    """One demonstration from the seeded initial condition as sensor streams (adlpipe.sim.episode.Streams): the
    rendered image, the agent as end effector and as the state (x, y in pixels), the keypoint state (keypoint_state,
    the low-dimensional observation), the action (the target position), the T block's pose as an object, all at the
    control rate."""
    from ..sim.episode import Streams
    from ..sim.world import SceneSpec

    K, T = camera_model(size)
    st = Streams(TASK, SceneSpec(task=TASK, poses={}), size, size, K, T, joint_names=["agent_x", "agent_y"],
                 state_names=["agent_x", "agent_y"], action_names=["target_x", "target_y"])
    keypoints = st.extra_states.setdefault(KEYPOINT_TOPIC, (KEYPOINT_NAMES, []))[1]
    env = make_env(size)
    info: dict = {}
    try:
        for i, step in enumerate(demonstrate(env, seed)):
            t, info = i / CONTROL_HZ, step.info
            agent = np.asarray(step.obs["agent_pos"], float)
            x, y, angle = step.block
            st.camera.append((t, step.obs["pixels"], None))
            st.joints.append((t, agent, np.zeros(2)))
            st.ee.append((t, np.array([*agent / 1000.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0])))
            st.states.append((t, agent))
            keypoints.append((t, step.keypoints))
            st.actions.append((t, np.asarray(step.action, float)))
            st.objects.append((t, {"tee": (np.array([x / 1000.0, y / 1000.0, 0.0]),
                                           np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]))}))
    finally:
        env.close()
    st.success = bool(info.get("is_success", False))
    st.duration = len(st.camera) / CONTROL_HZ
    return st


@dataclass
class Step:
    obs: dict  # the observation the action was chosen on
    block: np.ndarray  # the block's pose then (x, y, angle)
    keypoints: np.ndarray  # keypoint_state then
    action: np.ndarray
    info: dict  # after the action: coverage, is_success


def demonstrate(env: object, seed: int, max_steps: int = MAX_STEPS) -> Iterator[Step]:
    """Run the demonstrator from the seeded initial condition, one control step at a time, until success, the step
    limit, or no push helps."""
    obs, info = env.reset(seed=seed)
    u = env.unwrapped
    planner = PushPlanner(u.goal_pose)
    steps = 0
    while steps < max_steps:
        push = planner.plan(u)
        if push is None:
            return
        for action in push.actions:
            action = np.asarray(action, np.float32)
            block, keypoints = block_pose(u), keypoint_state(u)
            nxt, _reward, done, _trunc, info = env.step(action)
            yield Step(obs, block, keypoints, action, info)
            obs, steps = nxt, steps + 1
            if done or steps >= max_steps:
                return


REFERENCES = ("demonstrator", "no action")  # the scale a policy's score sits on


def run_policy(plan: object, seed: int, execute: int, n_obs: int, size: int = 96,
               max_steps: int = MAX_STEPS, state_only: bool = False) -> dict:
    """The seed's closed loop on Push-T from initial condition `seed`: plan(frames, states) -> actions (Tp, 2) from
    the last n_obs observations (the first repeated before the start), execute the first `execute`, re-plan.
    states: the agent's position per frame (the image policies' state), or for a `state_only` policy the keypoint
    state (keypoint_state, the low-dimensional setting). Returns score (the highest coverage reached), success
    (coverage above 0.95 at some step) and plans made."""
    # A state-only policy gets gym-pusht's own low-dimensional observation (no frame is rendered for it), the same
    # 18 values the recorder stores (keypoint_state; tests/test_pusht.py checks they agree).
    env = make_env(size, "environment_state_agent_pos" if state_only else "pixels_agent_pos")

    def observe(obs: dict) -> tuple[np.ndarray | None, np.ndarray]:
        if state_only:
            return None, np.concatenate([obs["environment_state"], obs["agent_pos"]]).astype(np.float64)
        return obs["pixels"], np.asarray(obs["agent_pos"], float)

    try:
        obs, _info = env.reset(seed=seed)
        frames = [observe(obs)] * n_obs
        best, plans, steps = 0.0, 0, 0
        while steps < max_steps:
            actions = np.asarray(plan([p for p, _ in frames], np.stack([s for _, s in frames])))
            plans += 1
            for a in actions[:execute]:
                obs, _r, done, _trunc, info = env.step(np.clip(a, 0, 512).astype(np.float32))
                frames = frames[1:] + [observe(obs)]
                best, steps = max(best, float(info["coverage"])), steps + 1
                if done:
                    return {"score": best, "success": True, "plans": plans}
                if steps >= max_steps:
                    break
        return {"score": best, "success": False, "plans": plans}
    finally:
        env.close()


def reference(kind: str, seed: int) -> dict:
    """The demonstrator, or the agent holding still (the coverage an episode starts with), from one initial
    condition, scored as run_policy scores a policy."""
    env = make_env()
    try:
        if kind == "demonstrator":
            steps = list(demonstrate(env, seed))
            return {"score": max(s.info["coverage"] for s in steps), "success": bool(steps[-1].info["is_success"])}
        env.reset(seed=seed)
        _obs, _r, done, _t, info = env.step(np.asarray(env.unwrapped.agent.position, np.float32))
        return {"score": float(info["coverage"]), "success": bool(done)}
    finally:
        env.close()
