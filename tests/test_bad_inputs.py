"""Bad input to every stage: one stderr line naming the problem, a non-zero exit, no traceback, old outputs kept.

Stages run in-process through their real entry point (run_cli + main) to keep the suite fast; a few cases that
need a process of their own (a read-only file system, concurrent writers) run as subprocesses.
"""

from __future__ import annotations

import importlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import REPO, copy_dataset, one_line_error, run_module

from adlpipe.plumbing.errors import run_cli
from adlpipe.policy.models import ModelConfig
from adlpipe.training.loop import train

TINY = dict(image_size=32, encoder_width=8, obs_dim=16, down_dims=(16, 32, 64), d_model=32, n_layers=1, n_heads=2)


class Proc:
    def __init__(self, rc: int, stdout: str, stderr: str) -> None:
        self.returncode, self.stdout, self.stderr = rc, stdout, stderr


def run_stage(capsys: pytest.CaptureFixture, stage: str, *args: object) -> Proc:
    module = importlib.import_module(f"adlpipe.{stage}")
    capsys.readouterr()
    try:
        rc = run_cli(f"adlpipe.{stage}", module.main, [str(a) for a in args])
    except SystemExit as exc:  # the parser's own exit
        rc = int(exc.code or 0)
    out = capsys.readouterr()
    return Proc(rc, out.out, out.err)


