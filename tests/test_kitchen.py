"""Franka Kitchen: gymnasium-robotics' environment on the pinned mujoco, the IK demonstrator, and its bags through
record and ingest (59-D state and 9-D action per frame)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REPO, one_line_error, record_seeded_world, run_module

from adlpipe.dataset import schema
from adlpipe.geometry.transforms import project

kitchen = pytest.importorskip("adlpipe.envs.kitchen")


@pytest.fixture(scope="module")
def env() -> object:
    e = kitchen.make_env()
    yield e
    e.close()


def test_the_environment_steps_on_the_installed_mujoco(env: object) -> None:
    """gymnasium-robotics 1.4.2 asserts on mujoco 4.0's joint types; with the patched readers it observes 59-D
    states, and the seeded initial conditions differ (only) by the arm's jitter."""
    a, b = kitchen.reset(env, 1), kitchen.reset(env, 2)
    assert a.shape == (59,) and b.shape == (59,)
    arm = np.abs(a[:7] - b[:7])
    assert 0.001 < arm.max() < 2 * kitchen.INITIAL_JITTER + 0.05
    assert np.allclose(a[18:], b[18:], atol=0.01)  # the kitchen itself starts the same
    obs, _r, _done, _trunc, info = env.step(np.zeros(9))
    assert obs["observation"].shape == (59,) and set(info["tasks_to_complete"]) == set(kitchen.TASKS)


def test_the_demonstrator_does_all_four_tasks_from_seed_0(env: object) -> None:
    """Seed 0 is one the demonstrator finishes (over seeds 0-39 it does microwave 95 %, kettle 100 %, light switch
    98 %, slide cabinet 98 %): all four within the 280-step limit, each at its own time."""
    steps = list(kitchen.demonstrate(env, 0))
    assert kitchen.completed(steps[-1].info) == set(kitchen.TASKS)
    assert len(steps) < kitchen.MAX_STEPS
    done_at = {t: i for i, s in enumerate(steps) for t in s.info["step_task_completions"]}
    assert sorted(done_at, key=done_at.get) == ["microwave", "light switch", "slide cabinet", "kettle"]
    assert all(np.abs(s.action).max() <= 1.0 for s in steps)


@pytest.fixture(scope="module")
def kitchen_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three demonstrations (initial conditions 0-2) at 32 px, ingested with pipelines/kitchen's topic map and
    split 2 / 1."""
    return record_seeded_world(tmp_path_factory.mktemp("kitchen"), "kitchen", 3, 32, 0.34)


def test_kitchen_bags_carry_state_and_action_per_frame(kitchen_data: Path) -> None:
    with schema.open_dataset(kitchen_data / "kitchen.h5") as f:
        names = schema.episode_names(f)
        assert len(names) == 3
        g = f[schema.EPISODES][names[0]]
        fr = g["frames"]
        n = len(fr["t"])
        assert 100 < n < kitchen.MAX_STEPS and np.allclose(np.diff(fr["t"][()]), 0.08, atol=1e-3)  # 12.5 Hz
        assert fr["state"].shape == (n, 59) and fr["action"].shape == (n, 9)
        assert list(fr["action"].attrs["names"])[:2] == ["panda0_joint1", "panda0_joint2"]
        # the state's first nine are the robot's joint positions (with the environment's sensor noise)
        assert np.allclose(fr["state"][:, :9], fr["joint_pos"][()], atol=0.02)
        # the camera model puts the end effector inside the rendered image
        uv = project(fr["ee_pos"][()].astype(float), g["K"][()], g["T_base_camera"][()])
        assert ((uv > 0) & (uv < 32)).all()


def train(kitchen_data: Path, out: Path, model: str, *extra: str) -> None:
    run_module("train", "--model", model, "--closed-loop", "--target", "action", *extra, "--data",
               kitchen_data / "kitchen.h5", "--split", kitchen_data / "split.json", "--out", out, "--epochs", "2",
               "--image-size", "32", "--val-fraction", "0.5", check=True)


@pytest.fixture(scope="module")
def state_models(kitchen_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """FM-CNN, DP-CNN and BC-CNN on the 59-D state alone, two epochs each, in one folder."""
    root = tmp_path_factory.mktemp("state_models")
    for model in ("fm_cnn", "dp_cnn", "bc_cnn"):
        train(kitchen_data, root / model, model, "--no-image")
    return root


def test_state_only_policies_train_and_run_the_kitchen_benchmark(state_models: Path, tmp_path: Path) -> None:
    models = state_models
    ck = torch.load(models / "fm_cnn" / "model.pt", weights_only=True)
    cfg = ck["config"]
    assert cfg["use_image"] is False and cfg["action_dim"] == 9 and cfg["state_dim"] == 2 * 59
    assert not any(k.startswith("encoder.") for k in ck["ema"])  # no image encoder at all
    out = tmp_path / "out"
    run_module("benchmark", "--env", "kitchen", "--models", *(models / m for m in ("fm_cnn", "dp_cnn", "bc_cnn")),
               "--steps", "2", "--dp-sampler", "ddim_trailing", "--checkpoints", "last", "--episodes", "1",
               "--max-steps", "12", "--metrics", out / "m.json",
               "--details", out / "d.json", "--table", out / "t.md", check=True)
    details = json.loads((out / "d.json").read_text())
    rows = {(r["model"], r["steps"], r["checkpoint"]): r for r in details["results"]}
    assert set(rows) == {("fm_cnn", 2, "last"), ("dp_cnn (ddim_trailing)", 2, "last"), ("bc_cnn", 1, "last")}
    for r in rows.values():  # the sampler is named; only the checkpoint asked for ran
        (e,) = r["per_episode"]
        assert e["seed"] == 100_000 and set(e["tasks"]) <= set(kitchen.TASKS)
        assert e["score"] == len(e["tasks"]) / 4 and e["success"] == (len(e["tasks"]) == 4)
        assert set(r["tasks"]) == set(kitchen.TASKS) and r["n"] == 1
        assert e["plans"] == 2  # --max-steps 12 at Ta 8: the second plan is cut after 4 of its actions
    demo = details["references"]["demonstrator"]
    assert demo["score"] == 1.0 and demo["tasks"] == {t: 1.0 for t in kitchen.TASKS}  # seed 100000: all four
    table = (out / "t.md").read_text()
    assert details["max_steps"] == 12 and "at most 12 steps (the environment's limit is 280" in table
    assert "| fm_cnn | 2 | last |" in table and "microwave / kettle / light switch / slide cabinet" in table
    # --clip-sample and --noise-scale: set alike for every generative model, and named in its row
    run_module("benchmark", "--env", "kitchen", "--models", models / "fm_cnn", models / "dp_cnn",
               "--steps", "2", "--clip-sample", "on", "--noise-scale", "0.5", "--checkpoints", "last",
               "--episodes", "1", "--max-steps", "4", "--metrics", out / "m2.json", "--details", out / "d2.json",
               "--table", out / "t2.md", check=True)
    rows = {r["model"] for r in json.loads((out / "d2.json").read_text())["results"]}
    assert rows == {"fm_cnn (clipped) (noise 0.5)", "dp_cnn (clipped) (noise 0.5)"}


def test_the_mechanism_measurement_reads_the_policies_own_windows(kitchen_data: Path, state_models: Path,
                                                                 tmp_path: Path) -> None:
    """pipelines/kitchen_levers/mechanism.py (issue L3) on the trained pair: the test episodes' windows in the
    training format, every DDPM step with its matched flow time, and each sampler with and without clipping; a
    clipped sampler's plans end inside [-1, 1] exactly (its last step lands on the clipped estimate)."""
    out = tmp_path / "m.json"
    subprocess.run([sys.executable, str(REPO / "pipelines" / "kitchen_levers" / "mechanism.py"),
                    str(state_models / "fm_cnn"), str(state_models / "dp_cnn"),
                    "--data", str(kitchen_data / "kitchen.h5"), "--split", str(kitchen_data / "split.json"),
                    "--frames", "6", "--samples", "2", "--out", str(out), "--table", str(tmp_path / "m.md")],
                   check=True, capture_output=True, text=True)
    r = json.loads(out.read_text())
    n_test = len(json.loads((kitchen_data / "split.json").read_text())["test"])
    assert r["windows"] == 6 * n_test and sum(r["phases"].values()) == r["windows"]
    ts = [f["t"] for f in r["fit"]]
    assert [f["k"] for f in r["fit"]][0] == 0 and ts[0] > 0.9 and ts[-1] < 0.05 and ts == sorted(ts, reverse=True)
    assert sum(b["dp"] for b in r["training_share"]) == pytest.approx(1.0)
    rows = {(p["model"], p["steps"]): p["by_phase"]["all"] for p in r["plans"]}
    models = ("FM", "FM clipped", "DP", "DP unclipped", "FM noise 0.5", "DP noise 0.5")
    assert set(rows) == {(m, s) for m in models for s in (2, 16)}
    for steps in (2, 16):
        assert rows["FM clipped", steps]["outside"] == 0.0 and rows["DP", steps]["outside"] == 0.0
    assert "| FM clipped | 16 |" in (tmp_path / "m.md").read_text()


