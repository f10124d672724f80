"""Demonstrations with recoveries (record --recoveries, train --target recovery): the demonstrator is disturbed
off its path and returns, in the scene the undisturbed recorder keeps; the labels are its plans back, never the
disturbance."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import one_line_error, run_module

from adlpipe.dataset import schema
from adlpipe.dataset.loader import WindowDataset, Windows, command_series, compute_window_stats, reference_series
from adlpipe.evaluation.recoveries import recording_disturbances, recording_line
from adlpipe.geometry.recovery import RETURN_S, recovering_plan
from adlpipe.sim.disturbances import Disturbance, disturbed_path, draw_disturbances

TASK = "put on the hat"  # the longest demonstration (5.6 s): room for several disturbances


def straight(t: float) -> np.ndarray:
    return np.array([0.3 * t, 0.0, 0.5])  # the demonstrator's 0.3 m/s along x


def test_a_disturbance_leaves_the_path_and_the_return_is_the_plan_from_anywhere_on_it() -> None:
    push = Disturbance(0.5, 0.7, np.array([0.0, 0.04, 0.0]))
    stall = Disturbance(0.7 + RETURN_S + 0.3, 0.7 + RETURN_S + 0.6)
    cmd = disturbed_path(straight, [push, stall])
    assert np.allclose(cmd(0.4), straight(0.4))  # before any disturbance: the path itself
    assert np.allclose(cmd(0.7) - straight(0.7), [0, 0.04, 0])  # the push's full offset at its end
    assert np.linalg.norm(cmd(0.7 + RETURN_S) - straight(0.7 + RETURN_S)) < 0.04 * 0.06  # 95 % back
    held = cmd(stall.t1 - 1e-6)
    assert np.allclose(held, cmd(stall.t0), atol=1e-6)  # a stall holds the command where it was
    assert np.linalg.norm(held - straight(stall.t1)) > 0.08  # 0.3 s behind at 0.3 m/s
    # from any command on the way back, the demonstrator's plan is the rest of that way back
    ref_t = np.linspace(0, 5, 501)
    ref_p = np.stack([straight(t) for t in ref_t])
    for t_k in (stall.t1, stall.t1 + 0.13, stall.t1 + 0.4):
        future = t_k + np.arange(1, 9)[None] / 10
        plan = recovering_plan(np.array([t_k]), cmd(t_k)[None], ref_t, ref_p, future)[0]
        np.testing.assert_allclose(plan, np.stack([cmd(t) for t in future[0]]), atol=1e-9)


def test_disturbances_are_seeded_and_over_before_the_end() -> None:
    a = draw_disturbances(np.random.default_rng(3), 5.6)
    b = draw_disturbances(np.random.default_rng(3), 5.6)
    assert [(e.t0, e.t1) for e in a] == [(e.t0, e.t1) for e in b] and len(a) >= 1
    assert all(e.t1 + RETURN_S <= 5.6 - 0.2 for e in a)
    assert all(later.t0 >= earlier.t1 + RETURN_S for earlier, later in zip(a, a[1:], strict=False))
    assert draw_disturbances(np.random.default_rng(3), 0.9) == []  # no room: an undisturbed demonstration


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the scene's undisturbed recording, its recording with recoveries), each ingested."""
    root = tmp_path_factory.mktemp("recoveries")
    out = []
    for name, extra in (("clean", []), ("recoveries", ["--recoveries"])):
        run_module("record", "--episodes", "1", "--tasks", TASK, "--size", "32", "--camera-hz", "10",
                   "--out", root / name, *extra, check=True)
        run_module("ingest", *sorted((root / name).glob("*.mcap")), "-o", root / f"{name}.h5", "--size", "32",
                   check=True)
        out.append(root / f"{name}.h5")
    return out[0], out[1]


def only_episode(data: Path) -> tuple[str, h5py.Group, h5py.File]:
    f = h5py.File(data)
    name = schema.episode_names(f)[0]
    return name, f[schema.EPISODES][name], f


def test_the_disturbed_demonstrator_records_its_reference_in_the_undisturbed_scene(recorded) -> None:
    clean, disturbed = recorded
    _, gc, fc = only_episode(clean)
    name, gd, fd = only_episode(disturbed)
    with fc, fd:
        assert "reference_stream" not in gc["frames"] and "reference_stream" in gd["frames"]
        np.testing.assert_allclose(gd["objects"][()], gc["objects"][()])  # the same scene, object for object
        ct, cmd = command_series(gd, name)
        rt, ref = reference_series(gd, name)
        _, clean_cmd = command_series(gc, name)
        off = np.linalg.norm(cmd - np.stack([np.interp(ct, rt, ref[:, d]) for d in range(3)], 1), axis=1)
        assert off.max() > 0.02  # pushed or held at least 2 cm off its path
        assert off[-1] < 0.003  # and back on it at the end
        n = min(len(ref), len(clean_cmd))
        assert np.abs(ref[:n] - clean_cmd[:n]).max() < 0.003  # the reference is the undisturbed demonstrator's path


