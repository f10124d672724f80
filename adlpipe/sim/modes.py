"""Every demonstrated mode of a recorded scene, rebuilt in the simulator: the reference for mode commitment.

The recorder draws one mode per scene (approach side, grasp side, stroke direction); the dataset keeps the scene's
object poses. Running the scripted demonstrator in each mode of the rebuilt scene gives every mode's end-effector
path, resampled to the dataset's waypoints as ingest resamples the recorded one (evenly in time from the first
frame to the last pose). The demonstrated mode is the one that reproduces the stored trajectory; a scene where
none does within MATCH_TOLERANCE_M is not used (the rebuild would not be the scene that was recorded).
"""

from __future__ import annotations

import numpy as np

from ..geometry.transforms import resample
from .controller import execute_path
from .episode import in_mode, keypoint_path, make_scene, spec_from_objects
from .tasks import TASKS
from .world import HOME_TCP

MATCH_TOLERANCE_M = 0.01  # measured: the demonstrated mode is rebuilt within 0.0-1.8 mm mean per waypoint


def demonstrator_path(spec: object, n_waypoints: int) -> np.ndarray:
    """The scripted demonstrator's tcp path in a scene, (n_waypoints, 3) in the base frame."""
    task = TASKS[spec.task]
    ctrl, scene = make_scene(spec, 16, 16)
    fn, duration = keypoint_path(HOME_TCP.copy(), task.tcp_keypoints(scene))
    times, points = [0.0], [ctrl.tcp_pos]

    def on_step(t: float) -> None:
        times.append(t)
        points.append(ctrl.tcp_pos)

    execute_path(ctrl, fn, duration, on_step=on_step)
    return resample(np.array(times), np.array(points), 0.0, times[-1], n_waypoints)


def mode_paths(task: str, object_names: list[str], objects: np.ndarray,
               demonstrated: np.ndarray) -> np.ndarray | None:
    """(demonstrated mode, other mode) paths, (2, N, 3), of a scene of a two-mode task; None for a task with one
    mode, a task the simulator does not know, or a scene whose rebuild matches no mode of the stored trajectory."""
    if task not in TASKS or not TASKS[task].multimodal:
        return None
    spec = spec_from_objects(task, object_names, objects)
    paths = [demonstrator_path(in_mode(spec, m), len(demonstrated)) for m in TASKS[task].modes]
    gaps = [float(np.linalg.norm(p - demonstrated, axis=1).mean()) for p in paths]
    k = int(np.argmin(gaps))
    if gaps[k] > MATCH_TOLERANCE_M:
        return None
    return np.stack([paths[k], paths[1 - k]])
