"""The scenes a policy is replayed in: the recorded test split's, or fresh scenes drawn by the recorder's own
scene generator at indices no recording uses, seen as a recording would have shown them.

A fresh scene is what `record` would have written as demonstration FRESH_INDEX0 + i of its task (the same seeded
draw, the same demonstrator that must succeed, the first frame rendered by the same camera at the recordings' size)
and what `ingest` would have kept of it (the image resized with the same filters, the trajectory as 32 waypoints of
the measured tcp over the same time span, the objects' initial poses), without writing a bag: its first frame goes
to the policy exactly as a test episode's does. Scene i of a task depends on (seed, task, index) alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..dataset.schema import Episode
from ..geometry.camera import PINHOLE, project
from ..geometry.transforms import resample, scale_intrinsics

STILL_DEMO = "demo-still-person"  # replay's row of the still person's demonstration run with the person moving


@dataclass
class ReplayScene:
    """What replay needs of a scene: the first frame's inputs, the initial poses and the demonstration."""

    name: str
    task: str
    rgb: np.ndarray  # (S, S, 3) uint8 at the dataset's stored size
    affordance: np.ndarray  # (S, S) float32
    depth: np.ndarray | None  # (S, S) metres, NaN: no return
    object_names: list[str]
    objects: np.ndarray  # (n, 7) x y z qw qx qy qz in the base frame
    duration_s: float
    traj3d: np.ndarray  # (N, 3) the demonstration's waypoints
    traj2d: np.ndarray  # (N, 2) the same in the stored image's pixels
    # What closed loop needs beyond the first frame: the camera (stored-size intrinsics, pose, rate) it renders live
    # at, and the demonstration's measured and commanded tcp series (the oracle's plans, the path it is compared to)
    K: np.ndarray
    T_base_camera: np.ndarray
    camera_hz: float
    ee_t: np.ndarray  # (M,) s
    ee_pos: np.ndarray  # (M, 3)
    command_t: np.ndarray | None  # (C,) s; None: the recording has no command stream
    command: np.ndarray | None  # (C, 3)
    person: dict[str, float] = field(default_factory=dict)  # the person's motion (adlpipe.sim.person); {}: still
    # With the person moving: the still person's demonstration of the same scene (N, 5: u, v, x, y, z), what a
    # perfect first-frame plan executes (the first frame is the same); None where the scenes differ or all is still
    still_traj: np.ndarray | None = None

    def series(self, target: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps, positions) of the demonstration's commanded ("command") or measured ("ee") tcp."""
        if target == "ee":
            return self.ee_t, self.ee_pos
        if self.command is None:
            raise ValueError(f"{self.name}: no command stream")
        return self.command_t, self.command


def from_episode(ep: Episode, camera_hz: float = 15.0,
                 command: tuple[np.ndarray, np.ndarray] | None = None) -> ReplayScene:
    """A recorded test episode as a replay scene (its camera rate and command series read beside it)."""
    ct, cmd = command if command is not None else (None, None)
    return ReplayScene(ep.name, ep.task, ep.rgb, ep.affordance, ep.depth, ep.object_names, ep.objects, ep.duration_s,
                       ep.traj3d, ep.traj2d, ep.K, ep.T_base_camera, camera_hz, ep.ee_t, ep.ee_pos, ct, cmd)


def fresh_name(task: str, index: int) -> str:
    return f"fresh/{task.replace(' ', '_')}/{index}"


def fresh_scene(task: str, i: int, seed: int, camera_size: int, size: int, n_waypoints: int,
                camera_hz: float = 15.0, moving_person: bool = False) -> ReplayScene:
    """Fresh scene i of a task (recording index FRESH_INDEX0 + i), at the stored image size `size` of a dataset
    recorded at `camera_size` px and `camera_hz` (the rate closed loop renders at)."""
    from ..sim.episode import FRESH_INDEX0

    return recorded_scene(task, FRESH_INDEX0 + i, seed, camera_size, size, n_waypoints, camera_hz, moving_person)


def recorded_scene(task: str, index: int, seed: int, camera_size: int, size: int, n_waypoints: int,
                   camera_hz: float = 15.0, moving_person: bool = False) -> ReplayScene:
    """The scene of the recorder's demonstration `index` of a task, as ingest would have stored its first frame.
    Only the first frame is rendered (the camera is asked for one frame per 1,000 s)."""
    from ..sim.episode import DEPTH_RANGE_M, seeded_demo

    st = seeded_demo(task, seed, index, camera_size, camera_hz=1e-3, moving_person=moving_person)
    if not st.success:
        raise RuntimeError(f"{task}: the demonstrator failed in every draw of scene {index}")
    _t, rgb, depth = st.camera[0]
    depth = depth.copy()
    depth[depth > DEPTH_RANGE_M] = np.nan
    ee_t, ee_p, traj3d = demonstration(st, n_waypoints)
    K = scale_intrinsics(st.K, size / camera_size, size / camera_size)
    names, poses = initial_poses(st)
    still_traj = None
    if moving_person:
        still = seeded_demo(task, seed, index, 16, camera_hz=1e-3)
        if still.spec.poses == st.spec.poses:
            path = demonstration(still, n_waypoints)[2]
            still_traj = np.concatenate([project(path, K, st.T_base_camera, PINHOLE, (size, size)), path], 1)
    return ReplayScene(
        name=fresh_name(task, index), task=task,
        rgb=cv2.resize(rgb, (size, size), interpolation=cv2.INTER_AREA).astype(np.uint8),
        affordance=cv2.resize(st.affordance.astype(np.float32), (size, size), interpolation=cv2.INTER_LINEAR),
        depth=cv2.resize(depth, (size, size), interpolation=cv2.INTER_NEAREST),
        object_names=names, objects=poses, duration_s=float(ee_t[-1]), traj3d=traj3d,
        traj2d=project(traj3d, K, st.T_base_camera, PINHOLE, (size, size)), K=K, T_base_camera=st.T_base_camera,
        camera_hz=camera_hz, ee_t=ee_t, ee_pos=ee_p, command_t=np.array([t for t, _a in st.actions]),
        command=np.array([a[:3] for _t, a in st.actions]), person=dict(st.spec.person), still_traj=still_traj)


def demonstration(st, n_waypoints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps, measured tcp, the same as n_waypoints over the demonstration's span) of a recorded demonstration."""
    ee_t = np.array([t for t, _p, _q in st.ee])
    ee_p = np.array([p for _t, p, _q in st.ee])
    return ee_t, ee_p, resample(ee_t, ee_p, 0.0, float(ee_t[-1]), n_waypoints)


def initial_poses(st) -> tuple[list[str], np.ndarray]:
    """The frames a recording's tf gives at its first image, as ingest stores them (x y z qw qx qy qz): the moving
    objects where the first frame saw them, the static ones (manikin, fixtures) at their spec pose."""
    moving = st.objects[0][1] if st.objects else {}
    out: dict[str, np.ndarray] = {}
    for name, (x, y, z, yaw) in st.spec.poses.items():
        if name in moving:
            p, q = moving[name]
            out[name] = np.concatenate([p, q])
        else:
            out[name] = np.array([x, y, z, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    names = sorted(out)
    return names, np.array([out[n] for n in names]).reshape(-1, 7)