def test_the_kitchen_benchmark_refuses_an_image_policy(kitchen_data: Path, tmp_path: Path) -> None:
    """The seed's kitchen policies see the state alone: a model trained with images is refused in one line, and
    --no-image without --closed-loop is too."""
    train(kitchen_data, tmp_path / "img", "bc_cnn")
    proc = run_module("benchmark", "--env", "kitchen", "--models", tmp_path / "img", "--episodes", "1",
                      "--metrics", tmp_path / "m.json", "--details", tmp_path / "d.json", "--table", tmp_path / "t.md")
    assert proc.returncode == 2 and "not a Franka Kitchen policy" in one_line_error(proc)
    assert not (tmp_path / "m.json").exists()
    proc = run_module("train", "--model", "bc_cnn", "--no-image", "--data", kitchen_data / "kitchen.h5", "--split",
                      kitchen_data / "split.json", "--out", tmp_path / "x", "--epochs", "1")
    assert proc.returncode == 2 and "--no-image needs --closed-loop" in one_line_error(proc)


def test_state_only_windows_read_no_image(kitchen_data: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A state-only window carries the same state and actions as the image one, an empty image part, and never
    reads a frame."""
    from adlpipe.dataset.loader import WindowDataset, Windows, compute_action_stats

    h5 = kitchen_data / "kitchen.h5"
    with schema.open_dataset(h5) as f:
        names = schema.episode_names(f)
    stats = compute_action_stats(h5, names)
    with_images = WindowDataset(h5, names, stats, 32, Windows(2, 16, target="action"))
    (img, state), target = with_images[40]
    assert img.shape == (2 * 4, 32, 32)

    def no_images(*_a: object) -> None:
        raise AssertionError("a state-only window read an image")

    monkeypatch.setattr(WindowDataset, "_images", no_images)
    state_only = WindowDataset(h5, names, stats, 32, Windows(2, 16, target="action", images=False))
    (img2, state2), target2 = state_only[40]
    assert img2.numel() == 0 and state2.shape == (2 * 59,) and target2.shape == (16, 9)
    assert torch.equal(state, state2) and torch.equal(target, target2)
    assert state2.abs().max() <= 1.0 and target2.abs().max() <= 1.0  # normalised with the train statistics
