"""Closed-loop ADL execution: the commanded action stream, the windows learnt from it, and the executor fed the
demonstrations' own plans in exactly the policy's output format (normalised offsets from the anchor)."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import run_module

from adlpipe.dataset import schema
from adlpipe.dataset.loader import STATE_DIM, WindowDataset, Windows, compute_window_stats


def test_the_recorder_publishes_the_arms_command_which_the_measured_tcp_trails(ingested: Path) -> None:
    with h5py.File(ingested) as f:
        for name in schema.episode_names(f):
            fr = f[schema.EPISODES][name]["frames"]
            assert list(fr["action"].attrs["names"]) == ["tcp_x", "tcp_y", "tcp_z", "gripper"]
            cmd, ee = fr["action"][:, :3], fr["ee_pos"][()]
            lag = np.linalg.norm(cmd - ee, axis=1)
            assert lag[0] < 1e-3  # at rest at home: command and measurement agree
            assert 0.005 < lag.mean() < 0.04, lag.mean()  # moving: the arm trails its command (~80 ms)
            assert set(np.round(fr["action"][:, 3].astype(float), 3)) <= {0.0, 0.04}  # gripper command: open or shut


def test_windows_learn_the_command_relative_to_the_command_now(ingested: Path) -> None:
    with h5py.File(ingested) as f:
        names = schema.episode_names(f)
        g = f[schema.EPISODES][names[0]]
        t = g["frames/t"][()]
        ct, cmd = g["frames/action_stream_t"][()], g["frames/action_stream"][:, :3]  # the command at its own rate
        grip = g["frames/gripper"][()]
        assert np.median(np.diff(ct)) == pytest.approx(0.01, abs=1e-3)  # 100 Hz, between the 5 Hz frames
    w = Windows(n_obs=2, horizon=8, rate_hz=10.0, target="command")
    stats = compute_window_stats(ingested, names, w)
    ds = WindowDataset(ingested, names, stats, 32, w)
    k = 4
    _, state, target = ds.raw(0, k)
    assert state.shape == (2, STATE_DIM) and state[-1, 3] == pytest.approx(grip[k])
    now = np.stack([np.interp(t[k], ct, cmd[:, d]) for d in range(3)])
    want = np.stack([np.interp(t[k] + 0.1, ct, cmd[:, d]) for d in range(3)]) - now
    np.testing.assert_allclose(target[0, 2:], want, atol=1e-5)
    measured = WindowDataset(ingested, names, compute_window_stats(ingested, names, Windows(2, 8, 10.0, "ee")), 32,
                             Windows(2, 8, 10.0, "ee"))
    assert not np.allclose(measured.raw(0, k)[2], target, atol=1e-3)  # the other anchor is another target


def test_oracle_plans_in_the_policys_format_solve_the_scenes_at_every_ta(ingested: Path, closed_loop_model,
                                                                         tmp_path: Path) -> None:
    """The demonstrations' own future commands, normalised with the model's statistics and taken through the
    replay's prediction path, anchored at the last command: every scene solved at Ta 4, 8 and 16. The same plans
    anchored at the lagging measured tcp (the earlier format) lose the lag at every re-plan and fail at Ta 4."""
    split, model = closed_loop_model
    details = tmp_path / "d.json"
    run_module("replay", "--models", model, "--closed-loop", "4", "8", "16", "--oracle", "command", "ee",
               "--data", ingested, "--split", split, "--metrics", tmp_path / "m.json", "--details", details,
               "--table", tmp_path / "t.md", "--workers", "2", check=True)
    success = json.loads(details.read_text())["success"]
    for ta in (4, 8, 16):
        assert success[f"oracle-command/Ta-{ta}"]["overall"] >= 0.9, success
        assert success[f"oracle-command/Ta-{ta}"]["n"] == 3
    assert success["oracle-ee/Ta-4"]["overall"] < success["oracle-command/Ta-4"]["overall"]
    table = (tmp_path / "t.md").read_text()
    assert "## Where the failed rollouts fail" in table and "| oracle-ee/Ta-4 |" in table
    assert "| oracle-command/Ta-4 | 100 [44, 100] | 3 |" in table  # the rate, Wilson's interval and n


@pytest.mark.parametrize("moving", [False, True], ids=["still", "moving-person"])
def test_closed_loop_replays_fresh_scenes_with_the_oracle_at_every_ta(ingested: Path, closed_loop_model,
                                                                      tmp_path: Path, moving: bool) -> None:
    """Closed loop on fresh seeded scenes, rendered live as from a recorded one: the oracle's plans (the fresh
    scene's own demonstration in the model's format) solve every scene at Ta 4, 8 and 16, with the person still and
    with the person moving (the demonstrator tracked them); the policy runs on the same scenes, paired by name with
    an open-loop replay of them."""
    split, model = closed_loop_model
    common = ["--data", ingested, "--split", split, "--scenes", "1", "--workers", "2",
              *(["--moving-person"] if moving else [])]
    run_module("replay", "--models", model, "--closed-loop", "4", "8", "16", "--oracle", "command", "--fm-steps", "1",
               *common,
               "--metrics", tmp_path / "m.json", "--details", tmp_path / "d.json", "--table", tmp_path / "t.md",
               check=True)
    details = json.loads((tmp_path / "d.json").read_text())
    assert details["scenes"] == {"kind": "fresh", "per_task": 1, "seed": 0, "moving_person": moving}
    names = set(details["tasks"])
    assert len(names) == 3 and all(n.startswith("fresh/") for n in names)
    for ta in (4, 8, 16):
        assert details["success"][f"oracle-command/Ta-{ta}"]["overall"] == 1.0, details["success"]
    policy = {label for label in details["per_episode"] if not label.startswith("oracle")}
    assert policy == {"fm/euler-1/Ta-4", "fm/euler-1/Ta-8", "fm/euler-1/Ta-16"}
    assert all(set(details["per_episode"][label]) == names for label in policy)
    run_module("replay", *common, "--metrics", tmp_path / "mo.json", "--details", tmp_path / "do.json",
               "--table", tmp_path / "to.md", check=True)
    assert set(json.loads((tmp_path / "do.json").read_text())["tasks"]) == names  # open loop: the same scenes


def test_temporal_ensembling_runs_the_oracle_and_the_policy_at_every_waypoint(ingested: Path, closed_loop_model,
                                                                              tmp_path: Path) -> None:
    """ACT's temporal ensembling in the executor: a plan at every waypoint, the executed waypoint the weighted mean
    of every plan's waypoint for that step. The oracle's plans all agree, so their mean is the demonstration: it
    solves every scene as at Ta 4; the policy runs one plan per waypoint (its per-re-plan diagnostics count them)."""
    split, model = closed_loop_model
    run_module("replay", "--models", model, "--closed-loop", "1", "--temporal-ensemble", "0.01", "--oracle",
               "command", "--fm-steps", "1", "--data", ingested, "--split", split, "--workers", "2",
               "--metrics", tmp_path / "m.json", "--details", tmp_path / "d.json", "--table", tmp_path / "t.md",
               check=True)
    details = json.loads((tmp_path / "d.json").read_text())
    assert details["success"]["oracle-command/Ta-1-ensemble"]["overall"] >= 0.9, details["success"]
    diag = details["diagnostics"]["fm/euler-1/Ta-1-ensemble"]
    assert all(d["replans"] >= 20 for d in diag.values()), diag  # about 10 per second of each demonstration
    bad = run_module("replay", "--models", model, "--closed-loop", "4", "--temporal-ensemble", "0.01",
                     "--data", ingested, "--split", split)
    assert "use it with --closed-loop 1" in bad.stderr


def test_ctrl_c_stops_a_replay_of_fresh_scenes_at_once(ingested: Path, closed_loop_model, tmp_path: Path) -> None:
    """SIGINT to replay (to the process group, as a terminal's Ctrl-C, or to replay alone, as a supervisor sends it)
    while fresh scenes are drawn: replay stops within seconds (its pools terminate their workers), exit 130."""
    import os
    import signal
    import subprocess
    import sys
    import time

    split, model = closed_loop_model
    cmd = [sys.executable, "-m", "adlpipe.replay", "--models", str(model), "--closed-loop", "8", "--fm-steps", "1",
           "--scenes", "30", "--data", str(ingested), "--split", str(split), "--workers", "2",
           "--metrics", str(tmp_path / "m.json"), "--details", str(tmp_path / "d.json"), "--table",
           str(tmp_path / "t.md")]
    for group in (False, True):  # 4 s in: while drawing the 90 scenes
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)
        time.sleep(4.0)
        (os.killpg if group else os.kill)(proc.pid, signal.SIGINT)
        t0 = time.monotonic()
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - t0
        if proc.returncode == 0:
            continue  # it had finished
        assert proc.returncode == 130 and "Traceback" not in err, err
        assert took < 30.0, f"{took:.1f} s to stop after Ctrl-C"
        assert not (tmp_path / "d.json").exists()