@pytest.fixture(scope="module")
def world(ingested: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A valid dataset, split and tiny trained model, to pair with one bad input at a time."""
    root = tmp_path_factory.mktemp("bad_inputs")
    data = root / "adl.h5"
    copy_dataset(ingested, data)
    with h5py.File(data) as f:
        names = sorted(f["episodes"])
    split = root / "split.json"
    split.write_text(json.dumps({"train": names[:2], "test": names[2:]}))
    model = root / "model"
    train(data, split, model, ModelConfig(model="fm_cnn", **TINY), epochs=1, batch_size=2, val_fraction=0)
    return {"data": data, "split": split, "model": model, "root": root}


def bad_data_files(root: Path) -> dict[str, Path]:
    root.mkdir(parents=True, exist_ok=True)
    (root / "folder.h5").mkdir(exist_ok=True)
    (root / "empty.h5").write_bytes(b"")
    (root / "text.h5").write_text("not hdf5 at all\n")
    with h5py.File(root / "foreign.h5", "w") as f:
        f["something"] = np.arange(3)
    return {"missing": root / "missing.h5", "folder": root / "folder.h5", "empty": root / "empty.h5",
            "not-hdf5": root / "text.h5", "foreign-hdf5": root / "foreign.h5"}


STAGES_WITH_DATA = ["split", "train", "evaluate", "replay", "inspect", "doctor", "edit", "assess"]


def data_args(stage: str, w: dict[str, Path], data: Path, tmp: Path) -> list[object]:
    return {
        "split": [data, "-o", tmp / "s.json"],
        "train": ["--model", "fm_cnn", "--data", data, "--split", w["split"], "--out", tmp / "m", "--epochs", 1],
        "evaluate": ["--models", w["model"], "--data", data, "--split", w["split"], "--metrics", tmp / "e.json",
                     "--details", tmp / "d.json", "--plots", tmp / "p.csv", "--table", tmp / "t.md"],
        "replay": ["--models", w["model"], "--data", data, "--split", w["split"], "--metrics", tmp / "r.json",
                   "--details", tmp / "rd.json", "--table", tmp / "t2.md"],
        "inspect": ["--model", w["model"], "--data", data, "--split", w["split"], "-o", tmp / "x.rrd"],
        "doctor": [data, "--json", tmp / "doctor.json"],
        "edit": [data, "-o", tmp / "edited.h5", "--drop", "x"],
        "assess": ["--data", data, "--split", w["split"], "--details", tmp / "a.json", "--table", tmp / "a.md"],
    }[stage]


@pytest.mark.parametrize("kind", ["missing", "folder", "empty", "not-hdf5", "foreign-hdf5"])
@pytest.mark.parametrize("stage", STAGES_WITH_DATA)
def test_a_bad_dataset_is_one_line(capsys: pytest.CaptureFixture, world: dict, tmp_path: Path, stage: str,
                                   kind: str) -> None:
    data = bad_data_files(tmp_path / "bad")[kind]
    line = one_line_error(run_stage(capsys, stage, *data_args(stage, world, data, tmp_path)))
    assert str(data) in line
    assert not any(p.name.startswith(".") and ".tmp" in p.name for p in tmp_path.iterdir())


def test_a_dataset_with_a_nan_trajectory_is_refused(capsys: pytest.CaptureFixture, world: dict,
                                                    tmp_path: Path) -> None:
    data = tmp_path / "nan.h5"
    copy_dataset(world["data"], data)
    with h5py.File(data, "a") as f:
        name = sorted(f["episodes"])[0]
        t = f["episodes"][name]["traj3d"]
        t[3, 1] = np.nan
    line = one_line_error(run_stage(capsys, "train", *data_args("train", world, data, tmp_path)))
    assert "non-finite" in line and name in line


@pytest.mark.parametrize("shape", ["rgba", "not-square"])
def test_a_first_frame_of_the_wrong_shape_is_refused(capsys: pytest.CaptureFixture, world: dict, tmp_path: Path,
                                                     shape: str) -> None:
    data = tmp_path / "shape.h5"
    copy_dataset(world["data"], data)
    with h5py.File(data, "a") as f:
        name = sorted(f["episodes"])[0]
        g = f["episodes"][name]
        rgb = g["rgb"][()]
        del g["rgb"]
        g["rgb"] = np.concatenate([rgb, rgb[..., :1]], 2) if shape == "rgba" else rgb[:-4]
    line = one_line_error(run_stage(capsys, "train", *data_args("train", world, data, tmp_path)))
    assert "first-frame images" in line and name in line


@pytest.mark.parametrize(("content", "needle"), [
    ("{", "cannot read split"),
    ('{"train": "abc", "test": []}', "list of episode names"),
    ('{"train": [1, 2], "test": []}', "list of episode names"),
    ('{"train": ["no_such_episode"], "test": []}', "not in the dataset"),
    ("[]", "not a split file"),
])
def test_a_bad_split_is_one_line(capsys: pytest.CaptureFixture, world: dict, tmp_path: Path, content: str,
                                 needle: str) -> None:
    split = tmp_path / "split.json"
    split.write_text(content)
    line = one_line_error(run_stage(capsys, "train", "--model", "fm_cnn", "--data", world["data"], "--split", split,
                                    "--out", tmp_path / "m", "--epochs", "1"))
    assert needle in line


@pytest.mark.parametrize("case", ["missing", "not-a-checkpoint", "no-stats", "unknown-key", "nan-stats",
                                  "nan-weights"])
def test_a_bad_checkpoint_is_one_line(capsys: pytest.CaptureFixture, world: dict, tmp_path: Path, case: str) -> None:
    import torch

    model = tmp_path / "model"
    model.mkdir()
    ck = torch.load(world["model"] / "best.pt", weights_only=True)
    if case == "not-a-checkpoint":
        (model / "best.pt").write_text("hello")
    elif case == "no-stats":
        torch.save({k: v for k, v in ck.items() if k != "stats"}, model / "best.pt")
    elif case == "unknown-key":
        torch.save({**ck, "config": {**ck["config"], "wings": 2}}, model / "best.pt")
    elif case.startswith("nan"):  # a policy that would act on NaN is refused, not run
        if case == "nan-stats":  # the normalisation's statistics, as training stores them (lists)
            stats = {**ck["stats"], "min": [float("nan")] * len(ck["stats"]["min"])}
            torch.save({**ck, "stats": stats}, model / "best.pt")
        else:
            ema = ck["ema"]
            name = next(k for k, v in ema.items() if torch.is_tensor(v) and v.is_floating_point())
            torch.save({**ck, "ema": {**ema, name: torch.full_like(ema[name], float("nan"))}}, model / "best.pt")
    line = one_line_error(run_stage(capsys, "inspect", "--model", model, "--data", world["data"], "--split",
                                    world["split"], "-o", tmp_path / "x.rrd"))
    assert "best.pt" in line
    if case.startswith("nan"):
        assert "non-finite values" in line


@pytest.mark.parametrize(("stage", "args", "needle"), [
    ("evaluate", ["--models", "m", "--steps", "0"], "out of range"),
    ("evaluate", ["--models", "m", "--steps", "-1"], "out of range"),
    ("evaluate", ["--models", "m", "--steps", "1000"], "out of range"),
    ("evaluate", ["--models", "m", "--repeats", "0"], "out of range"),
    ("evaluate", ["--models", "m", "--best-of", "-2"], "out of range"),
    ("evaluate", ["--models", "m", "--threads", "-1"], "out of range"),
    ("train", ["--model", "fm_cnn", "--lr", "-1"], "out of range"),
    ("train", ["--model", "fm_cnn", "--lr", "nan"], "not a finite number"),
    ("train", ["--model", "fm_cnn", "--image-size", "0"], "out of range"),
    ("train", ["--model", "fm_cnn", "--image-size", "-5"], "out of range"),
    ("train", ["--model", "fm_cnn", "--epochs", "x"], "not an integer"),
    ("record", ["--out", "o", "--camera-hz", "0"], "out of range"),
    ("record", ["--out", "o", "--camera-hz", "-1"], "out of range"),
    ("record", ["--out", "o", "--size", "100000"], "out of range"),
    ("replay", ["--models", "m", "--closed-loop", "-1"], "out of range"),
    ("replay", ["--models", "m", "--max-episodes", "0"], "out of range"),
    ("split", ["x.h5", "--test-fraction", "1.5"], "out of range"),
    ("ingest", ["b.mcap", "-o", "x.h5", "--waypoints", "1"], "out of range"),
    ("inspect", ["--model", "m", "--samples", "0"], "out of range"),
    ("train", ["--model", "fm_cnn", "--seed", str(2**70)], "out of range"),
    ("evaluate", ["--models", "m", "--fm-methods", "bogus"], "invalid choice: 'bogus'"),
    ("benchmark", ["--models", "m", "--seed", str(2**70)], "out of range"),
    ("benchmark", ["--models", "m", "--episodes", "1000000000"], "out of range"),
    ("benchmark", ["--models", "m", "--seed", str(2**32 - 5), "--episodes", "10"], "past the largest seed"),
    ("replay", ["--models", "m", "--scenes", "1000000000"], "out of range"),  # killed at 22 GB before
    ("doctor", ["x.h5", "--idle-s", "-1"], "out of range"),
    ("doctor", ["x.h5", "--idle-s", "nan"], "not a finite number"),
    ("doctor", ["x.h5", "--max-speed", "0"], "out of range"),
    ("doctor", ["x.h5", "--max-speed", "nan"], "not a finite number"),
    ("edit", ["x.h5", "-o", "y.h5", "--flags", "frozen camera"], "give --drop-flagged"),
    ("replay", ["--models", "m", "--until-decided"], "add --scenes N"),
    ("trials", ["t.csv", "--margin", "0.9"], "out of range"),
])
def test_bad_numbers_are_refused_at_the_parser(capsys: pytest.CaptureFixture, stage: str, args: list[str],
                                               needle: str) -> None:
    assert needle in one_line_error(run_stage(capsys, stage, *args))


def test_evaluate_failing_cleanly_leaves_no_journal(capsys: pytest.CaptureFixture, world: dict,
                                                    tmp_path: Path) -> None:
    """A model whose checkpoints are not checkpoints fails evaluate in one line, and its resume journal goes with
    it (it was left beside the metrics before)."""
    bad = tmp_path / "bad_model"
    bad.mkdir()
    for name in ("best.pt", "last.pt"):
        (bad / name).write_bytes(b"not a checkpoint")
    details = tmp_path / "d.json"
    line = one_line_error(run_stage(capsys, "evaluate", "--models", world["model"], bad, "--data", world["data"],
                                    "--split", world["split"], "--metrics", tmp_path / "e.json", "--details", details,
                                    "--plots", tmp_path / "p.csv", "--table", tmp_path / "t.md", "--steps", "1"))
    assert "bad_model" in line
    assert not list(tmp_path.glob(".*journal")) and not details.exists()


@pytest.mark.parametrize("loop", [[], ["--closed-loop", "8"]])
def test_replay_failing_cleanly_leaves_no_journal(capsys: pytest.CaptureFixture, world: dict, tmp_path: Path,
                                                  loop: list[str]) -> None:
    """A checkpoint that is not one: replay refuses it in one line, open or closed loop, and leaves no journal."""
    bad = tmp_path / "bad_model"
    bad.mkdir()
    for name in ("best.pt", "model.pt"):
        (bad / name).write_bytes(b"not a checkpoint")
    details = tmp_path / "d.json"
    line = one_line_error(run_stage(capsys, "replay", "--models", bad, "--data", world["data"], "--split",
                                    world["split"], "--metrics", tmp_path / "m.json", "--details", details,
                                    "--table", tmp_path / "t.md", *loop))
    assert "bad_model" in line and "not a loadable adlpipe checkpoint" in line
    assert not list(tmp_path.glob(".*journal")) and not details.exists()


def test_a_state_message_left_out_for_nan_is_not_stored_as_nan(tmp_path: Path) -> None:
    """A state topic whose message at the first frame held NaN (and was left out) leaves that frame without a
    state: the ingest says so in one line, naming the frame and why, instead of storing NaN (it did before)."""
    from adlpipe.bags.topics import TopicMap
    from adlpipe.sim.episode import record_demo
    from adlpipe.sim.recording import write_episode_bag

    st = record_demo("wipe the nose", np.random.default_rng(0), 32, 32, camera_hz=2.0)
    st.state_names = ["x", "y"]
    st.states = [(t, np.array([np.nan, 0.0]) if i == 0 else np.array([0.1 * i, 0.0]))
                 for i, (t, _, _) in enumerate(st.camera)]  # one state per frame, the first NaN
    bag = write_episode_bag(st, tmp_path / "nan_state.mcap", "mcap", "raw", "32FC1", 0,
                            TopicMap(state="/adl/state"))
    config = tmp_path / "topics.yaml"
    config.write_text("state: /adl/state\n")
    line = one_line_error(run_module("ingest", bag, "-o", tmp_path / "x.h5", "--size", "32", "--config", config))
    assert "frame 0 (0.00 s) has no state message" in line and "non-finite" in line
    assert not (tmp_path / "x.h5").exists()


def test_a_suggested_topic_map_left_unfilled_is_named(mcap_bags: list[Path], tmp_path: Path) -> None:
    """The quick start on a bag without a camera (../shared's public bags): ingest --suggest-config writes FILL_ME
    where it found nothing; ingesting with that map names the keys still to fill, not 'missing topic FILL_ME'."""
    config = tmp_path / "topics.yaml"
    config.write_text("image: FILL_ME\ncamera_info: FILL_ME\ntf: /tf\n")
    line = one_line_error(run_module("ingest", mcap_bags[0], "--config", config, "-o", tmp_path / "x.h5"))
    assert "image, camera_info still FILL_ME" in line and "ingest --list" in line


def test_doctor_verify_reads_a_folder_of_bags_and_refuses_a_device(world: dict, mcap_bags: list[Path]) -> None:
    """--verify with the folder record writes (its own --help's form) verifies; /dev/zero, which hashing never
    finishes, is one line at once (it hung before)."""
    proc = run_module("doctor", world["data"], "--verify", mcap_bags[0].parent, timeout=300)
    assert proc.returncode in (0, 1) and "episode(s) verified against their bags" in proc.stdout, proc.stderr
    assert "not a regular file" in one_line_error(run_module("doctor", world["data"], "--verify", "/dev/zero",
                                                             timeout=60))


def test_an_output_path_that_is_a_folder_keeps_every_old_output(capsys: pytest.CaptureFixture, world: dict,
                                                                tmp_path: Path) -> None:
    metrics = tmp_path / "e.json"
    metrics.write_text("old")
    (tmp_path / "table.md").mkdir()
    line = one_line_error(run_stage(capsys, "evaluate", "--models", world["model"], "--data", world["data"],
                                    "--split", world["split"], "--metrics", metrics, "--details", tmp_path / "d.json",
                                    "--plots", tmp_path / "p.csv", "--table", tmp_path / "table.md"))
    assert "table.md" in line and "folder" in line
    assert metrics.read_text() == "old" and not (tmp_path / "d.json").exists()


def test_training_stops_on_a_non_finite_loss_and_keeps_the_last_good_checkpoint(world: dict, tmp_path: Path) -> None:
    import torch

    from adlpipe.plumbing.errors import AdlError
    from adlpipe.policy.checkpoint import load_checkpoint, save_atomic

    out = tmp_path / "m"
    cfg = ModelConfig(model="bc_cnn", **TINY)
    train(world["data"], world["split"], out, cfg, epochs=3, batch_size=2, val_fraction=0, stop_after_epoch=1)
    ck = load_checkpoint(out / "last.pt")
    first = next(iter(ck["model"]))
    ck["model"][first] = torch.full_like(ck["model"][first], float("nan"))  # the run goes bad in epoch 2
    save_atomic(ck, out / "last.pt")
    before = (out / "last.pt").read_bytes()
    with pytest.raises(AdlError, match="diverged"):
        train(world["data"], world["split"], out, cfg, epochs=3, batch_size=2, val_fraction=0)
    assert (out / "last.pt").read_bytes() == before and not (out / "model.pt").exists()


def _can_unshare() -> bool:
    return shutil.which("unshare") is not None and subprocess.run(
        ["unshare", "-rm", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not _can_unshare(), reason="needs unshare for a private read-only mount")
@pytest.mark.parametrize("stage", ["record", "ingest", "split", "train", "evaluate", "replay", "inspect", "report"])
def test_a_read_only_output_is_one_line(world: dict, mcap_bags: list[Path], tmp_path: Path, stage: str) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    w = world
    args = {
        "record": ["--out", ro / "bags", "--episodes", 1, "--tasks", "wipe the nose", "--size", 32],
        "ingest": [mcap_bags[0], "-o", ro / "x.h5", "--size", 64],
        "split": [w["data"], "-o", ro / "s.json"],
        "train": ["--model", "fm_cnn", "--data", w["data"], "--split", w["split"], "--out", ro / "m", "--epochs", 1],
        "evaluate": ["--models", w["model"], "--data", w["data"], "--split", w["split"], "--metrics", ro / "e.json"],
        "replay": ["--models", w["model"], "--data", w["data"], "--split", w["split"], "--metrics", ro / "r.json"],
        "inspect": ["--model", w["model"], "--data", w["data"], "--split", w["split"], "-o", ro / "x.rrd"],
        "report": ["--eval", w["split"], "--replay", w["split"], "-o", ro / "r.md"],
    }[stage]
    cmd = " ".join(f"'{a}'" for a in [sys.executable, "-m", f"adlpipe.{stage}", *map(str, args)])
    proc = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o ro tmpfs '{ro}' && exec {cmd}"],
                          capture_output=True, text=True, cwd=REPO, timeout=300,
                          env={**os.environ, "MUJOCO_GL": "egl"})
    line = one_line_error(proc)
    assert "read-only" in line, line


def test_a_second_writer_of_one_output_is_refused_while_the_first_holds_it(mcap_bags: list[Path],
                                                                          tmp_path: Path) -> None:
    from adlpipe.plumbing.lock import exclusive

    out = tmp_path / "same.h5"
    with exclusive(out):  # as a running ingest would
        line = one_line_error(subprocess.run([sys.executable, "-m", "adlpipe.ingest", *map(str, mcap_bags), "-o",
                                              str(out), "--size", "64"], capture_output=True, text=True, cwd=REPO))
        assert f"in use by pid {os.getpid()}" in line and not out.exists()
        line = one_line_error(subprocess.run([sys.executable, "-m", "adlpipe.train", "--model", "fm_cnn", "--data",
                                              str(out), "--out", str(out)], capture_output=True, text=True, cwd=REPO))
        assert "in use by pid" in line or "no such dataset" in line or "is an input of this command" in line


def test_two_ingests_started_together_lose_nothing(mcap_bags: list[Path], tmp_path: Path) -> None:
    """Different bags into one file at once: each run either adds its bags or is refused as 'in use'; re-running the
    refused one, the file holds every episode."""
    out = tmp_path / "same.h5"
    halves = [mcap_bags[:2], mcap_bags[2:]]

    def start(bags: list[Path]) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "adlpipe.ingest", *map(str, bags), "-o", str(out), "--size",
                                 "64", "--workers", "1"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)

    procs = [start(h) for h in halves]
    for bags, proc in zip(halves, procs, strict=True):
        _, err = proc.communicate(timeout=300)
        if proc.returncode != 0:
            assert "in use by pid" in err, err
            assert start(bags).wait(timeout=300) == 0
    with h5py.File(out) as f:
        assert len(f["episodes"]) == len(mcap_bags)


@pytest.mark.parametrize("delay", [0.1, 0.6])
def test_ctrl_c_while_a_stage_starts_is_exit_130_and_one_line(delay: float) -> None:
    """While torch, cv2 and mujoco import (a second or more), Ctrl-C is one line and 130, like later."""
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "adlpipe.replay", "--models", "no-such-model"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and len(err.strip().splitlines()) == 1 and "interrupted" in err, err


@pytest.mark.parametrize(("workers", "delay"), [(2, 0.0), (2, 0.5), (2, 1.5), (1, 0.0), (1, 1.0)])
def test_ctrl_c_stops_an_ingest_and_keeps_the_old_file(mcap_bags: list[Path], tmp_path: Path, workers: int,
                                                       delay: float) -> None:
    """In a pool or in the ingesting process itself (--workers 1: 16 of 16 tries at 0-3 s stopped with 130 when
    measured), a Ctrl-C stops the ingest at once and leaves nothing of it."""
    import signal
    import time

    out = tmp_path / "x.h5"
    old = b"an older dataset stays byte for byte"
    out.write_bytes(old)
    bags = []
    for i in range(8):  # copies are distinct files to the pool; their episodes are the same
        for b in mcap_bags:
            c = tmp_path / f"{i}_{b.name}"
            shutil.copy(b, c)
            bags.append(c)
    out.unlink()
    proc = subprocess.Popen([sys.executable, "-m", "adlpipe.ingest", *map(str, bags), "-o", str(out), "--size", "64",
                             "--workers", str(workers)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    lock = tmp_path / ".x.h5.lock"  # the ingest holds its output's lock from the start of its work
    deadline = time.time() + 120
    while not lock.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    t0 = time.time()
    out_text, err = proc.communicate(timeout=60)
    if proc.returncode == 0 or "episode(s) added" in out_text:
        # it finished before the signal came (measured: on an idle machine the 24 bags take under 1.5 s, and a
        # signal during Python's own shutdown, after the dataset is committed, ends the process by SIGINT, -2):
        # nothing to check about stopping, but the dataset it reported is whole
        assert out.exists() and "Traceback" not in err
        return
    # 130 from the stage; about 1 run in 30 under load the process that printed its "interrupted" line still ends by
    # SIGINT (-2; the cause is not found): a shell reports both as 130, and the checks below hold for both
    assert proc.returncode in (130, -signal.SIGINT) and "interrupted" in err, (proc.returncode, err)
    assert time.time() - t0 < 10, err
    assert "Traceback" not in err and not out.exists(), err
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


@pytest.mark.parametrize("group", [True, False])
def test_ctrl_c_stops_a_recording_pool_at_once_and_records_no_job_that_had_not_started(tmp_path: Path,
                                                                                       group: bool) -> None:
    """record's pool of 2 workers, 20 jobs: Ctrl-C to the process group (a terminal) or to record alone (kill -INT)
    after its first bag. Before, the executor finished the jobs it had already handed to its workers (R5: record
    --world kitchen took 16-58 s to stop and wrote the bags of jobs that had not started); now the workers are
    stopped, what they were writing is removed, and the bags that were finished stay whole."""
    import signal
    import time

    out = tmp_path / "bags"
    proc = subprocess.Popen([sys.executable, "-m", "adlpipe.record", "--episodes", "2", "--size", "32",
                             "--camera-hz", "5", "--out", str(out), "--workers", "2"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.time() + 240
    while not list(out.glob("*.mcap")) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    finished = len(list(out.glob("*.mcap")))
    (os.killpg if group else os.kill)(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, (proc.returncode, err)
    bags = sorted(out.glob("*.mcap"))
    # at most one bag renamed into place between the count and the signal; before, kill -INT let the two running
    # jobs and the one queued behind them finish (3 more bags), and a Ctrl-C to the group let the queued one run
    assert finished <= len(bags) <= finished + 1, (finished, [b.name for b in bags])
    assert not [p for p in out.iterdir() if ".tmp" in p.name]
    proc = subprocess.run([sys.executable, "-m", "adlpipe.ingest", *map(str, bags), "-o", str(tmp_path / "a.h5"),
                           "--size", "32"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr  # every bag left is whole


@pytest.mark.skipif(not _can_unshare(), reason="needs unshare for a private small file system")
@pytest.mark.parametrize("stage", ["ingest", "ingest-while-writing", "train", "inspect", "inspect-dataset",
                                   "export"])
def test_a_full_disk_is_one_line_and_keeps_the_old_output(world: dict, mcap_bags: list[Path], tmp_path: Path,
                                                          stage: str) -> None:
    small = tmp_path / "small"
    small.mkdir()
    old = world["root"] / "old_small.h5"
    size_mb = 3
    if stage == "ingest-while-writing":
        # the space check passes (a 1 MB bag, 20 MB free) but its frames stored at 2048 px take about 28 MB: the
        # disk fills while the episode is written, in a pool worker
        old = tmp_path / "big" / "x.h5"
        old.parent.mkdir()
        subprocess.run([sys.executable, "-m", "adlpipe.ingest", str(mcap_bags[0]), "-o", str(old), "--size", "2048"],
                       cwd=REPO, check=True, capture_output=True)
        shards = old.with_suffix(".shards")
        size_mb = int(sum(p.stat().st_size for p in shards.rglob("*") if p.is_file()) / 2**20) + 20
        inner = (f"cp '{old}' '{small}/x.h5' && cp -r '{shards}' '{small}/x.shards' && '{sys.executable}' -m "
                 f"adlpipe.ingest '{mcap_bags[1]}' '{mcap_bags[2]}' -o '{small}/x.h5' --size 2048 --workers 2; rc=$?; "
                 f"ls '{small}/x.shards'; (exit $rc)")
        target = "x.h5"
    elif stage == "ingest":  # a dataset of one bag, to be extended by the other two on a nearly full disk
        subprocess.run([sys.executable, "-m", "adlpipe.ingest", str(mcap_bags[0]), "-o", str(old), "--size", "64"],
                       cwd=REPO, check=True, capture_output=True)
        shards = old.with_suffix(".shards")  # the index and its episode files: a whole dataset to append to
        inner = (f"cp '{old}' '{small}/x.h5' && cp -r '{shards}' '{small}/' && "
                 f"head -c $(( $(stat -f -c %a '{small}') * $(stat -f -c %S '{small}') "
                 f"- 50000 )) /dev/zero > '{small}/filler'; '{sys.executable}' -m adlpipe.ingest "
                 + " ".join(f"'{b}'" for b in mcap_bags) + f" -o '{small}/x.h5' --size 64")
        target = "x.h5"
    elif stage.startswith("inspect"):  # Rerun writes the file on its own thread: a full disk raised nothing there
        args = (["--dataset", "--data", str(world["data"])] if stage == "inspect-dataset" else
                ["--model", str(world["model"]), "--data", str(world["data"]), "--split", str(world["split"])])
        old = tmp_path / "old.rrd"
        subprocess.run([sys.executable, "-m", "adlpipe.inspect", *args, "-o", str(old)], cwd=REPO, check=True,
                       capture_output=True)
        inner = (f"cp '{old}' '{small}/x.rrd' && head -c $(( $(stat -f -c %a '{small}') * $(stat -f -c %S "
                 f"'{small}') - 20000 )) /dev/zero > '{small}/filler'; '{sys.executable}' -m adlpipe.inspect "
                 + " ".join(f"'{a}'" for a in args) + f" -o '{small}/x.rrd'")
        target = "x.rrd"
    elif stage == "export":  # the disk fills while the video and the data files are written (pyarrow's writer
        # printed an "Exception ignored" trace from its finaliser, and the error named the hidden temp folder)
        inner = (f"head -c $(( $(stat -f -c %a '{small}') * $(stat -f -c %S '{small}') - 60000 )) /dev/zero > "
                 f"'{small}/filler'; '{sys.executable}' -m adlpipe.export --format lerobot '{world['data']}' "
                 f"'{small}/out'")
        target = None
    else:
        inner = (f"head -c $(( $(stat -f -c %a '{small}') * $(stat -f -c %S '{small}') - 20000 )) /dev/zero > "
                 f"'{small}/filler'; '{sys.executable}' -m adlpipe.train --model fm_cnn --data '{world['data']}' "
                 f"--split '{world['split']}' --out '{small}/m' --epochs 1 --image-size 32")
        target = None
    script = (f"mount -t tmpfs -o size={size_mb}m tmpfs '{small}' && {inner}; rc=$?; "
              f"ls -a '{small}' '{small}/m' 2>/dev/null; cmp '{small}/{target}' '{old}' 2>/dev/null && echo SAME; "
              "exit $rc")
    proc = subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, cwd=REPO,
                          timeout=300)
    line = one_line_error(proc)
    assert "no space left on device writing" in line, line
    assert ".tmp" not in proc.stdout and ".tmp" not in line
    if stage == "export":
        assert "out" not in proc.stdout.split()  # nothing at OUT, and nothing half-written beside it
    if target:
        assert "SAME" in proc.stdout
    if stage == "ingest-while-writing":  # only the old run's folder: the new run's files went with it
        assert proc.stdout.split()[0].startswith("run-") and ".run-" not in proc.stdout


def test_a_jpeg_with_its_frame_header_past_64_kib_decodes() -> None:
    """Cameras that write large EXIF/ICC segments put the frame header far into the file."""
    import cv2

    from adlpipe.bags.images import decode_compressed

    img = np.zeros((24, 40, 3), np.uint8)
    img[:, :20] = (200, 30, 10)
    ok, enc = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    assert ok
    jpeg = enc.tobytes()
    app = b"\xff\xe1" + (65000).to_bytes(2, "big") + b"\0" * 64998  # three 65 kB metadata segments
    big = jpeg[:2] + app * 3 + jpeg[2:]
    msg = type("CompressedImage", (), {"data": big, "format": "jpeg"})()
    out = decode_compressed(msg, "cam")
    assert out.shape == (24, 40, 3) and abs(int(out[5, 5, 0]) - 200) < 20


def _edited_schema_bag(path: Path, edit: str) -> Path:
    """An MCAP written with mcap_ros2's writer whose message definitions for one type were edited (a field gone)."""
    from mcap_ros2.writer import Writer

    from adlpipe.bags.messages import typestore

    store = typestore(2)
    defs = {t: store.generate_msgdef(t, ros_version=2)[0] for t in
            ("sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "tf2_msgs/msg/TFMessage")}
    stamp = {"sec": 1, "nanosec": 0}
    header = {"stamp": stamp, "frame_id": "cam"}
    image = {"header": header, "height": 2, "width": 2, "encoding": "rgb8", "is_bigendian": 0, "step": 6,
             "data": bytes(12)}
    info = {"header": header, "height": 2, "width": 2, "distortion_model": "", "d": [], "k": [1.0, 0, 0.5, 0, 1, 0.5,
            0, 0, 1], "r": [0.0] * 9, "p": [0.0] * 12, "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}
    tf = {"transforms": [{"header": {"stamp": stamp, "frame_id": "base_link"}, "child_frame_id": "ee_link",
                          "transform": {"translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                                        "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}]}
    garbled = edit == "garbled TFMessage definition"
    if edit == "TFMessage without transforms":
        defs["tf2_msgs/msg/TFMessage"], tf = "int32 count", {"count": 1}
    elif edit == "CameraInfo without k":
        d = defs["sensor_msgs/msg/CameraInfo"]
        defs["sensor_msgs/msg/CameraInfo"] = d.replace("float64[9]  k\n", "").replace("float64[9] k\n", "")
        assert defs["sensor_msgs/msg/CameraInfo"] != d
        info.pop("k")
    elif edit == "Image without header":
        d = defs["sensor_msgs/msg/Image"]
        defs["sensor_msgs/msg/Image"] = d.replace("std_msgs/Header header", "", 1)
        assert defs["sensor_msgs/msg/Image"] != d
        image.pop("header")
    with open(path, "wb") as f:
        w = Writer(f)
        schemas = {t: w.register_msgdef(t, text) for t, text in defs.items()}
        if garbled:  # a definition the writer itself would refuse to parse: written as a raw MCAP schema record
            raw = w._writer  # noqa: SLF001 - the plain mcap writer under mcap_ros2's
            sid = raw.register_schema("tf2_msgs/msg/TFMessage", "ros2msg", b"float64 = oops ===\nint32[ x")
            cid = raw.register_channel("/tf", "cdr", sid)
            raw.add_message(cid, 10**9, b"\x00\x01\x00\x00" + bytes(8), 10**9)
        else:
            w.write_message("/tf", schemas["tf2_msgs/msg/TFMessage"], tf, log_time=10**9, publish_time=10**9)
        w.write_message("/camera/color/camera_info", schemas["sensor_msgs/msg/CameraInfo"], info, log_time=10**9,
                        publish_time=10**9)
        w.write_message("/camera/color/image_raw", schemas["sensor_msgs/msg/Image"], image, log_time=10**9,
                        publish_time=10**9)
        w.finish()
    return path


@pytest.mark.parametrize(("edit", "topic"), [("TFMessage without transforms", "/tf"),
                                             ("garbled TFMessage definition", "/tf"),
                                             ("CameraInfo without k", "/camera/color/camera_info"),
                                             ("Image without header", "/camera/color/image_raw")])
def test_messages_with_edited_definitions_are_one_line_naming_topic_and_field(tmp_path: Path, edit: str,
                                                                              topic: str) -> None:
    bag = _edited_schema_bag(tmp_path / "edited.mcap", edit)
    line = one_line_error(subprocess.run([sys.executable, "-m", "adlpipe.ingest", str(bag), "-o",
                                          str(tmp_path / "x.h5"), "--task", "t"], capture_output=True, text=True,
                                         cwd=REPO))
    assert topic in line, line
    assert {"TFMessage without transforms": "transforms", "CameraInfo without k": "k",
            "Image without header": "header", "garbled TFMessage definition": "does not decode"}[edit] in line, line


@pytest.mark.parametrize("where", ["frame", "joint"])
def test_a_nul_in_a_name_is_one_line(tmp_path: Path, where: str) -> None:
    from layouts import ROBOTS, Layout, topic_map, write_layout_bag

    robot = dict(ROBOTS["ur"])
    if where == "frame":
        robot["static"] = [("flange", 0.0), ("tool\x000", 0.0)]
    ROBOTS["nul"] = robot
    try:
        lay = Layout(robot="nul")
        bag, _t, _p = write_layout_bag(tmp_path / "n.mcap", lay)
        m = topic_map(lay)
    finally:
        del ROBOTS["nul"]
    if where == "joint":  # rewrite the joint names with a NUL through the real writer
        from adlpipe.bags import messages as M
        from adlpipe.bags.writer import BagWriter

        w = BagWriter(tmp_path / "j.mcap", "mcap")
        for topic, msgtype, t, msg in _copy_messages(bag):
            if msgtype == M.JOINT_STATE:
                msg.name[0] = "joint\x001"
            w.write(topic, msgtype, t, msg)
        bag = w.close()
    cfg = tmp_path / "m.yaml"
    import yaml

    m["ee_frame"] = "flange"
    cfg.write_text(yaml.safe_dump(m))
    line = one_line_error(subprocess.run([sys.executable, "-m", "adlpipe.ingest", str(bag), "-o",
                                          str(tmp_path / "x.h5"), "--config", str(cfg), "--size", "32"],
                                         capture_output=True, text=True, cwd=REPO))
    assert "control characters" in line and where in line


def _copy_messages(bag: Path):  # noqa: ANN202
    from rosbags.highlevel import AnyReader

    from adlpipe.bags.messages import typestore

    with AnyReader([bag], default_typestore=typestore(2)) as r:
        for c, t, raw in r.messages():
            yield c.topic, c.msgtype, t, r.deserialize(raw, c.msgtype)


def test_the_horizon_comes_from_the_data(capsys: pytest.CaptureFixture, mcap_bags: list[Path],
                                         tmp_path: Path) -> None:
    """--waypoints 16 trains and evaluates a 16-waypoint model; 6 (not a multiple of 4 for the U-Net) is refused."""
    for n in (16, 6):
        data = tmp_path / f"w{n}.h5"
        assert run_stage(capsys, "ingest", *mcap_bags, "-o", data, "--size", "32", "--waypoints", n).returncode == 0
        with h5py.File(data) as f:
            names = sorted(f["episodes"])
        split = tmp_path / f"s{n}.json"
        split.write_text(json.dumps({"train": names[:2], "test": names[2:]}))
        args = ["--model", "fm_cnn", "--data", data, "--split", split, "--out", tmp_path / f"m{n}", "--epochs", 1,
                "--image-size", 32, "--val-fraction", 0]
        if n == 6:
            assert "multiple of 4" in one_line_error(run_stage(capsys, "train", *args))
            continue
        assert run_stage(capsys, "train", *args).returncode == 0
        proc = run_stage(capsys, "evaluate", "--models", tmp_path / f"m{n}", "--data", data, "--split", split,
                         "--steps", 1, 2,
                         "--repeats", 1, "--best-of", 1, "--metrics", tmp_path / "e.json", "--details",
                         tmp_path / "d.json", "--plots", tmp_path / "p.csv", "--table", tmp_path / "t.md")
        assert proc.returncode == 0, proc.stderr
        d = json.loads((tmp_path / "d.json").read_text())
        assert d["models"][f"m{n}"]["best"]["euler/1"]["px"] > 0
        # the same episodes at 32 waypoints: the 16-waypoint model is not scored on them (one line, no output)
        data32 = tmp_path / "w32.h5"
        assert run_stage(capsys, "ingest", *mcap_bags, "-o", data32, "--size", "32").returncode == 0
        (tmp_path / "d.json").unlink()
        line = one_line_error(run_stage(capsys, "evaluate", "--models", tmp_path / "m16", "--data", data32, "--split",
                                        split, "--steps", 1, "--repeats", 1, "--best-of", 1, "--metrics",
                                        tmp_path / "e.json", "--details", tmp_path / "d.json", "--plots",
                                        tmp_path / "p.csv", "--table", tmp_path / "t.md"))
        assert "predicts 16 waypoints" in line and "holds 32" in line and not (tmp_path / "d.json").exists()


@pytest.mark.parametrize("bad", ["binary-eval", "text-eval", "bad-log"])
def test_report_on_bad_input_is_one_line_and_writes_nothing(capsys: pytest.CaptureFixture, tmp_path: Path,
                                                           bad: str) -> None:
    ev, rp, logs = tmp_path / "eval.json", tmp_path / "replay.json", tmp_path / "train"
    logs.mkdir()
    ev.write_text(json.dumps({"n_test": 1, "models": {"fm_cnn": {"best": {}, "last": {}}}, "training": {}}))
    rp.write_text(json.dumps({"episodes": 1, "success": {}}))
    (logs / "fm_cnn.csv").write_text("epoch,step,train_loss,test_loss,val_px\n1,5,0.5,0.4,3.0\n")
    if bad == "binary-eval":
        ev.write_bytes(bytes(range(256)) * 4)
    elif bad == "text-eval":
        ev.write_text("[1, 2")
    else:
        (logs / "fm_cnn.csv").write_bytes(b"\xff\xfe\x00garbage")
    out = tmp_path / "reports" / "report.md"
    line = one_line_error(run_stage(capsys, "report", "--eval", ev, "--replay", rp, "--train-logs", logs, "-o", out))
    assert str(ev if bad != "bad-log" else logs / "fm_cnn.csv") in line
    assert not (tmp_path / "reports").exists()  # no figure left behind


@pytest.mark.parametrize(("episodes", "split", "needle"), [
    (["²"], None, "no episode '²'"),  # a non-ASCII digit is not an index
    (["abc"], None, "no episode 'abc'"),
    (["0"], {"train": [], "test": ["ghost-0000"]}, "names episode 'ghost-0000', which"),
])
def test_inspect_episode_choices_are_one_line(capsys: pytest.CaptureFixture, world: dict, tmp_path: Path,
                                              episodes: list[str], split: dict | None, needle: str) -> None:
    split_file = world["split"]
    if split is not None:
        split_file = tmp_path / "split.json"
        split_file.write_text(json.dumps(split))
    line = one_line_error(run_stage(capsys, "inspect", "--model", world["model"], "--data", world["data"], "--split",
                                    split_file, "--episodes", *episodes, "-o", tmp_path / "x.rrd"))
    assert needle in line and not (tmp_path / "x.rrd").exists()


@pytest.mark.parametrize("damage", ["truncated", "emptied", "text"])
def test_a_damaged_episode_file_is_one_line_naming_episode_and_file(capsys: pytest.CaptureFixture, world: dict,
                                                                    mcap_bags: list[Path], tmp_path: Path,
                                                                    damage: str) -> None:
    from adlpipe.dataset import schema

    data = copy_dataset(world["data"], tmp_path / "adl.h5")
    with h5py.File(data) as f:
        name = sorted(f["episodes"])[1]
        path = schema.episode_path(data, f, name)
    raw = path.read_bytes()
    path.write_bytes({"truncated": raw[:5000], "emptied": b"", "text": b"not hdf5\n"}[damage])
    for stage, args in (("split", [data, "-o", tmp_path / "s.json"]),
                        ("export", [data, tmp_path / "out"])):
        line = one_line_error(run_stage(capsys, stage, *args))
        assert name in line and str(path) in line and "cannot be read" in line, (stage, line)
    assert not (tmp_path / "s.json").exists() and not (tmp_path / "out").exists()
    # --skip-bad: split and export go on without it, naming it; every later stage reads what the split names
    with h5py.File(data) as f:
        names = sorted(f["episodes"])
    proc = run_stage(capsys, "split", data, "-o", tmp_path / "s.json", "--skip-bad")
    assert proc.returncode == 0, proc.stderr
    assert f"skipped bad episode: {data}: episode {name}: its file" in proc.stderr
    split = json.loads((tmp_path / "s.json").read_text())
    assert sorted(split["train"] + split["test"]) == [n for n in names if n != name] and len(split["skipped"]) == 1
    proc = run_stage(capsys, "export", data, tmp_path / "out", "--skip-bad")
    assert proc.returncode == 0 and f"episode {name}" in proc.stderr, proc.stderr
    assert f"{len(names) - 1} episode(s)" in proc.stdout
    before = data.read_bytes()  # an append refuses to build on it and changes nothing
    line = one_line_error(run_stage(capsys, "ingest", mcap_bags[0], "-o", data, "--size", "64"))
    assert line.startswith("adlpipe.ingest: error: cannot append to a damaged dataset") and name in line
    assert data.read_bytes() == before
