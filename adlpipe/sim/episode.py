"""Runs one episode in the ADL world: the demonstrator (recording sensor streams) or a replayed trajectory."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from ..geometry.transforms import project
from .controller import ArmController, execute_path, release_and_settle, track_path
from .person import mover
from .tasks import TASKS, Scene, SuccessMonitor, Task
from .world import ARM_JOINTS, FINGER_JOINTS, HOME_TCP, SceneSpec, build_mjcf

DEPTH_RANGE_M = 5.0
# The commanded setpoint, recorded as the bags' action stream: what the arm is told, which its measured tcp trails
# by 75-85 ms (Diffusion Policy and LeRobot learn the command, not the lagging measurement).
COMMAND_NAMES = ["tcp_x", "tcp_y", "tcp_z", "gripper"]
SPEED = 0.30  # m/s of the demonstrator's tcp between keypoints
MIN_SEGMENT_S = 0.25


def make_scene(spec: SceneSpec, width: int = 224, height: int = 224,
               markers: list | None = None) -> tuple[ArmController, Scene]:
    model = mujoco.MjModel.from_xml_string(build_mjcf(spec, width, height, markers))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    ctrl = ArmController(model, data)
    ctrl.reset_home()
    if spec.person:
        ctrl.person = mover(model, spec)
    return ctrl, Scene(model, data, spec)


def _min_jerk(s: float) -> float:
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def keypoint_path(start: np.ndarray, keypoints: list[tuple[np.ndarray, float]],
                  moving: Callable[[float], list[tuple[np.ndarray, float]]] | None = None) -> tuple[Callable, float]:
    """A smooth path through keypoints (min-jerk per segment, dwelling where asked) and its duration. moving(t):
    the keypoints where they are at time t (a person who moves), tracked along the same timing."""
    knots = [(0.0, -1, -1)]  # (end time, from keypoint, to keypoint); -1: the start
    t = 0.0
    prev, i_prev = start, -1
    for i, (p, dwell) in enumerate(keypoints):
        seg = max(MIN_SEGMENT_S, float(np.linalg.norm(p - prev)) / SPEED)
        knots.append((t + seg, i_prev, i))
        t += seg
        if dwell > 0:
            knots.append((t + dwell, i, i))
            t += dwell
        prev, i_prev = p, i
    times = np.array([k[0] for k in knots])

    def fn(tq: float) -> np.ndarray:
        kp = moving(tq) if moving is not None else keypoints
        i = int(np.searchsorted(times, tq, side="left"))
        if i == 0:
            return start.copy()
        if i >= len(knots):
            return kp[knots[-1][2]][0].copy()
        t_end, ia, ib = knots[i]
        a, b = (start if ia < 0 else kp[ia][0]), kp[ib][0]
        t_beg = times[i - 1]
        s = _min_jerk(np.clip((tq - t_beg) / max(t_end - t_beg, 1e-9), 0.0, 1.0))
        return a + s * (b - a)

    return fn, t


def demonstrator_path(task: Task, scene: Scene) -> tuple[Callable, float]:
    """The scripted demonstrator's tcp path from home through the task's keypoints; with a person who moves, the
    keypoints follow the person: they are planned at every instant in a copy of the scene where only the person
    has moved (objects where they started), so a keypoint on an object stays put and one on the mouth moves."""
    keypoints = task.tcp_keypoints(scene)
    if not scene.spec.person:
        return keypoint_path(HOME_TCP.copy(), keypoints)
    probe = mujoco.MjData(scene.m)
    probe.qpos[:], probe.mocap_pos[:], probe.mocap_quat[:] = scene.d.qpos, scene.d.mocap_pos, scene.d.mocap_quat
    move, probe_scene = mover(scene.m, scene.spec), Scene(scene.m, probe, scene.spec)

    def at(t: float) -> list[tuple[np.ndarray, float]]:
        move(probe, t)
        mujoco.mj_kinematics(scene.m, probe)
        return task.tcp_keypoints(probe_scene)

    return keypoint_path(HOME_TCP.copy(), keypoints, at)


def waypoint_path(waypoints: np.ndarray, duration: float) -> Callable:
    """Linear interpolation of N waypoints spread evenly over `duration` (how a predicted trajectory runs)."""
    ts = np.linspace(0.0, duration, len(waypoints))

    def fn(tq: float) -> np.ndarray:
        return np.array([np.interp(tq, ts, waypoints[:, k]) for k in range(3)])

    return fn


class RgbdCamera:
    """Renders RGB and metric depth of the fixed `rgbd` camera in one pass (read from the same frame buffer)."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int) -> None:
        self.m, self.w, self.h = model, width, height
        self.gl = mujoco.GLContext(width, height)
        self.gl.make_current()
        self.ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.ctx)
        self.scene = mujoco.MjvScene(model, maxgeom=2000)
        self.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0  # shadows cost 60% of a software-rendered frame
        self.cam = mujoco.MjvCamera()
        self.cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self.cam.fixedcamid = model.camera("rgbd").id
        self.opt, self.pert = mujoco.MjvOption(), mujoco.MjvPerturb()
        self.rect = mujoco.MjrRect(0, 0, width, height)
        extent = model.stat.extent
        self.near, self.far = model.vis.map.znear * extent, model.vis.map.zfar * extent

    def render(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        self.gl.make_current()
        mujoco.mjv_updateScene(self.m, data, self.opt, self.pert, self.cam, mujoco.mjtCatBit.mjCAT_ALL, self.scene)
        mujoco.mjr_render(self.rect, self.scene, self.ctx)
        rgb = np.empty((self.h, self.w, 3), np.uint8)
        z = np.empty((self.h, self.w), np.float32)
        mujoco.mjr_readPixels(rgb, z, self.rect, self.ctx)
        depth = self.near / (1 - z * (1 - self.near / self.far))  # z-buffer -> metres along the optical axis
        return np.flipud(rgb).copy(), np.flipud(depth).astype(np.float32)

    def close(self) -> None:
        self.ctx.free()
        self.gl.free()


@dataclass
class Streams:
    """The sensor streams of one episode, at their own rates, stamped in seconds from the episode start."""

    task: str
    spec: SceneSpec
    width: int
    height: int
    K: np.ndarray
    T_base_camera: np.ndarray  # camera optical frame pose in base_link (4x4)
    camera: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)  # (t, rgb, depth m)
    joints: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)  # (t, pos, vel)
    ee: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)  # (t, pos, quat wxyz)
    objects: list[tuple[float, dict[str, tuple[np.ndarray, np.ndarray]]]] = field(default_factory=list)
    affordance: np.ndarray | None = None
    joint_names: list[str] = field(default_factory=lambda: ARM_JOINTS + FINGER_JOINTS)
    success: bool = False
    duration: float = 0.0
    attempts: int = 1  # scenes drawn until the demonstrator succeeded (seeded_demo)
    # A policy's own state and action streams (joint-space and Push-T data): (t, values), named per dimension
    states: list[tuple[float, np.ndarray]] = field(default_factory=list)
    actions: list[tuple[float, np.ndarray]] = field(default_factory=list)
    state_names: list[str] = field(default_factory=list)
    action_names: list[str] = field(default_factory=list)
    # Further JointState streams of the same kind: topic -> (names, [(t, values)]) (Push-T's keypoint state)
    extra_states: dict[str, tuple[list[str], list[tuple[float, np.ndarray]]]] = field(default_factory=dict)
    # The demonstrator's undisturbed path (t, tcp) beside a disturbed command (record --recoveries; else empty)
    reference: list[tuple[float, np.ndarray]] = field(default_factory=list)
    disturbances: int = 0  # how many disturbances the demonstrator recovered from
    # A policy's plans in a closed-loop trial (t observed, waypoints (Tp, 3) in the base frame, their times after t)
    plans: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)
    # A labelled rollout's (adlpipe.sim.dagger): the expert's plan at each re-plan, in the plans' form, and who
    # drove from each re-plan on (t, True: the operator)
    expert_plans: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)
    interventions: list[tuple[float, bool]] = field(default_factory=list)
    expert_phase: list[tuple[float, float]] = field(default_factory=list)  # (t, the expert's phase s on the path)


