"""The DVC pipeline end to end with tiny params (record -> ... -> report), then the Rerun inspection of its models.

This is the CI's small `dvc repro`: real bags, real HDF5, real training, evaluation and MuJoCo replay.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml
from conftest import REPO, one_line_error, run_module

MODELS = ["fm_cnn", "dp_cnn", "bc_cnn"]  # the default run's like-for-like trio
PAPER = ["fm_cnn_velocity", "dp_cnn_epsilon"]  # pipelines/paper


def dvc(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    # The stages call `python -m adlpipe...`: the python running the tests must come first on PATH (a venv).
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
    env = {**os.environ, "DVC_NO_ANALYTICS": "1", "PATH": path}
    proc = subprocess.run([sys.executable, "-m", "dvc", *args], cwd=cwd, capture_output=True, text=True, env=env,
                          timeout=900)
    assert proc.returncode == 0, f"dvc {' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("pipeline")
    shutil.copy(REPO / "dvc.yaml", root)
    shutil.copytree(REPO / "adlpipe", root / "adlpipe", ignore=shutil.ignore_patterns("__pycache__"))
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["record"].update(episodes=2, size=32, camera_hz=2)
    params["ingest"]["size"] = 32
    params["train"].update(epochs=2, threads=1)
    params["evaluate"].update(steps="1 16", best_of=2, repeats=2)
    params["replay"].update(scenes=1, workers=2)  # one fresh scene per task
    (root / "params.yaml").write_text(yaml.safe_dump(params))
    subprocess.run(["git", "init", "-q"], cwd=root, check=True)
    dvc(root, "init", "-q")
    dvc(root, "repro")
    return root


def side_pipeline(root: Path, name: str, targets: tuple[str, ...] = (), **params: object) -> Path:
    """pipelines/<name> (its own DVC project) run on the tiny default pipeline's data and models: the stages
    `targets` and what they depend on, or all."""
    where = root / "pipelines" / name
    # .resume: a long training in progress, committed for the next session to finish
    shutil.copytree(REPO / "pipelines" / name, where,
                    ignore=shutil.ignore_patterns("metrics", "models", "reports", ".resume"))
    if params:
        own = yaml.safe_load((where / "params.yaml").read_text())
        for section, values in params.items():
            own[section].update(values)
        (where / "params.yaml").write_text(yaml.safe_dump(own))
    dvc(where, "repro", *targets)
    return where


@pytest.fixture(scope="module")
def closed_loop(pipeline: Path) -> Path:
    # the stages the tests below assert on; the ensemble replays and the Ta sweep (4, 8, 16) are tested in
    # test_closed_loop, so one Ta here (setup 347 -> 194 s with two Ta)
    return side_pipeline(pipeline, "closed_loop", ("report", "history", "disturbances", "replay_recoveries",
                                                   "replay_moving_recoveries"),
                         closed_loop={"execute": "8", "moving_execute": "8", "epochs": 2})


@pytest.fixture(scope="module")
def paper(pipeline: Path) -> Path:
    return side_pipeline(pipeline, "paper")


def test_repro_runs_every_stage(pipeline: Path) -> None:
    bags = sorted((pipeline / "data" / "bags").glob("*.mcap"))
    assert len(bags) == 20
    split = json.loads((pipeline / "data" / "split.json").read_text())
    assert len(split["test"]) == 10 and len(split["train"]) == 10  # one test episode per task
    headline = json.loads((pipeline / "metrics" / "eval.json").read_text())
    assert set(headline) == {*MODELS, "blind", "n_test"}
    assert "px_16_steps" in headline["fm_cnn"] and "px_16_steps" not in headline["dp_cnn"]
    ev = json.loads((pipeline / "metrics" / "eval_details.json").read_text())
    assert sorted(ev["models"]) == sorted([*MODELS, "blind"])
    # the blind baseline: each test episode's task mean training trajectory, the same for every test episode of a
    # task (one per task here), scored like a model
    blind = ev["models"]["blind"]["best"]["task_mean/1"]
    assert blind["n"] == 10 and blind["px"] > 0 and blind["px_ci"][0] <= blind["px"] <= blind["px_ci"][1]
    fm = ev["models"]["fm_cnn"]
    assert sorted(fm) == ["best", "last"]
    assert sorted(fm["best"]) == ["euler/1", "euler/16"] and fm["best"]["euler/16"]["evaluations"] == 16
    row = fm["last"]["euler/1"]
    assert ev["mode_scenes"] == 7  # every two-mode test scene rebuilt in the simulator (one per task)
    assert 0.0 <= row["commitment"] <= 1.0 and set(row["commitment_per_task"]) == {
        "sweep the trash", "pass the water", "hang the towel", "put on the hat", "cover the food", "wipe the forearm",
        "feed the human"}
    assert row["image_px"] == 32 and row["px224"] == pytest.approx(row["px"] * 224 / 32)
    # every mean with its bootstrap interval over the test episodes, whose errors are kept for paired comparisons
    assert row["n"] == 10 and len(row["px_per_episode"]) == 10
    assert np.mean(row["px_per_episode"]) == pytest.approx(row["px"], abs=1e-3)
    assert row["px_ci"][0] < row["px"] < row["px_ci"][1] and row["cm_ci"][0] < row["cm"] < row["cm_ci"][1]
    # and best-of-K, the multimodal tasks' error and mode commitment (resampling scenes) too
    for key in ("best_of_2_px", "px_multimodal", "commitment", "ms"):
        assert row[f"{key}_ci"][0] <= row[key] <= row[f"{key}_ci"][1], key
    assert row["best_of_2_px"] <= row["px"]
    for dp in ("dp_cnn",):
        assert sorted(ev["models"][dp]["last"]) == ["ddim/1", "ddim/16", "ddpm/1", "ddpm/16", "ddpm_trailing/1",
                                                    "ddpm_trailing/16"]
    for model in MODELS:
        hist = (pipeline / "metrics" / "train" / f"{model}.csv").read_text().splitlines()
        assert hist[0].startswith("epoch,step,train_loss,test_loss,val_px") and len(hist) == 3
        assert ev["training"][model]["optimizer_steps"] == ev["training"]["fm_cnn"]["optimizer_steps"]
    report = (pipeline / "reports" / "report.md").read_text()
    assert "## Success rate" in report
    headline_rows = report.split("## Headline")[1].split("\n## ")[0]  # one row per model, before the detail
    assert headline_rows.count("\n| ") == len(MODELS) + 3 and "| fm_cnn | euler | 1 | " in headline_rows
    assert "| blind | task_mean | 1 | " in headline_rows and "## Above the blind baseline" in report
    assert "## How the policies fail, safety first" in report and "| blind | " in report
    assert report.index("## Headline") < report.index("## Table 1 in detail")
    assert "FM-1 about as accurate as DP-16 (within 10% or better; clean-trajectory output for both)" in report
    assert "## Mode commitment" in report and "| fm_cnn | 16 |" in report
    assert "| model | optimiser steps | val px best [95 %] (epoch) |" in report
    assert "exact McNemar p = " in report and "| verdict in success |" in report
    assert "10 fresh scenes (1 per task, drawn by the recorder's generator with seed 0" in report
    assert "### Scenes solved per task" in report and "| pass the water * |" in report
    # the decision: the stated rule on the replayed scenes, which replay ran until decided or its cap (1 per task)
    decision = report.split("## The decision: which policy to put on the robot")[1].split("\n## ")[0]
    assert "Rule: safety first (force on the person > 20 N), then success with a 5-point" in decision
    assert "**Recommended: " in decision or "**Undecided** after 10 scenes" in decision
    assert "Replay ran until decided: it stopped after 10 scenes" in decision
    assert "FM better than BC (U-Net for both" in report and "FM-1 much faster than DP-16" in report
    assert "px: pixels of the 32 px stored image" in report and "a rescaling to the paper's image size" in report
    for fig in ("loss_fm_vs_dp", "val_px_vs_epoch", "px_vs_steps", "ms_vs_steps"):
        png = pipeline / "reports" / "figures" / f"{fig}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"(figures/{fig}.png)" in report


def test_the_demonstrations_replay_successfully(pipeline: Path) -> None:
    """On fresh scenes (the recorder's generator at indices no recording uses), the demonstrator's trajectories,
    resampled to 32 waypoints and executed open loop, solve every task."""
    rp = json.loads((pipeline / "metrics" / "replay_details.json").read_text())
    assert json.loads((pipeline / "metrics" / "replay.json").read_text())["success"]["demo"] == rp["success"]["demo"][
        "overall"]
    assert {"fm_cnn/euler-1", "fm_cnn/euler-16", "dp_cnn/ddpm-16", "bc_cnn"} <= set(rp["success"])
    assert rp["scenes"] == {"kind": "fresh", "per_task": 1, "seed": 0, "moving_person": False}
    assert rp["sequential"]["cap_per_task"] == 1 and rp["sequential"]["looks"][0]["scenes"] == 10
    split = json.loads((pipeline / "data" / "split.json").read_text())
    assert not set(rp["per_episode"]["demo"]) & set(split["test"] + split["train"])
    assert sorted(rp["per_episode"]["demo"])[0] == "fresh/brush_the_teeth/1000000"
    demo = rp["success"]["demo"]
    assert demo["n"] == 10 and len(demo["per_task"]) == 10  # one fresh scene per task
    assert demo["overall"] >= 0.9, demo
    # at the task's demonstrated speed (no demonstration's own duration), the demonstrations still succeed
    assert rp["success"]["demo@fixed-speed"]["overall"] >= 0.8, rp["success"]["demo@fixed-speed"]
    assert {"blind", "blind@fixed-speed", "fm_cnn/euler-1@fixed-speed"} <= set(rp["success"])
    # every episode keeps which parts of its predicate failed and its peak force on the person
    diag = rp["diagnostics"]["fm_cnn/euler-1"]
    assert len(diag) == 10 and all(d["peak_force_n"] >= 0 for d in diag.values())
    failed = [n for n, ok in rp["per_episode"]["fm_cnn/euler-1"].items() if not ok]
    assert all(diag[n]["failed"] for n in failed) and not any(diag[n]["failed"] for n in diag if n not in failed)
    strips = sorted((pipeline / "reports" / "failures").glob("*.png"))
    assert strips and all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in strips)
    assert (pipeline / "reports" / "failures" / "fm_cnn_euler-1.png").exists() == bool(failed)


def test_dvc_commands_print_clean_in_120_columns(pipeline: Path) -> None:
    """After the pipeline ran, dvc metrics show is one row per policy, no warning, and fits a 120-column terminal;
    dvc status and dvc plots show warn of nothing."""
    proc = dvc(pipeline, "metrics", "show")
    lines = proc.stdout.splitlines()
    assert "WARNING" not in proc.stderr + proc.stdout and "failed to load" not in proc.stderr + proc.stdout
    assert max(len(line) for line in lines) <= 120, proc.stdout
    rows = {line.split()[0] for line in lines[1:]}
    assert {f"metrics/summary/{m}.json" for m in ("fm_cnn", "dp_cnn", "bc_cnn", "blind", "demo")} <= rows, proc.stdout
    assert lines[0].split() == ["Path", "cm", "converged", "decision", "ms", "px", "success"]
    decided = {line.split()[3] for line in lines[1:] if "/fm_cnn.json" in line or "/bc_cnn.json" in line}
    assert len(decided) and decided <= {"deploy", "candidate", "undecided", "out-safety", "out-success"}, proc.stdout
    status = dvc(pipeline, "status")
    assert status.stdout.strip() == "Data and pipelines are up to date." and not status.stderr.strip()
    plots = dvc(pipeline, "plots", "show", "--json")
    assert "WARNING" not in plots.stderr, plots.stderr


def test_a_stage_run_by_hand_refuses_to_replace_the_pipelines_outputs(pipeline: Path) -> None:
    split = pipeline / "data" / "split.json"
    before = split.read_bytes()
    proc = run_module("split", "data/adl.h5", "-o", "data/split.json", "--seed", "1", cwd=pipeline)
    line = one_line_error(proc)
    assert "data/split.json" in line and "DVC stage 'split'" in line and "--force" in line
    assert split.read_bytes() == before
    # elsewhere it writes, and --force replaces the pipeline's own (the same seed: the same split)
    run_module("split", "data/adl.h5", "-o", "elsewhere/split.json", cwd=pipeline, check=True)
    assert (pipeline / "elsewhere" / "split.json").exists()
    run_module("split", "data/adl.h5", "-o", "data/split.json", "--test-fraction", "0.2", "--force", cwd=pipeline,
               check=True)
    assert "Data and pipelines are up to date" in dvc(pipeline, "status").stdout


def test_repro_reruns_only_what_changed(pipeline: Path) -> None:
    assert "Data and pipelines are up to date" in dvc(pipeline, "status").stdout
    params = yaml.safe_load((pipeline / "params.yaml").read_text())
    params["train"]["epochs"] = 3
    (pipeline / "params.yaml").write_text(yaml.safe_dump(params))
    changed = dvc(pipeline, "status", "--json").stdout
    stages = set(json.loads(changed))
    assert {f"train@{m}" for m in MODELS} <= stages
    assert not {"record", "ingest", "split"} & stages
    params["train"]["epochs"] = 2
    (pipeline / "params.yaml").write_text(yaml.safe_dump(params))
    assert "Data and pipelines are up to date" in dvc(pipeline, "status").stdout


def test_plots_render_the_loss_curves(pipeline: Path) -> None:
    out = json.loads(dvc(pipeline, "plots", "show", "--json").stdout)
    names = set(out["data"]) if "data" in out else set(out)
    assert any("Train and test loss" in n for n in names) and any("vs sampling steps" in n for n in names)


def test_inspect_writes_a_readable_rerun_recording(pipeline: Path, tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    rrd, verdicts = tmp_path / "preds.rrd", tmp_path / "replay_details.json"  # replay's on recorded test episodes
    run_module("replay", "--models", pipeline / "models" / "fm_cnn", "--data", pipeline / "data" / "adl.h5",
               "--fm-steps", "1", "--metrics", tmp_path / "m.json", "--details", verdicts,
               "--table", tmp_path / "t.md", check=True)
    run_module("inspect", "--model", pipeline / "models" / "fm_cnn", "--data", pipeline / "data" / "adl.h5",
               "--episodes", "0", "1", "--samples", "3", "--replay", verdicts, "-o", rrd, check=True)
    reader = RrdReader(str(rrd))
    summary = reader.store().summary()
    for entity in ("/world/replay", "/world/camera", "/world/camera/image", "/world/camera/image/rgb",
                   "/world/camera/image/affordance", "/world/camera/image/gt", "/world/camera/image/pred",
                   "/world/gt", "/world/pred"):
        assert f"{entity} rows=2 " in summary, (entity, summary)
    assert "Pinhole:image_from_camera" in summary and "Transform3D:mat3x3" in summary
    strips: dict[str, list] = {}
    for chunk in reader.stream().to_chunks():
        rb = chunk.to_record_batch()
        for name in rb.schema.names:
            if name.endswith(":strips"):
                strips.setdefault(str(chunk.entity_path), []).extend(rb.column(name).to_pylist())
    # two episodes; ground truth one strip each, predictions 3 samples each; 32 waypoints per strip
    assert [len(s) for s in strips["/world/camera/image/gt"]] == [1, 1]
    assert [len(s) for s in strips["/world/pred"]] == [3, 3]
    assert {len(strip) for rows in strips.values() for s in rows for strip in s} == {32}
    gt3d = np.array(strips["/world/gt"][0][0])
    assert gt3d.shape == (32, 3) and np.all(np.abs(gt3d) < 2.0)  # metres in the base frame
    assert [e.kind for e in reader.blueprints()] == ["blueprint"]
    texts = [t for chunk in reader.stream().to_chunks() if str(chunk.entity_path) == "/world/replay"
             for name in chunk.to_record_batch().schema.names if name.endswith(":text")
             for t in chunk.to_record_batch().column(name).to_pylist()]
    # replay's verdict on each shown episode for every label of this model (samplers, speed profiles)
    assert len(texts) == 2 and all("fm_cnn/euler-1: " in str(t) and "peak force" in str(t) for t in texts), texts


def test_closed_loop_replay_replans_from_new_images(closed_loop: Path, pipeline: Path) -> None:
    details = json.loads((closed_loop / "metrics" / "replay_closed_loop_details.json").read_text())
    labels = {f"{m}/Ta-8" for m in ("fm_cnn/euler-1", "dp_cnn/ddpm-16", "bc_cnn", "oracle-command")}
    assert set(details["success"]) == labels
    root = json.loads((pipeline / "metrics" / "replay_details.json").read_text())
    assert all(set(v) == set(root["tasks"]) for v in details["per_episode"].values())  # the same fresh scenes
    # the executor fed the demonstrations' plans in the policies' format solves the scenes
    assert details["success"]["oracle-command/Ta-8"]["overall"] >= 0.9, details["success"]
    assert details["training"]["fm_cnn"]["optimizer_steps"] == json.loads(
        (pipeline / "models" / "fm_cnn" / "metrics.json").read_text())["optimizer_steps"]  # the same budget
    ck = torch.load(closed_loop / "models" / "fm_cnn" / "best.pt", weights_only=True)
    cfg = ck["config"]
    assert cfg["n_obs"] == 2 and cfg["horizon"] == 16 and cfg["rate_hz"] == 10 and cfg["state_dim"] == 8
    assert cfg["target"] == "command"  # the commanded tcp, with the measured tcp and gripper as state
    report = (closed_loop / "reports" / "report.md").read_text()
    assert "## Closed loop vs open loop" in report and "| closed loop: fm_cnn/euler-1/Ta-8 |" in report
    assert "| closed loop: oracle-command/Ta-8 (the demonstration's own plans" in report
    assert "- fm_cnn: closed loop " in report and "open loop. Best closed loop fm_cnn/euler-1/Ta-" in report
    assert "exact McNemar p = " in report and "## Where the failed rollouts fail" in report
    assert "| open loop: fm_cnn/euler-1 (first frame -> whole trajectory) |" in report
    # the person who moves: the same scenes, every policy open and closed loop, and open loop's ceiling
    moving = json.loads((closed_loop / "metrics" / "replay_moving_closed_loop_details.json").read_text())
    assert moving["scenes"]["moving_person"] and set(moving["tasks"]) == set(root["tasks"])
    assert moving["success"]["oracle-command/Ta-8"]["overall"] >= 0.9, moving["success"]
    # history.py: each model's plan lengths with its true history and with a frozen one, per test window
    history = json.loads((closed_loop / "metrics" / "history.json").read_text())
    assert set(history) == {"fm_cnn", "dp_cnn", "bc_cnn"}
    assert all(len(h["true"]) == len(h["frozen"]) == len(h["demo"]) > 0 for h in history.values()), history
    section = report.split("## The person who moves")[1]
    for row in ("| open loop: demo-still-person |", "| open loop: fm_cnn/euler-1 |", "| closed loop: bc_cnn/Ta-8 |",
                "| closed loop: oracle-command/Ta-8 |"):
        assert row in section, row


def test_the_trio_trained_with_recoveries_replays_on_the_same_scenes(closed_loop: Path, pipeline: Path) -> None:
    from adlpipe.dataset.splits import recording_keys
    from adlpipe.evaluation.recoveries import recoveries_lines

    rec = json.loads((closed_loop / "metrics" / "recoveries_recording.json").read_text())
    # the recorder pushed its demonstrator off the path (2-5 cm pushes, or stalls), in the default data's scenes
    assert rec["episodes"] == 20 and rec["disturbed"] >= 10 and rec["largest_offset_m"][2] >= 0.02, rec
    assert 0 < rec["samples_off"] < 0.6, rec
    trained = []
    for data in (closed_loop / "data" / "recoveries", pipeline / "data"):
        with h5py.File(data / "adl.h5") as f:
            trained.append(sorted(recording_keys(f, json.loads((data / "split.json").read_text())["train"]).values()))
    assert trained[0] == trained[1]  # the same scenes' bags (other episode names: other commands) in training
    ck = torch.load(closed_loop / "models_recoveries" / "bc_cnn" / "best.pt", weights_only=True)
    assert ck["config"]["target"] == "recovery" and ck["config"]["horizon"] == 16
    path = json.loads((closed_loop / "metrics" / "replay_closed_loop_details.json").read_text())
    got = json.loads((closed_loop / "metrics" / "replay_recoveries_details.json").read_text())
    assert set(got["success"]) == set(path["success"])  # every policy and Ta the path-trained trio ran
    assert all(set(v) == set(path["per_episode"]["bc_cnn/Ta-8"]) for v in got["per_episode"].values())
    open_loop = json.loads((pipeline / "metrics" / "replay_details.json").read_text())
    rows = recoveries_lines([("still", path, got, open_loop)])
    assert len(rows) == 2 + 3 and all(" | still | " in r for r in rows[2:]), rows  # the trio at Ta 8, oracle left out
    moving = json.loads((closed_loop / "metrics" / "replay_moving_recoveries_details.json").read_text())
    assert moving["scenes"]["moving_person"] and moving["success"]["oracle-command/Ta-8"]["overall"] >= 0.9


def test_the_papers_pair_runs_beside_the_trio(paper: Path) -> None:
    ev = json.loads((paper / "metrics" / "eval_details.json").read_text())
    assert set(PAPER + MODELS) <= set(ev["models"])
    assert sorted(ev["models"]["dp_cnn_epsilon"]["last"]) == ["ddim/1", "ddim/16", "ddpm/1", "ddpm/16",
                                                              "ddpm_trailing/1", "ddpm_trailing/16"]
    rp = json.loads((paper / "metrics" / "replay_details.json").read_text())
    root = json.loads((paper.parent.parent / "metrics" / "replay_details.json").read_text())
    assert set(rp["per_episode"]["fm_cnn_velocity/euler-1"]) == set(root["per_episode"]["fm_cnn/euler-1"])
    report = (paper / "reports" / "report.md").read_text()
    assert "FM-1 about as accurate as DP-16 (within 10% or better; the paper's pair: velocity vs noise" in report


def test_closed_loop_replay_refuses_a_first_frame_model(pipeline: Path, tmp_path: Path) -> None:
    proc = run_module("replay", "--models", pipeline / "models" / "fm_cnn", "--data", pipeline / "data" / "adl.h5",
                      "--closed-loop", "8", "--max-episodes", "1", "--metrics", tmp_path / "m.json",
                      "--details", tmp_path / "d.json", "--table", tmp_path / "t.md")
    line = one_line_error(proc)
    assert "trained on first frames only" in line and "--closed-loop" in line
    assert not (tmp_path / "m.json").exists()


def killed_repro(root: Path, stage: str, ready: Callable[[], bool], force: bool = True) -> bool:
    """`dvc repro [-f] -s <stage>`, SIGKILLed with its children once ready() holds: whether it was still running."""
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
    proc = subprocess.Popen([sys.executable, "-m", "dvc", "repro", *(["-f"] if force else []), "-s", stage], cwd=root,
                            env={**os.environ, "DVC_NO_ANALYTICS": "1", "PATH": path}, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 600
    while proc.poll() is None and not ready() and time.time() < deadline:
        time.sleep(0.01)
    running = proc.poll() is None
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    return running


def journal_parts(path: Path) -> int:
    return path.read_text().count("\n") - 1 if path.exists() else 0  # the first line is the fingerprint


def test_a_killed_repro_resumes_without_redoing_finished_parts(pipeline: Path) -> None:
    """R.6, last in this file (it retrains a model): killed in evaluate, replay or training, `dvc repro` goes on
    where the stage stopped and ends with the figures of the uninterrupted run."""
    metrics = pipeline / "metrics"
    ev_before = json.loads((metrics / "eval_details.json").read_text())
    ev_journal = metrics / ".eval_details.json.journal"
    assert killed_repro(pipeline, "evaluate", lambda: journal_parts(ev_journal) >= 1)
    assert not (metrics / "eval_details.json").exists()  # DVC removes a stage's outputs before it runs it
    resumed = dvc(pipeline, "repro", "-s", "evaluate").stdout
    assert "resuming: 1 model(s) evaluated before" in resumed or "resuming: 2 model(s)" in resumed, resumed
    ev_after = json.loads((metrics / "eval_details.json").read_text())
    for model, rows in ev_before["models"].items():
        for key, row in rows["best"].items():  # the same errors; latencies are measured again for the rest
            assert ev_after["models"][model]["best"][key]["px"] == row["px"], (model, key)
    assert not ev_journal.exists()

    rp_before = json.loads((metrics / "replay_details.json").read_text())
    rp_journal = metrics / ".replay_details.json.journal"
    assert killed_repro(pipeline, "replay", lambda: journal_parts(rp_journal) >= 2)
    resumed = dvc(pipeline, "repro", "-s", "replay").stdout
    assert "policies replayed before" in resumed, resumed
    assert json.loads((metrics / "replay_details.json").read_text()) == rp_before
    assert not rp_journal.exists()

    # training: a run that never finished (more epochs), killed after a checkpoint, resumes from it
    params = yaml.safe_load((pipeline / "params.yaml").read_text())
    params["train"]["epochs"] = 4
    (pipeline / "params.yaml").write_text(yaml.safe_dump(params))
    model = pipeline / "models" / "fm_cnn" / "model.pt"
    last = pipeline / ".resume" / "models" / "fm_cnn" / "last.pt"
    assert killed_repro(pipeline, "train@fm_cnn", last.exists, force=False)
    assert not model.exists() and last.exists()  # DVC removed the stage's outputs, not the run in progress
    resumed = dvc(pipeline, "repro", "-s", "train@fm_cnn")
    assert "last.pt: resuming after epoch" in resumed.stderr, resumed.stdout + resumed.stderr
    assert not last.parent.exists()  # a finished run leaves nothing to resume
    cmd = yaml.safe_load((pipeline / "dvc.lock").read_text())["stages"]["train@fm_cnn"]["cmd"]
    cmd = cmd.replace("--out models/fm_cnn --resume-dir .resume/models/fm_cnn", "--out whole")
    run_module("train", *cmd.split()[3:], "--log", "whole/log.csv", cwd=pipeline, check=True)  # uninterrupted
    whole = torch.load(pipeline / "whole" / "model.pt", weights_only=True)["history"]
    again = torch.load(model, weights_only=True)["history"]
    assert [r["train_loss"] for r in again] == pytest.approx([r["train_loss"] for r in whole], rel=1e-4)
    params["train"]["epochs"] = 2  # back to the fixture's run (restored from DVC's run cache)
    (pipeline / "params.yaml").write_text(yaml.safe_dump(params))
    dvc(pipeline, "repro")
    shutil.rmtree(pipeline / "whole")