def test_recovery_labels_never_show_the_disturbance(recorded) -> None:
    _, disturbed = recorded
    name, g, f = only_episode(disturbed)
    with f:
        t = g["frames/t"][()]
        ct, cmd = command_series(g, name)
        rt, ref = reference_series(g, name)
    command, recovery = Windows(2, 16, 10.0, "command"), Windows(2, 16, 10.0, "recovery")
    stats = compute_window_stats(disturbed, [name], command)
    labels = {w.target: WindowDataset(disturbed, [name], stats, 32, w) for w in (command, recovery)}
    gap = []
    for k in range(labels["command"].lengths[0]):
        a, b = labels["command"].raw(0, k)[2][:, 2:], labels["recovery"].raw(0, k)[2][:, 2:]
        gap.append(np.abs(a - b).max())
        # every recovery label ends on the reference path (16 waypoints: 1.6 s, past the 0.9 s return)
        end = np.stack([np.interp(t[k], ct, cmd[:, d]) for d in range(3)]) + b[-1]  # the anchor plus the offset
        ref_end = np.stack([np.interp(t[k] + 1.6, rt, ref[:, d]) for d in range(3)])
        assert np.linalg.norm(end - ref_end) < 0.004, k
    gap = np.array(gap)
    assert gap.max() > 0.02  # the command's own future shows a disturbance in some windows
    assert (gap < 0.003).sum() >= len(gap) // 4  # where none lies ahead, both labels are the same plan


def test_the_recordings_disturbances_are_measured_from_its_streams(recorded) -> None:
    clean, disturbed = recorded
    names = {}
    for data in recorded:
        with h5py.File(data) as f:
            names[data] = schema.episode_names(f)
    quiet = recording_disturbances(clean, names[clean])  # no reference stream: its own command is its path
    assert quiet["disturbed"] == 0 and quiet["largest_offset_m"] == [0.0, 0.0, 0.0] and quiet["samples_off"] == 0
    got = recording_disturbances(disturbed, names[disturbed])
    assert got["episodes"] == 1 and got["disturbed"] == 1 and got["largest_offset_m"][2] > 0.02
    assert 0 < got["samples_off"] < 0.6
    assert "1 of 1 demonstrations pushed more than 1 cm off their path" in recording_line(got)


def test_train_target_recovery_needs_a_reference_stream(recorded, tmp_path: Path) -> None:
    clean, disturbed = recorded
    for data in (clean, disturbed):
        with h5py.File(data) as f:
            names = schema.episode_names(f)
        split = tmp_path / f"{data.stem}.json"
        split.write_text(json.dumps({"train": names, "test": [], "seed": 0, "test_fraction": 0.0}))
        args = ["--model", "bc_cnn", "--closed-loop", "--target", "recovery", "--data", data, "--split", split,
                "--out", tmp_path / data.stem, "--epochs", "1", "--batch-size", "2", "--val-fraction", "0"]
        proc = run_module("train", *args)
        if data == clean:
            assert "no training episode has a reference stream" in one_line_error(proc)
        else:
            assert proc.returncode == 0, proc.stderr


def test_the_recoveries_table_pairs_each_policy_on_the_same_scenes() -> None:
    from adlpipe.evaluation.recoveries import recoveries_lines

    names = [f"fresh/t/{i}" for i in range(10)]
    diag = {n: {"replans": 4, "replans_off_path": 1 if i < 5 else 3, "peak_force_n": 25.0 if i == 0 else 5.0}
            for i, n in enumerate(names)}
    path = {"per_episode": {"fm_cnn/euler-1/Ta-16": {n: i < 2 for i, n in enumerate(names)},
                            "oracle-command/Ta-16": dict.fromkeys(names, True)},
            "diagnostics": {"fm_cnn/euler-1/Ta-16": diag}, "training": {"fm_cnn": {"converged": False}}}
    rec = {"per_episode": {"fm_cnn/euler-1/Ta-16": {n: 1 <= i < 7 for i, n in enumerate(names)},
                           "oracle-command/Ta-16": dict.fromkeys(names, True)},
           "diagnostics": {"fm_cnn/euler-1/Ta-16": {n: {**d, "replans_off_path": 1} for n, d in diag.items()}}}
    open_loop = {"per_episode": {"fm_cnn/euler-1": {n: i < 5 for i, n in enumerate(names)}}}
    lines = recoveries_lines([("still", path, rec, open_loop)])
    assert len(lines) == 3  # the oracle is the executor's ceiling, not a trained policy: no row
    cells = [c.strip() for c in lines[2].split("|")[1:-1]]
    assert cells[:3] == ["fm_cnn/euler-1", "still", "16"]
    assert cells[3].startswith("20 [") and cells[4].startswith("60 [")
    assert cells[5].startswith("+40.0 points (5 : 1 discordant scenes")  # scenes 2-6 gained, scene 0 lost
    assert cells[6].startswith("50 [") and cells[7].startswith("+10.0 points (2 : 1 discordant")
    assert cells[8] == "50 % / 25 %" and cells[9] == "10.0 % / 10.0 %"
    assert cells[10] == "no / -"  # the path-trained model did not converge; the other's training is not recorded