def camera_intrinsics(model: mujoco.MjModel, width: int, height: int) -> np.ndarray:
    fovy = np.deg2rad(model.cam_fovy[model.camera("rgbd").id])
    f = 0.5 * height / np.tan(fovy / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


def camera_pose(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """Pose of the ROS optical frame (x right, y down, z forward) in base_link."""
    cid = model.camera("rgbd").id
    R_mj = data.cam_xmat[cid].reshape(3, 3)  # MuJoCo camera: x right, y up, looks along -z
    T = np.eye(4)
    T[:3, :3] = R_mj @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = data.cam_xpos[cid]
    return T


def affordance_map(points_uv: np.ndarray, width: int, height: int, sigma: float) -> np.ndarray:
    """2D Gaussian blobs (peak 1) on the pixels the action touches."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    out = np.zeros((height, width), np.float32)
    for u, v in points_uv:
        out = np.maximum(out, np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2)))
    return out


def in_mode(spec: SceneSpec, mode: float) -> SceneSpec:
    return replace(spec, extras={**spec.extras, "mode": float(mode)})


def touched_points(task: Task, scene: Scene) -> np.ndarray:
    """The 3D points the action may touch, over every mode of the task (the affordance map must not tell the mode):
    for tool tasks the parts of the manikin (or bowl) the tool works on; for object tasks where the gripper or broom
    meets the object and where the object is put (the dwell keypoints of the plan)."""
    pts: list[np.ndarray] = [fn(scene) for fn, _ in task.touches]
    if task.stroke:
        pts += [task.stroke.a(scene), task.stroke.b(scene)]
    if task.dwell:
        pts.append(task.dwell.point(scene))
    if not pts:
        for mode in task.modes:
            plan = task.plan(Scene(scene.m, scene.d, in_mode(scene.spec, mode)))
            pts += [p for p, dwell in plan if dwell > 0]
    return np.unique(np.round(np.array(pts), 6), axis=0)


def demo_succeeds(spec: SceneSpec) -> bool:
    """Run the demonstrator on a scene without recording anything: does its success predicate hold?"""
    task = TASKS[spec.task]
    ctrl, scene = make_scene(spec, 16, 16)
    path, duration = demonstrator_path(task, scene)
    monitor = SuccessMonitor(task, scene)
    execute_path(ctrl, path, duration, on_step=lambda _t: monitor.step())
    return monitor.success()


def sample_balanced_scene(task_name: str, rng: np.random.Generator, max_attempts: int = 8,
                          person: dict[str, float] | None = None) -> SceneSpec:
    """A scene in which the demonstrator succeeds in every mode; its mode is then drawn at random.

    Re-drawing a scene only when the chosen mode fails would make the accepted mode depend on the scene (the side
    that fails more often near an edge would be rarer there), which a regressor could learn: the modes would no
    longer be ambiguous. Accepting scenes where all modes work keeps P(mode | scene) = 1/2.
    """
    task = TASKS[task_name]
    spec = replace(task.sample(rng), person=person or {})
    for _ in range(max_attempts):
        if all(demo_succeeds(in_mode(spec, m)) for m in task.modes):
            break
        spec = replace(task.sample(rng), person=person or {})
    return in_mode(spec, float(rng.choice(task.modes)))


MAX_ATTEMPTS = 8  # a demonstration whose success predicate still fails is re-sampled, as an operator would redo it
# Scene indices from here on are never recorded (record caps --episodes at 100,000): replay's fresh scenes
FRESH_INDEX0 = 1_000_000


def seeded_demo(task_name: str, seed: int, index: int, size: int, camera_hz: float,
                moving_person: bool = False, recoveries: bool = False) -> Streams:
    """The recorder's demonstration `index` of a task: its scene drawn from (seed, task, index, attempt), redrawn
    (up to MAX_ATTEMPTS) while the demonstrator fails. The scene depends on these integers alone, never on the
    host; replay's fresh scenes are the same draw at indices from FRESH_INDEX0. moving_person: the person's motion
    is drawn from a stream of its own, so the scene is the still person's scene with the person moving in it
    (unless the demonstrator fails with the motion and the scene is redrawn). recoveries: the demonstrator is
    disturbed and recovers (disturbances drawn from a stream of their own) in the scene the undisturbed recorder
    keeps; where it fails so, the scene's undisturbed demonstration is recorded instead."""
    from .person import draw_motion
    from .tasks import TASK_NAMES

    ti = TASK_NAMES.index(task_name)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, ti, index, attempt])
        person = draw_motion(np.random.default_rng([seed, ti, index, attempt, 1])) if moving_person else None
        spec = sample_balanced_scene(task_name, rng, person=person)
        if recoveries and demo_succeeds(spec):
            disturb = np.random.default_rng([seed, ti, index, attempt, 2])
            st = record_demo(task_name, rng, size, size, camera_hz=camera_hz, spec=spec, disturb=disturb)
            if st.success:
                break
        st = record_demo(task_name, rng, size, size, camera_hz=camera_hz, spec=spec)
        if st.success:
            break
    st.attempts = attempt + 1
    return st


