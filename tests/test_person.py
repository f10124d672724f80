"""The person who moves (record / replay --moving-person): the manikin's head and forearm move at a seated person's
pace, the task predicates and the demonstrator follow them, the still world is built as before, and a first-frame
plan (the still person's demonstration) misses where the person went, in real rollouts."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from adlpipe.sim.episode import FRESH_INDEX0, make_scene, replay_trajectory, seeded_demo
from adlpipe.sim.person import draw_motion, moved_by, still_until
from adlpipe.sim.tasks import TASKS


def scene_pair(task: str, index: int) -> tuple:
    """(still, moving) demonstrations of fresh scene `index` of a task: the same draw, the person still or moving."""
    return (seeded_demo(task, 0, FRESH_INDEX0 + index, 16, 1e-3),
            seeded_demo(task, 0, FRESH_INDEX0 + index, 16, 1e-3, moving_person=True))


def test_the_person_moves_once_at_a_seated_persons_pace() -> None:
    """Mouth and forearm stay put until the drawn start, move by centimetres at a few cm/s, then hold."""
    spec = replace(TASKS["feed the human"].sample(np.random.default_rng(3)),
                   person=draw_motion(np.random.default_rng(4)))
    ctrl, scene = make_scene(spec, 16, 16)
    mouth, forearm, t = [], [], []
    while ctrl.d.time < 4.0:
        ctrl.step()
        t.append(ctrl.d.time)
        mouth.append(scene.site("mouth"))
        forearm.append(scene.site("forearm_end"))
    t, mouth, forearm = np.array(t), np.array(mouth), np.array(forearm)
    before, after = t < still_until(spec.person) - 0.01, t > moved_by(spec.person) + 0.01
    for path, least in ((mouth, 0.01), (forearm, 0.02)):
        assert np.ptp(path[before], axis=0).max() < 1e-6  # still before the move
        assert np.ptp(path[after], axis=0).max() < 1e-6  # holds the end pose after it
        moved = np.linalg.norm(path[after][0] - path[0])
        assert least < moved < 0.08, moved
        speed = np.linalg.norm(np.diff(path, axis=0), axis=1) / np.diff(t)
        assert speed.max() < 0.15, speed.max()  # m/s: slow, comfortable movements
    assert forearm[after][0][2] > forearm[0][2] + 0.02  # the forearm lifts


def test_a_still_person_is_built_as_before() -> None:
    """Without motion the manikin is one body with no mocap parts; with motion its head and forearm are mocap
    bodies whose sites start exactly where the still manikin has them."""
    spec = TASKS["wipe the forearm"].sample(np.random.default_rng(0))
    still, _ = make_scene(spec, 16, 16)
    moving, _ = make_scene(replace(spec, person=draw_motion(np.random.default_rng(1))), 16, 16)
    assert still.m.nmocap == 0 and moving.m.nmocap == 2
    for name in ("mouth", "nose", "head_top", "forearm_start", "forearm_end", "hand_rest"):
        assert np.abs(still.d.site(name).xpos - moving.d.site(name).xpos).max() < 1e-6


@pytest.mark.parametrize("task", ["feed the human", "wipe the forearm"])
def test_the_demonstrator_follows_the_person_and_a_first_frame_plan_misses(task: str) -> None:
    """The tracking demonstrator succeeds with the person moving; the still person's demonstration of the same scene
    (what a perfect first-frame plan would execute) succeeds with the person still and fails with the person moving:
    the predicate judges the spoon at the mouth, the sponge on the forearm, where they are then, and the force of a
    forearm lifting into the sponge."""
    still, moving = scene_pair(task, 0)
    assert still.success and moving.success and moving.spec.poses == still.spec.poses
    plan = np.array([p for _t, p, _q in still.ee])
    assert replay_trajectory(still.spec, plan, still.duration).success
    run = replay_trajectory(moving.spec, plan, still.duration)
    assert not run.success, run.checks
    # it misses the mouth or the stroke, or the forearm lifts into the sponge (force on the person)
    assert {k for k, ok in run.checks.items() if not ok} & {"dwell", "stroke", "force"}, run.checks


def test_contact_with_a_moving_person_counts_as_force() -> None:
    """The forearm lifting into a sponge held just above it pushes on it: the force on the person is measured on
    the moving body (a still person is not touched)."""
    from adlpipe.sim.controller import track_path
    from adlpipe.sim.tasks import SuccessMonitor

    spec = TASKS["wipe the forearm"].sample(np.random.default_rng(0))
    person = {"head_t0": 9.0, "head_s": 1.0, "head_yaw": 0.0, "head_pitch": 0.0, "arm_t0": 0.2, "arm_s": 1.0,
              "arm_lift": float(np.deg2rad(15))}
    forces = {}
    for label, p in (("still", {}), ("moving", person)):
        ctrl, scene = make_scene(replace(spec, person=p), 16, 16)
        above = scene.site("forearm_end") + np.array([0.0, 0.0, 0.085])  # the sponge 1.5 cm above the skin
        monitor = SuccessMonitor(TASKS[spec.task], scene)
        track_path(ctrl, lambda _t, a=above: a, 2.0, on_step=lambda _t, m=monitor: m.step())
        forces[label] = monitor.max_force
    assert forces["still"] == 0.0 and forces["moving"] > 1.0, forces


def test_record_moving_person_writes_the_same_scene_with_the_person_moving(tmp_path) -> None:
    """record --moving-person: the same seeded scene (the first frame equal to the still recording's) with a
    demonstration that follows the mouth where it went; a world without a person refuses the option."""
    from conftest import one_line_error, run_module

    from adlpipe.dataset import schema

    eps = {}
    for label, extra in (("still", []), ("moving", ["--moving-person"])):
        run_module("record", "--out", tmp_path / label, "--episodes", "1", "--tasks", "feed the human", "--size", "32",
                   "--camera-hz", "2", "--workers", "1", *extra, check=True)
        run_module("ingest", *sorted((tmp_path / label).iterdir()), "-o", tmp_path / f"{label}.h5", "--size", "32",
                   check=True)
        with schema.open_dataset(tmp_path / f"{label}.h5") as f:
            eps[label] = schema.read_episode(f, schema.episode_names(f)[0])
    assert np.array_equal(eps["still"].rgb, eps["moving"].rgb)  # the person moves after the first frame
    assert 0.005 < np.abs(eps["still"].traj3d - eps["moving"].traj3d).max() < 0.1  # the spoon went elsewhere
    proc = run_module("record", "--world", "pusht", "--out", tmp_path / "p", "--moving-person")
    assert proc.returncode != 0 and "--moving-person" in one_line_error(proc)
