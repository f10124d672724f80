"""Push-T: gym-pusht's environment, the scripted demonstrator, its bags through record and ingest (state and action
topics), training on the action stream and the closed-loop benchmark."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import one_line_error, record_seeded_world, run_module

from adlpipe.dataset import schema
from adlpipe.geometry.transforms import project


def test_the_demonstrator_pushes_the_t_onto_the_goal(pusht_data: Path) -> None:
    """Every seeded initial condition ends above gym-pusht's 0.95 coverage within its 300 steps (measured on seeds
    0-9: 0.95-0.98 in 129-249 steps): the recorder's own verdict on the fixture's seeds 0-3 (one attempt each), and
    seed 0 step by step."""
    from adlpipe.envs.pusht import demonstrate, make_env

    assert "recorded 4 episodes" in (pusht_data / "record.txt").read_text()
    assert "(0 without a successful demo)" in (pusht_data / "record.txt").read_text()
    steps = list(demonstrate(make_env(), 0))
    assert steps[-1].info["is_success"] and steps[-1].info["coverage"] > 0.95
    assert len(steps) < 300
    assert steps[0].info["coverage"] < 0.9  # it had work to do


@pytest.fixture(scope="module")
def pusht_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_seeded_world(tmp_path_factory.mktemp("pusht"), "pusht", 4, 48, 0.25)


def test_pusht_bags_carry_state_and_action_per_frame(pusht_data: Path) -> None:
    with schema.open_dataset(pusht_data / "pusht.h5") as f:
        names = schema.episode_names(f)
        assert len(names) == 4
        for n in names:
            g = f[schema.EPISODES][n]
            fr = g["frames"]
            assert g.attrs["task"] == "push the T" and list(g["objects"].attrs["names"]) == ["tee"]
            assert fr["state"].shape == (len(fr["t"]), 2) and fr["action"].shape == (len(fr["t"]), 2)
            assert list(fr["action"].attrs["names"]) == ["target_x", "target_y"]
            assert np.isfinite(fr["state"][()]).all() and np.isfinite(fr["action"][()]).all()
            assert np.allclose(np.diff(fr["t"][()]), 0.1, atol=1e-3)  # the 10 Hz control rate
            # the agent is the end effector (1 px = 1 mm) and the camera model maps it to its rendered pixel
            assert np.allclose(fr["ee_pos"][:, :2] * 1000.0, fr["state"][()], atol=1e-3)
            uv = project(np.c_[fr["state"][()] / 1000.0, np.zeros(len(fr["t"]))], g["K"][()], g["T_base_camera"][()])
            assert np.allclose(uv, (fr["state"][()] + 0.5) * 48 / 512 - 0.5, atol=0.1)
            # the action leads the state: the agent moves towards where it was sent
            step = fr["state"][1:] - fr["state"][:-1]
            towards = fr["action"][:-1] - fr["state"][:-1]
            moving = np.linalg.norm(step, axis=1) > 2
            norms = np.linalg.norm(step, axis=1) * np.linalg.norm(towards, axis=1)
            cos = (step * towards).sum(1)[moving] / norms[moving]
            assert np.median(cos) > 0.8


def test_train_on_actions_and_run_the_benchmark(pusht_data: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    # BC with the references' encoder (a random crop, spatial softmax, each frame through the encoder): the
    # benchmark feeds it the whole image, which it centre-crops
    encoders = {"fm_cnn": ["--image-size", "32"],
                "bc_cnn": ["--image-size", "40", "--crop", "32", "--pool", "spatial_softmax", "--per-frame"]}
    for model, encoder in encoders.items():
        run_module("train", "--model", model, "--closed-loop", "--target", "action", "--data",
                   pusht_data / "pusht.h5", "--split", pusht_data / "split.json", "--out", tmp_path / model,
                   "--epochs", "2", "--val-fraction", "0.34", *encoder, check=True)
    torch = __import__("torch")
    ck = torch.load(tmp_path / "fm_cnn" / "model.pt", weights_only=True)
    assert ck["config"]["action_dim"] == 2 and ck["config"]["state_dim"] == 4 and ck["config"]["target"] == "action"
    ref = torch.load(tmp_path / "bc_cnn" / "model.pt", weights_only=True)
    assert {k: ref["config"][k] for k in ("image_size", "crop", "pool", "per_frame")} == {
        "image_size": 40, "crop": 32, "pool": "spatial_softmax", "per_frame": True}
    assert ref["ema"]["encoder.stem.0.weight"].shape[1] == 4  # one frame's channels per encoder pass
    out = tmp_path / "out"
    run_module("benchmark", "--models", tmp_path / "fm_cnn", tmp_path / "bc_cnn", "--steps", "2", "--episodes", "2",
               "--reference-episodes", "1", "--metrics", out / "m.json", "--details", out / "d.json",
               "--table", out / "t.md", check=True)
    details = json.loads((out / "d.json").read_text())
    rows = {(r["model"], r["steps"], r["checkpoint"]): r for r in details["results"]}
    assert set(rows) == {(m, s, ck) for m, s in (("fm_cnn", 2), ("bc_cnn", 1)) for ck in ("best", "last")}
    for r in rows.values():
        eps = r["per_episode"]
        assert [e["seed"] for e in eps] == [100_000, 100_001] and r["n"] == 2
        assert all(0.0 <= e["score"] <= 1.0 for e in eps)
        lo, hi = r["score_ci"]  # the bootstrap interval holds the mean; Wilson's the rate
        assert lo <= r["score"] <= hi and r["success_ci"][0] <= r["success"] <= r["success_ci"][1]
    assert "| fm_cnn | 2 | last |" in (out / "t.md").read_text()
    from adlpipe import benchmark  # --compare runs nothing: in this process

    assert benchmark.main(["--compare", str(out / "d.json")]) == 0
    compared = capsys.readouterr().out.splitlines()
    assert len(compared) == 6  # 4 rows (2 models x best/last), every pair, on the same 2 initial conditions
    assert any(ln.startswith("- fm_cnn-2 vs bc_cnn-1: score ") and "McNemar" in ln for ln in compared)
    (out / "again_details.json").write_text((out / "d.json").read_text())  # two runs compared: rows by file
    assert benchmark.main(["--compare", str(out / "d.json"), str(out / "again_details.json")]) == 0
    across = capsys.readouterr().out
    assert len(across.splitlines()) == 28  # 8 rows
    assert "- d:fm_cnn-2 vs again:fm_cnn-2: score +0.000 [+0.000, +0.000]" in across
    assert "not a benchmark details file" in one_line_error(run_module("benchmark", "--compare", out / "t.md"))
    refs = details["references"]  # on the first initial condition only (--reference-episodes 1), and said so
    assert [e["seed"] for e in refs["demonstrator"]["per_episode"]] == [100_000] and refs["demonstrator"]["n"] == 1
    assert "| demonstrator, first 1 initial conditions (reference) |" in (out / "t.md").read_text()
    assert refs["demonstrator"]["success"] == 1.0 and refs["demonstrator"]["score"] > 0.95
    assert refs["no action"]["success"] == 0.0 and refs["no action"]["score"] < 0.9
    # the first-frame stages refuse a closed-loop policy in one line
    for stage, args in (("evaluate", ["--models", tmp_path / "fm_cnn", "--metrics", out / "e.json", "--details",
                                      out / "ed.json", "--plots", out / "s.csv", "--table", out / "t1.md"]),
                        ("inspect", ["--model", tmp_path / "fm_cnn", "-o", out / "p.rrd"])):
        proc = run_module(stage, *args, "--data", pusht_data / "pusht.h5", "--split", pusht_data / "split.json")
        assert proc.returncode == 2 and "a closed-loop model" in one_line_error(proc), stage
    # a folder without a trained policy: one line
    proc = run_module("benchmark", "--models", pusht_data, "--episodes", "1", "--metrics", out / "x.json",
                      "--details", out / "y.json", "--table", out / "z.md")
    assert proc.returncode != 0 and "no best.pt; train it first" in one_line_error(proc)


def test_ingest_without_the_state_topic_has_no_state(pusht_data: Path, tmp_path: Path) -> None:
    """state/action are optional topics: a map without them ingests the same bags without the streams, and
    training on actions then says what is missing in one line."""
    bag = sorted((pusht_data / "bags").glob("*.mcap"))[0]
    cfg = tmp_path / "topics.yaml"
    cfg.write_text("depth: null\naffordance: null\ngripper_joint: null\nee_frame: agent\n")
    run_module("ingest", bag, "-o", tmp_path / "d.h5", "--size", "48", "--config", cfg, check=True)
    with h5py.File(tmp_path / "d.h5") as f:
        name = schema.episode_names(f)[0]
    with schema.open_dataset(tmp_path / "d.h5") as f:
        assert "state" not in f[schema.EPISODES][name]["frames"]
    (tmp_path / "split.json").write_text(json.dumps({"train": [name], "test": []}))
    proc = run_module("train", "--model", "fm_cnn", "--closed-loop", "--target", "action", "--data",
                      tmp_path / "d.h5", "--split", tmp_path / "split.json", "--out", tmp_path / "m", "--epochs", "1")
    assert proc.returncode == 2 and "no state/action per frame" in one_line_error(proc)


def test_the_state_variant_records_trains_from_memory_and_curves(pusht_data: Path, tmp_path: Path) -> None:
    """The low-dimensional Push-T: the same bags ingested with topics_state.yaml carry gym-pusht's keypoint state;
    a state-only policy trains on windows held in memory (the same windows the streamed loader gives), keeps
    checkpoints along training and runs the benchmark's learning curve on the keypoint state the environment gives."""
    import torch

    from adlpipe.dataset.loader import WindowDataset, Windows, compute_action_stats
    from adlpipe.dataset.memory_windows import MemoryBatches
    from adlpipe.envs.pusht import keypoint_state, make_env

    data = tmp_path / "state.h5"
    run_module("ingest", *sorted((pusht_data / "bags").glob("*.mcap")), "-o", data, "--size", "48", "--config",
               Path(__file__).parents[1] / "pipelines" / "pusht" / "topics_state.yaml", check=True)
    with schema.open_dataset(data) as f, schema.open_dataset(pusht_data / "pusht.h5") as g:
        names = schema.episode_names(f)
        first = f[schema.EPISODES][names[0]]["frames"]
        assert first["state"].shape[1] == 18 and list(first["state"].attrs["names"])[-2:] == ["agent_x", "agent_y"]
        # the agent part is the image variant's state; frame 0 is the environment's own keypoints at reset
        assert np.allclose(first["state"][:, 16:], g[schema.EPISODES][names[0]]["frames/state"][()])
        source = str(f[schema.EPISODES][names[0]].attrs["source_path"])
    seed = int(Path(source).stem.rsplit("_", 1)[1])  # push_the_T_<initial condition>.mcap
    env = make_env(48, "environment_state_agent_pos")  # what the benchmark gives a state-only policy
    obs, _ = env.reset(seed=seed)
    at_reset = np.concatenate([obs["environment_state"], obs["agent_pos"]])
    assert np.array_equal(at_reset, keypoint_state(env.unwrapped))  # the recorder's formula is gym-pusht's
    env.close()
    with schema.open_dataset(data) as f:
        assert np.allclose(f[schema.EPISODES][names[0]]["frames/state"][0], at_reset, atol=1e-6)

    # memory windows == streamed windows, and each epoch's draw is a permutation continued across epochs
    stats = compute_action_stats(data, names)
    w = Windows(2, 16, 10.0, "action", images=False)
    streamed = WindowDataset(data, names, stats, 48, w)
    mem = MemoryBatches(streamed, batch_size=8, draws=len(streamed), seed=3)
    for i in (0, 7, len(streamed) - 1):
        (_img, state), target = streamed[i]
        assert torch.equal(mem.states[i], state) and torch.equal(mem.targets[i], target)
    assert sorted(mem.order(0)) == list(range(len(streamed))) and not np.array_equal(mem.order(0), mem.order(1))
    (obs_img, obs_state), target, eps, u = next(iter(mem))
    assert obs_img.shape == (8, 0) and obs_state.shape == (8, 36) and target.shape == eps.shape == (8, 16, 2)
    two = MemoryBatches(streamed, batch_size=8, draws=len(streamed), seed=3, world=2, rank=1)
    two.set_epoch(0)
    (_, s1), t1, e1, _ = next(iter(two))
    assert torch.equal(s1, obs_state[4:]) and torch.equal(e1, eps[4:])  # rank 1's share of the same global batch

    out = tmp_path / "fm"
    run_module("train", "--model", "fm_cnn", "--closed-loop", "--target", "action", "--no-image", "--data",
                      data, "--split", pusht_data / "split.json", "--out", out, "--epochs", "2", "--batch-size", "16",
                      "--windows-per-epoch", "all", "--save-every", "1", "--val-fraction", "0.34", check=True)
    metrics = json.loads((out / "metrics.json").read_text())
    steps_per_epoch = metrics["optimizer_steps"] // 2
    assert steps_per_epoch > 2  # every window once per epoch, not one per episode
    assert sorted(p.name for p in (out / "checkpoints").glob("*.pt")) == [
        f"step_{steps_per_epoch:07d}.pt", f"step_{2 * steps_per_epoch:07d}.pt"]
    res = tmp_path / "res"
    run_module("benchmark", "--models", out, "--steps", "2", "--checkpoints", "last", "--episodes", "1",
               "--curve", "--curve-steps", "2", "--metrics", res / "m.json", "--details", res / "d.json",
               "--table", res / "t.md", "--curve-plot", res / "c.png", check=True)
    details = json.loads((res / "d.json").read_text())
    (curve,) = details["curves"]
    assert [p["step"] for p in curve["points"]] == [steps_per_epoch, 2 * steps_per_epoch]
    assert curve["last"]["checkpoints"] == 2 and curve["max"]["score"] == max(p["score"] for p in curve["points"])
    assert (res / "c.png").read_bytes()[:4] == b"\x89PNG"
    assert "Along training" in (res / "t.md").read_text()


def test_two_model_folders_of_one_name_get_rows_of_their_own() -> None:
    """The same model trained with two encoders (models/fm_cnn, models/refenc/fm_cnn) in one benchmark table."""
    from adlpipe.evaluation.benchmark_runs import model_labels

    dirs = [Path("models/fm_cnn"), Path("models/refenc/fm_cnn"), Path("models/bc_cnn")]
    assert model_labels(dirs) == ["models/fm_cnn", "refenc/fm_cnn", "bc_cnn"]