def record_demo(task_name: str, rng: np.random.Generator, width: int = 224, height: int = 224,
                camera_hz: float = 15.0, joint_hz: float = 100.0, tf_hz: float = 50.0,
                spec: SceneSpec | None = None, disturb: np.random.Generator | None = None) -> Streams:
    """Run the scripted demonstrator in a scene (sampled from rng unless given) and record every stream
    (renders RGB-D at camera_hz). disturb: the demonstrator is disturbed (disturbances drawn from it) and recovers,
    its undisturbed path recorded as the reference."""
    from .disturbances import disturbed_path, draw_disturbances

    task = TASKS[task_name]
    spec = spec or task.sample(rng)
    ctrl, scene = make_scene(spec, width, height)
    m, d = ctrl.m, ctrl.d
    reference, duration = demonstrator_path(task, scene)
    events = draw_disturbances(disturb, duration) if disturb is not None else []
    path = disturbed_path(reference, events) if events else reference
    K = camera_intrinsics(m, width, height)
    T_bc = camera_pose(m, d)
    st = Streams(task_name, spec, width, height, K, T_bc, duration=duration, action_names=list(COMMAND_NAMES),
                 disturbances=len(events))
    tip_pts = touched_points(task, scene)
    st.affordance = affordance_map(project(tip_pts, K, T_bc), width, height, sigma=0.03 * width)
    camera = RgbdCamera(m, width, height)
    monitor = SuccessMonitor(task, scene)
    record = _StreamRecorder(ctrl, st, joint_hz, tf_hz,
                             reference=(lambda t: reference(min(t, duration))) if disturb is not None else None)
    next_cam = [0.0]

    def on_step(t: float) -> None:
        monitor.step()
        record.step(t)
        if t + 1e-9 >= next_cam[0]:
            rgb, depth = camera.render(d)
            depth[depth > DEPTH_RANGE_M] = np.nan  # no return beyond the sensor's range (REP 118)
            record.frame(t, rgb, depth)
            next_cam[0] += 1.0 / camera_hz

    on_step(0.0)
    execute_path(ctrl, path, duration, on_step=on_step)
    camera.close()
    st.success = monitor.success()
    return st


