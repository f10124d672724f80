"""Offline assessment on recordings (issue S): inverse kinematics on the robot's MuJoCo model, the first frame's
depth as the scene, the demonstration's key poses; validated against the simulated replay on the same episodes."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import one_line_error, run_module

from adlpipe.dataset import schema
from adlpipe.geometry.camera import Lens, project
from adlpipe.offline.assess import Criteria, assess, context
from adlpipe.offline.robot import Robot, Tolerances, surface_samples
from adlpipe.offline.scene import DepthScene, back_project
from adlpipe.sim.tasks import TASKS
from adlpipe.sim.world import ARM_JOINTS, HOME_Q, arm_mjcf


def test_inverse_kinematics_reach_and_speed() -> None:
    robot = Robot(arm_mjcf())
    q0 = robot.start_q(ARM_JOINTS, HOME_Q)
    robot.set_q(q0)
    start = robot.ee()
    near = start + np.linspace(0, 1, 32)[:, None] * np.array([0.10, 0.15, -0.10])
    ok = robot.feasibility(near, q0, 0.15, Tolerances())
    assert ok.feasible and ok.residual_m.max() < 1e-3 and ok.self_collisions == 0
    robot.set_q(ok.q[-1])
    assert np.linalg.norm(robot.ee() - near[-1]) < 1e-3  # MuJoCo's own forward kinematics agrees
    far = robot.feasibility(start + np.linspace(0, 1, 32)[:, None] * np.array([1.5, 0, 0]), q0, 0.15, Tolerances())
    assert not far.feasible and "out of reach" in far.why[0]
    fast = robot.feasibility(near, q0, 0.005, Tolerances())  # the same path in 0.16 s
    assert not fast.feasible and any("joint speed" in w for w in fast.why)
    assert robot.start_q(["joint4"], np.array([-1.0]))[3] == -1.0  # joints the recording lacks keep the rest pose


@pytest.mark.parametrize("lens", [Lens(), Lens("plumb_bob", (-0.28, 0.07, 1e-4, -2e-4, 0.0))])
def test_the_depth_scene_round_trips_through_the_camera_model(lens: Lens) -> None:
    """Back-projected depth pixels project back to their own pixels (through the lens) at their own depth."""
    K = np.array([[40.0, 0, 31.5], [0, 40.0, 31.5], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0.2, -0.1, 1.0]
    depth = np.full((64, 64), 1.2, np.float32) + np.linspace(0, 0.3, 64, dtype=np.float32)[None]
    depth[:5] = np.nan
    pts = back_project(depth, K, T, lens)
    assert len(pts) == 59 * 64
    uv = project(pts, K, T, lens, (64, 64))
    v, u = np.nonzero(np.isfinite(depth))
    assert np.abs(uv - np.stack([u, v], 1)).max() < 1e-3
    scene = DepthScene.from_depth(depth, K, T, lens)
    assert np.abs(scene.behind(pts)).max() < 1e-5  # each surface point lies on the surface along its ray
    ray_in = pts + (pts - T[:3, 3]) * 0.05  # 5 % further along the ray: behind the surface
    assert (scene.behind(ray_in) > 0).all() and scene.clearance(pts).max() < 1e-9


def test_the_demonstration_passes_and_a_path_sunk_20_cm_does_not(ingested: Path) -> None:
    crit = Criteria()
    with h5py.File(ingested) as f:
        for name in schema.episode_names(f):
            g = f["episodes"][name]
            robot = Robot(arm_mjcf(TASKS[str(g.attrs["task"])].tool))
            samples = surface_samples(robot.model)
            ctx = context(g, robot, samples, crit)
            demo = assess(robot, samples, ctx, g["traj3d"][()].astype(float), crit)
            assert demo["pass"] and demo["reach_m"] < 1e-3 and demo["penetration_m"] == 0.0, (name, demo)
            sunk = assess(robot, samples, ctx, g["traj3d"][()].astype(float) - [0, 0, 0.20], crit)
            assert not sunk["safe"] and sunk["penetration_m"] > 0.05 and not sunk["does_what_demo_did"], (name, sunk)


def test_the_stage_validates_its_verdicts_against_replay(ingested: Path, tmp_path: Path) -> None:
    with h5py.File(ingested) as f:
        names = schema.episode_names(f)
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": [], "test": names}))
    replay = tmp_path / "replay.json"
    run_module("replay", "--data", ingested, "--split", split, "--details", replay, "--metrics", tmp_path / "r.json",
               "--table", tmp_path / "t2.md", "--workers", "1", check=True)
    details, table = tmp_path / "a.json", tmp_path / "a.md"
    run_module("assess", "--data", ingested, "--split", split, "--replay", replay, "--details", details, "--table",
               table, check=True)
    out = json.loads(details.read_text())
    demo = out["verdicts"]["demo"]
    assert len(demo) == 3 and all(v["pass"] for v in demo.values())
    truth = json.loads(replay.read_text())["per_episode"]["demo"]
    c = out["validation"]["pass_vs_success"]
    assert c["tp"] + c["fp"] + c["fn"] + c["tn"] == 3 and c["tp"] == sum(truth.values())
    assert "Validated against the simulated replay" in table.read_text()
    # the default pipeline's replay runs fresh scenes: no ground truth for these episodes, said in one line
    fresh = tmp_path / "fresh.json"
    fresh.write_text(json.dumps({**json.loads(replay.read_text()), "scenes": {"kind": "fresh", "per_task": 20}}))
    proc = run_module("assess", "--data", ingested, "--split", split, "--replay", fresh, "--details",
                      tmp_path / "b.json", "--table", tmp_path / "b.md")
    assert "a replay of fresh scenes, not of the recorded test episodes" in one_line_error(proc)
    assert not (tmp_path / "b.json").exists()


def test_a_labs_robot_model_from_a_file_and_a_wrong_site_is_one_line(tmp_path: Path) -> None:
    from adlpipe.plumbing.errors import AdlError

    xml = tmp_path / "arm.xml"
    xml.write_text(arm_mjcf())
    robot = Robot(path=xml, ee_site="tcp")
    assert robot.joints[:7] == ARM_JOINTS
    with pytest.raises(AdlError, match="no site 'gripper_tip' for the end effector"):
        Robot(path=xml, ee_site="gripper_tip")
    (tmp_path / "bad.xml").write_text("<mujoco><worldbody><body></mujoco>")
    with pytest.raises(AdlError, match="not a MuJoCo model"):
        Robot(path=tmp_path / "bad.xml")


def test_without_a_depth_image_safety_is_not_assessed_rather_than_called_safe(ingested: Path, tmp_path: Path) -> None:
    from conftest import copy_dataset

    data = copy_dataset(ingested, tmp_path / "nodepth.h5")
    with h5py.File(data) as f:
        name = schema.episode_names(f)[0]
        file = schema.episode_path(data, f, name)
    with h5py.File(file, "r+") as f:
        del f["episodes"][name]["depth"]
    crit = Criteria()
    with h5py.File(data) as f:
        g = f["episodes"][name]
        robot = Robot(arm_mjcf(TASKS[str(g.attrs["task"])].tool))
        samples = surface_samples(robot.model)
        ctx = context(g, robot, samples, crit)
        v = assess(robot, samples, ctx, g["traj3d"][()].astype(float) - [0, 0, 0.2], crit)
    assert v["safe"] is None and v["pass"] is None and v["min_clearance_m"] is None
    assert v["feasible"] in (True, False) and not v["does_what_demo_did"]
