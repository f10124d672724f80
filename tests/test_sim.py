"""The MuJoCo ADL world: modes invisible in the observation, and success predicates that mean what they say."""

from __future__ import annotations

import numpy as np
import pytest

from adlpipe.sim.controller import execute_path
from adlpipe.sim.episode import in_mode, keypoint_path, make_scene, record_demo
from adlpipe.sim.tasks import FORCE_LIMIT_N, TASKS, SuccessMonitor
from adlpipe.sim.world import HOME_TCP

MULTIMODAL = sorted(name for name, t in TASKS.items() if t.multimodal)


@pytest.mark.parametrize("task", MULTIMODAL)
def test_the_first_observation_does_not_tell_the_mode(task: str) -> None:
    """One scene recorded in both modes: the first RGB frame, depth and affordance map are identical, while the
    demonstrated trajectories differ."""
    spec = TASKS[task].sample(np.random.default_rng(7))
    a = record_demo(task, np.random.default_rng(0), 48, 48, camera_hz=1.0, spec=in_mode(spec, -1.0))
    b = record_demo(task, np.random.default_rng(0), 48, 48, camera_hz=1.0, spec=in_mode(spec, 1.0))
    (_, rgb_a, depth_a), (_, rgb_b, depth_b) = a.camera[0], b.camera[0]
    assert np.array_equal(rgb_a, rgb_b)
    assert np.array_equal(depth_a, depth_b, equal_nan=True)
    assert np.array_equal(a.affordance, b.affordance)
    assert a.affordance.max() > 0.5  # the map does mark something
    path_a, path_b = np.array([p for _, p, _ in a.ee]), np.array([p for _, p, _ in b.ee])
    n = min(len(path_a), len(path_b))
    assert np.abs(path_a[:n] - path_b[:n]).max() > 0.02  # the two modes are different motions


def _run(task_name: str, keypoints_fn, seed: int = 1) -> SuccessMonitor:  # noqa: ANN001
    task = TASKS[task_name]
    spec = in_mode(task.sample(np.random.default_rng(seed)), 1.0)
    ctrl, scene = make_scene(spec, 16, 16)
    path, duration = keypoint_path(HOME_TCP.copy(), keypoints_fn(task, scene))
    monitor = SuccessMonitor(task, scene)
    execute_path(ctrl, path, duration, on_step=lambda _t: monitor.step())
    return monitor


@pytest.mark.parametrize("task", sorted(TASKS))
def test_the_demonstrator_succeeds_within_the_force_limit(task: str) -> None:
    monitor = _run(task, lambda t, s: t.tcp_keypoints(s))
    assert monitor.success(), monitor.checks()
    assert monitor.max_force < FORCE_LIMIT_N


def test_pressing_into_the_face_fails_on_force() -> None:
    """The nose wipe 3 cm deeper into the face: the stroke is there, but the force on the person is too high."""
    def deeper(t, s):  # noqa: ANN001, ANN202
        return [(p + np.array([0, 0.03, 0]) if dwell > 0 or i in (2, 3) else p, dwell)
                for i, (p, dwell) in enumerate(t.tcp_keypoints(s))]

    monitor = _run("wipe the nose", deeper)
    assert monitor.max_force > FORCE_LIMIT_N and not monitor.success()


def test_hovering_over_the_skin_is_not_wiping() -> None:
    """The forearm stroke 1.5 cm above the skin passes every waypoint within the old 3 cm radius: no contact, no
    success."""
    monitor = _run("wipe the forearm", lambda t, s: [(p + np.array([0, 0, 0.015]), d) for p, d in t.tcp_keypoints(s)])
    assert monitor.stroked == 0.0 and not monitor.success()


def test_a_grasp_needs_the_fingers_at_the_object() -> None:
    """The cup grasped 2 cm off its grasp site (inside the old 3.5 cm 'magnetic' radius): it is not taken."""
    monitor = _run("pass the water", lambda t, s: [(p + np.array([0.02, 0, 0]), d) for p, d in t.tcp_keypoints(s)])
    assert monitor.checks()["placed"] is False