@dataclass
class OpenLoopRun:
    """What an open-loop replay did: success, each part of the predicate, the peak force on the manikin."""

    success: bool
    checks: dict[str, bool]  # each part of the task's predicate (force, touches, stroke, dwell, placed)
    peak_force_n: float  # the largest contact normal force on the manikin at any step
    tcp_path: np.ndarray  # (S, 3) measured tcp after every physics step


def replay_trajectory(spec: SceneSpec, waypoints: np.ndarray, duration: float) -> OpenLoopRun:
    """Execute a tcp trajectory open loop in the scene rebuilt from `spec`."""
    task = TASKS[spec.task]
    ctrl, scene = make_scene(spec, 64, 64)
    monitor = SuccessMonitor(task, scene)
    path: list[np.ndarray] = []

    def on_step(t: float) -> None:
        monitor.step()
        path.append(ctrl.tcp_pos)

    # The arm starts at home, as in the demonstrations, whose first waypoint is the home pose.
    fn = waypoint_path(np.asarray(waypoints, float), duration)
    execute_path(ctrl, fn, duration, on_step=on_step)
    return OpenLoopRun(monitor.success(), monitor.checks(), monitor.max_force, np.array(path))


Frame = tuple[np.ndarray, np.ndarray, np.ndarray, float]  # rgb, depth (m), measured tcp, gripper joint


@dataclass
class ClosedLoopRun:
    """What a closed-loop rollout did: success, plans made, and where it ended against its goal."""

    success: bool
    plans: int
    checks: dict[str, bool]  # each part of the task's predicate (force, touches, stroke, dwell, placed)
    tcp_path: np.ndarray  # (S, 3) measured tcp after every physics step
    peak_force_n: float  # the largest contact normal force on the manikin at any step
    command_path: np.ndarray  # (P, 3) every executed waypoint (the commands), in order


def replay_closed_loop(spec: SceneSpec, plan: Callable[[list[Frame], float, np.ndarray], np.ndarray],
                       duration: float, rate_hz: float, execute: int, n_obs: int, image_size: int,
                       camera_hz: float, anchor: str = "command", ensemble: float | None = None,
                       latency_s: float | None = 0.0, execution: str = "sync",
                       streams: Streams | None = None, expert: object | None = None) -> ClosedLoopRun:
    """The seed's closed loop: from the last `n_obs` camera frames (rgb, depth, tcp position and gripper joint when
    rendered) the policy plans the next waypoints at rate_hz (plan(frames, progress, anchor) -> (Tp, 3) waypoints in
    the base frame, the k-th for k / rate_hz s after the observation; progress: the seconds the arm has spent
    moving along plans, the clock less any wait for a plan, which the oracle's plans follow); the arm executes the
    first `execute` of them, and the policy re-plans from the frames of the scene as it is then, until the
    demonstration's duration has passed. The camera runs at camera_hz throughout, as when recording.

    anchor "command": plans start from the last commanded waypoint (where the previous plan left the arm's
    command, the home pose at first), the policies trained on the command stream; "measured": from the measured tcp
    of the newest frame, which trails the command by ~80 ms (policies trained with --target ee).

    ensemble (ACT's temporal ensembling, Zhao et al. 2023, with its weight m): re-plan at every waypoint (execute
    1) and execute the weighted mean of every plan's waypoint for that step, in the base frame, weights exp(-m i)
    from the oldest plan (i = 0) on.

    latency_s: the world goes on for this long while a plan is computed (None: as long as plan() took on the wall
    clock, a server's round trip included). execution "sync": the arm holds its last command meanwhile; "async":
    it goes on with the previous plan's waypoints after the executed ones (holding the last once they run out), and
    the new plan is joined at the waypoint for the time it arrives (LeRobot's asynchronous inference). The first
    plan is always waited for. streams: record the rollout into it (camera, joints, tcp, command, objects, plans),
    expert (a labelled rollout's, adlpipe.sim.dagger.Expert): the scene's demonstrated path and the expert's phase
    on it are recorded beside the command."""
    if ensemble is not None and execute != 1:
        raise ValueError("temporal ensembling re-plans at every waypoint: execute must be 1")
    if execution not in ("sync", "async"):
        raise ValueError(f"execution {execution!r}: sync or async")
    task = TASKS[spec.task]
    ctrl, scene = make_scene(spec, image_size, image_size)
    camera = RgbdCamera(ctrl.m, image_size, image_size)
    monitor = SuccessMonitor(task, scene)
    frames: deque[Frame] = deque(maxlen=n_obs)
    next_frame = [0.0]
    tcp_path: list[np.ndarray] = []
    commands: list[np.ndarray] = []
    record = _StreamRecorder(ctrl, streams, expert=expert) if streams is not None else None

    def on_step(t: float) -> None:
        monitor.step()
        tcp_path.append(ctrl.tcp_pos)
        if t + 1e-9 >= next_frame[0]:
            rgb, depth = camera.render(ctrl.d)
            depth[depth > DEPTH_RANGE_M] = np.nan
            frames.append((rgb, depth, ctrl.tcp_pos, ctrl.gripper_pos))
            next_frame[0] += 1.0 / camera_hz
            if record is not None:
                record.frame(t, rgb, depth)
        if record is not None:
            record.step(t)

    def move(waypoints: np.ndarray, start: np.ndarray, t0: float) -> None:
        seg = np.vstack([start, waypoints])
        track_path(ctrl, waypoint_path(seg, len(waypoints) * dt), len(waypoints) * dt, on_step, t_offset=t0)

    ctrl.d.ctrl[len(ARM_JOINTS):] = 0.04
    plans, elapsed, dt = 0, 0.0, 1.0 / rate_hz
    waited = 0.0  # seconds the arm held still waiting for a plan
    last = ctrl.tcp_pos
    pending: dict[int, list[np.ndarray]] = {}  # ensembling: step -> every plan's waypoint for it, oldest first
    ahead = np.zeros((0, 3))  # async: the previous plan's waypoints after the executed ones
    try:
        on_step(0.0)
        while elapsed < duration - 1e-9:
            stack = [frames[0]] * (n_obs - len(frames)) + list(frames)  # padded at the start, as in training
            base = last if anchor == "command" else stack[-1][2]
            t_wall = time.perf_counter()
            planned = np.asarray(plan(stack, elapsed - waited, np.asarray(base, float)), float)
            wait = time.perf_counter() - t_wall if latency_s is None else latency_s
            if record is not None:
                record.plan(elapsed, planned, dt)
            skip = 0
            if wait > 0:
                if execution == "async" and plans > 0:  # go on with the previous plan while this one computes
                    skip = int(np.ceil(wait / dt - 1e-9))
                    go_on = np.vstack([ahead, np.repeat(ahead[-1:] if len(ahead) else last[None], skip, 0)])[:skip]
                    move(go_on, last, elapsed)
                    commands += list(go_on)
                    last = go_on[-1]
                    elapsed += skip * dt
                else:  # hold the last command until the plan arrives (to the physics step)
                    wait = max(1, round(wait / ctrl.m.opt.timestep)) * ctrl.m.opt.timestep
                    track_path(ctrl, _constant(last), wait, on_step, t_offset=elapsed)
                    elapsed += wait
                    waited += wait
                if elapsed >= duration - 1e-9:
                    break
            if ensemble is None:
                waypoints = planned[skip:skip + execute]
                if not len(waypoints):  # the whole plan was for times already gone: hold and plan again
                    waypoints = last[None]
                ahead = planned[skip + execute:]
            else:
                for k, p in enumerate(planned):
                    pending.setdefault(plans + k, []).append(p)
                votes = np.array(pending.pop(plans))
                w = np.exp(-ensemble * np.arange(len(votes)))
                waypoints = (w[:, None] * votes).sum(0, keepdims=True) / w.sum()
            commands += list(waypoints)
            plans += 1
            move(waypoints, last, elapsed)
            elapsed += len(waypoints) * dt
            last = waypoints[-1]
        release_and_settle(ctrl, last, on_step=lambda _t: monitor.step())
    finally:
        camera.close()
    if record is not None:
        record.finish(duration=elapsed)
    return ClosedLoopRun(monitor.success(), plans, monitor.checks(), np.array(tcp_path), monitor.max_force,
                         np.array(commands).reshape(-1, 3))


def _constant(p: np.ndarray) -> Callable[[float], np.ndarray]:
    """A path that stays at p (the arm holding its command)."""
    held = np.array(p, float)
    return lambda _t: held


class _StreamRecorder:
    """Fills a Streams at the recorder's rates (joints and command at joint_hz, tcp at tf_hz, camera and objects at
    each rendered frame): the demonstrator's recording and a closed-loop trial's, so both are the same kind of bag.
    reference: the demonstrator's undisturbed path at t, kept beside the command (record --recoveries); expert (a
    labelled rollout's): its demonstrated path as the reference, and its phase on it tracked from the command."""

    def __init__(self, ctrl: object, st: Streams, joint_hz: float = 100.0, tf_hz: float = 50.0,
                 reference: Callable[[float], np.ndarray] | None = None, expert: object | None = None) -> None:
        m = ctrl.m  # type: ignore[attr-defined]
        self.ctrl, self.st, self.joint_dt, self.tf_dt = ctrl, st, 1.0 / joint_hz, 1.0 / tf_hz
        self.reference = reference if expert is None else expert.reference  # type: ignore[attr-defined]
        self.expert = expert
        self.qadr = [m.jnt_qposadr[m.joint(j).id] for j in st.joint_names]
        self.vadr = [m.jnt_dofadr[m.joint(j).id] for j in st.joint_names]
        self.objects = [n for n in st.spec.poses if n != "manikin"]
        self.next = {"joint": 0.0, "tf": 0.0}
        st.K = camera_intrinsics(m, st.width, st.height)
        st.T_base_camera = camera_pose(m, ctrl.d)  # type: ignore[attr-defined]
        st.action_names = list(COMMAND_NAMES)

    def frame(self, t: float, rgb: np.ndarray, depth: np.ndarray) -> None:
        m, d = self.ctrl.m, self.ctrl.d  # type: ignore[attr-defined]
        self.st.camera.append((t, rgb, depth))
        self.st.objects.append((t, {n: (d.xpos[m.body(n).id].copy(), d.xquat[m.body(n).id].copy())
                                    for n in self.objects}))

    def step(self, t: float) -> None:
        c, d, st = self.ctrl, self.ctrl.d, self.st  # type: ignore[attr-defined]
        if t + 1e-9 >= self.next["joint"]:
            st.joints.append((t, d.qpos[self.qadr].copy(), d.qvel[self.vadr].copy()))
            st.actions.append((t, np.append(c.target, c.gripper_command)))  # type: ignore[attr-defined]
            if self.reference is not None:
                st.reference.append((t, self.reference(t)))
            if self.expert is not None:  # where on the demonstrated path the command is (never back)
                st.expert_phase.append((t, self.expert.track(c.target)))  # type: ignore[attr-defined]
            self.next["joint"] += self.joint_dt
        if t + 1e-9 >= self.next["tf"]:
            q = np.zeros(4)
            mujoco.mju_mat2Quat(q, d.site_xmat[c.tcp])  # type: ignore[attr-defined]
            st.ee.append((t, c.tcp_pos, q))  # type: ignore[attr-defined]
            self.next["tf"] += self.tf_dt

    def plan(self, t: float, waypoints: np.ndarray, dt: float) -> None:
        self.st.plans.append((t, waypoints.copy(), np.arange(1, len(waypoints) + 1) * dt))

    def finish(self, duration: float) -> None:
        self.st.duration = duration


def spec_from_objects(task: str, names: list[str], poses: np.ndarray,
                      person: dict[str, float] | None = None) -> SceneSpec:
    """Rebuild a scene specification from the initial object poses stored with an episode (x y z qw qx qy qz), with
    the person's motion where the person moves (a fresh scene's; recordings do not store it)."""
    out = {}
    for name, p in zip(names, poses, strict=True):
        qw, qz = p[3], p[6]
        out[name] = (float(p[0]), float(p[1]), float(p[2]), float(2 * np.arctan2(qz, qw)))
    return SceneSpec(task=task, poses=out, tool=TASKS[task].tool, person=dict(person or {}))
