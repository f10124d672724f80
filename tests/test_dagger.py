"""DAgger and HG-DAgger (adlpipe.sim.dagger, adlpipe rollout): a closed-loop policy rolled out in the MuJoCo world,
every re-plan labelled by the expert and written as a bag; the operator who takes over off the path; the
intervention flag from a bag into HDF5, training windows and a LeRobot export; warm starts and extended splits."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import one_line_error, run_module

from adlpipe.bags.reader import BagSource
from adlpipe.dataset import schema
from adlpipe.dataset.loader import (
    WindowDataset,
    Windows,
    command_series,
    expert_reference,
    relative_waypoints,
)
from adlpipe.sim.dagger import Expert, Operator, OperatorRule
from adlpipe.sim.recording import EXPERT_PLAN_TOPIC, PLAN_TOPIC


def _paths(bag: Path, topic: str) -> list[tuple[float, np.ndarray]]:
    """(stamp s, waypoints (N, 3)) of every nav_msgs/Path on a topic."""
    out = []
    for _t, _ns, decode in BagSource(bag).messages([topic]):
        msg = decode()
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        out.append((stamp, np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in msg.poses])))
    return out


@pytest.fixture(scope="module")
def rollouts(closed_loop_model: tuple[Path, Path], ingested: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Two labelled rollouts of the tiny closed-loop model (DAgger), and the same with an operator who takes over
    at the first chance and never hands back, each ingested."""
    split, model = closed_loop_model
    root = tmp_path_factory.mktemp("dagger")
    out = {}
    for kind, extra in (("dagger", []), ("hg", ["--operator", "0.001", "0.1", "0.00001"])):
        run_module("rollout", model, "--data", ingested, "--split", split.with_name("train.json"), "--out",
                   root / kind, "--limit", "2", "--workers", "1", "--summary", root / f"{kind}.json", *extra,
                   check=True)
        bags = sorted((root / kind).glob("*.mcap"))
        run_module("ingest", *bags, "-o", root / f"{kind}.h5", "--size", "64", check=True)
        out[kind] = {"bags": bags, "h5": root / f"{kind}.h5",
                     "summary": json.loads((root / f"{kind}.json").read_text())}
    out["root"] = root
    return out


def test_every_replan_of_a_rollout_is_labelled_by_the_expert_as_training_labels_it(rollouts: dict,
                                                                                   closed_loop_model: tuple) -> None:
    split, _model = closed_loop_model
    s = rollouts["dagger"]["summary"]
    assert s["rollouts"] == 2 and s["operator_plans"] == 0
    train = json.loads(split.with_name("train.json").read_text())["train"]
    assert {r["scene"] for r in s["per_rollout"]} <= set(train)  # training scenes, never the test split's
    bag = rollouts["dagger"]["bags"][0]
    expert, executed = _paths(bag, EXPERT_PLAN_TOPIC), _paths(bag, PLAN_TOPIC)
    assert len(expert) == len(executed) == s["per_rollout"][0]["plans"] >= 3
    with h5py.File(rollouts["dagger"]["h5"]) as f:
        g = next(iter(f[schema.EPISODES].values()))
        t0 = float(g.attrs["stamp0_ns"]) / 1e9
        ref_t, ref_p, phase_t, phase = expert_reference(g, "rollout")
        assert np.all(np.diff(phase) >= 0) and phase[-1] > 0  # the expert's phase goes on along the path
        ct, cmd = command_series(g, "rollout")
        frame_t = g["frames/t"][()]
        for i, (stamp, waypoints) in enumerate(expert[1:], 1):
            t = stamp - t0
            k = int(np.argmin(abs(frame_t - t)))
            assert abs(frame_t[k] - t) < 5e-3  # a re-plan's frame (0.8 s at 5 Hz, to the physics step)
            # the label train makes from the bag's reference stream, from the command the arm had then (the
            # previous plan's 8th waypoint, Ta 8; the command stream samples it at 100 Hz)
            now = executed[i - 1][1][7][None]
            label = relative_waypoints(np.array([t]), now, ct, cmd, 16, 10.0, g["K"][()], g["T_base_camera"][()],
                                       reference=(ref_t, ref_p, phase_t, phase))[0, :, 2:] + now
            np.testing.assert_allclose(label, waypoints, atol=1e-5)  # what train --target recovery learns there
            # the expert goes back to the demonstrated path from the phase reached: at the plan's end 0.5 % of the
            # offset is left
            at = np.interp(t, phase_t, phase)
            ref_end = np.array([np.interp(at + 1.6, ref_t, ref_p[:, d]) for d in range(3)])
            ref_now = np.array([np.interp(at, ref_t, ref_p[:, d]) for d in range(3)])
            assert np.linalg.norm(waypoints[-1] - ref_end) <= 0.01 * np.linalg.norm(now[0] - ref_now) + 1e-4


def test_the_expert_leads_a_lagging_arm_on_along_the_path_not_to_where_the_timetable_is(ingested: Path) -> None:
    from adlpipe.geometry.recovery import recovering_plan

    with h5py.File(ingested) as f:
        g = f[schema.EPISODES][schema.episode_names(f)[0]]
        ref_t, ref_p = command_series(g, "demo")
    expert = Expert(ref_t, ref_p, 16, 10.0)
    start = ref_p[0]
    for _ in range(100):  # the arm stood still at the start for a second (100 Hz)
        assert expert.track(start) == 0.0
    ahead = np.arange(1, 17) / 10.0
    along = np.stack([np.interp(ahead, ref_t, ref_p[:, d]) for d in range(3)], 1)
    np.testing.assert_allclose(expert.plan(start), along, atol=1e-9)  # the demonstration's first 1.6 s
    timed = recovering_plan(np.array([1.0]), start[None], ref_t, ref_p, 1.0 + ahead[None])[0]
    assert np.linalg.norm(timed[2] - start) > 2 * np.linalg.norm(along[2] - start)  # the timetable's dash
    for t in np.arange(1.0, 3.0, 0.01):  # then it goes along the path at half the demonstration's pace
        phase = expert.track(expert.reference((t - 1.0) / 2))
    assert phase == pytest.approx(0.995, abs=0.01)  # the arm's own progress, not the clock's 3 s
    assert expert.track(start) >= phase  # never back


def test_the_operator_takes_over_after_hold_s_off_the_path_and_hands_back(ingested: Path) -> None:
    with h5py.File(ingested) as f:
        g = f[schema.EPISODES][schema.episode_names(f)[0]]
        ref_t, ref_p = command_series(g, "demo")
    expert = Expert(ref_t, ref_p, 16, 10.0)
    on = np.stack([np.interp(np.linspace(0.5, 1.2, 8), ref_t, ref_p[:, d]) for d in range(3)], 1)
    assert expert.off_path(on).max() < 1e-3
    shift = next(v for v in np.vstack([np.eye(3), -np.eye(3)]) * 0.03 if expert.off_path(on[5:] + v).min() > 0.021)
    op = Operator(expert, OperatorRule(off_cm=2.0, hold_s=0.3, back_cm=0.5))
    assert not op.decide(on, 0.1, on[-1])
    assert not op.decide(np.vstack([on[:6], on[6:] + shift]), 0.1, on[-1] + shift)  # 0.2 s off: not yet
    assert op.decide(np.vstack([on[:5], on[5:] + shift]), 0.1, on[-1] + shift)  # 0.3 s off: it drives
    assert op.decide(np.zeros((0, 3)), 0.1, on[-1] + shift / 3)  # 1 cm off: still driving
    assert not op.decide(np.zeros((0, 3)), 0.1, on[-1] + shift / 10)  # 3 mm: handed back


def test_the_operators_flag_goes_from_the_bag_to_hdf5_training_windows_and_lerobot(rollouts: dict,
                                                                                   ingested: Path) -> None:
    hg = rollouts["hg"]
    s = hg["summary"]
    plans = [r["plans"] for r in s["per_rollout"]]
    assert s["operator_plans"] == sum(p - 1 for p in plans)  # from the second re-plan on (the first has no past)
    with h5py.File(hg["h5"]) as f:
        names = schema.episode_names(f)
        for n in names:
            fr = f[schema.EPISODES][n]["frames"]
            np.testing.assert_array_equal(fr["intervention"][()], fr["t"][()] >= 0.8 - 1e-6)
            drove = int(fr["intervention"][()][: int(np.searchsorted(fr["t"][()],
                                                     f[schema.EPISODES][n].attrs["duration_s"], "right"))].sum())
            w = Windows(2, 16, 10.0, "recovery", corrections_only=True)
            ds = WindowDataset(hg["h5"], [n], {"min": [-1] * 5, "max": [1] * 5}, 64, w)
            assert len(ds.items) == drove > 0 and all(fr["intervention"][k] for _e, k in ds.items)
    out = rollouts["root"] / "lerobot"
    run_module("export", hg["h5"], out, "--images", "png", check=True)
    table = pq.read_table(next(out.glob("data/*/*.parquet")))
    info = json.loads((out / "meta/info.json").read_text())
    assert info["features"]["intervention"] == {"dtype": "bool", "shape": [1], "names": None}
    with h5py.File(hg["h5"]) as f:
        flags = np.concatenate([f[schema.EPISODES][n]["frames/intervention"][()] for n in names])
    np.testing.assert_array_equal(np.array(table.column("intervention").to_pylist()), flags)


def test_a_labs_flag_on_its_own_topic_is_read_through_the_topic_map(tmp_path: Path) -> None:
    from adlpipe.bags.topics import TopicMap
    from adlpipe.sim.episode import seeded_demo
    from adlpipe.sim.recording import write_episode_bag

    st = seeded_demo("wipe the nose", 0, 0, 64, 5.0)
    st.interventions = [(0.0, False), (1.0, True), (1.6, False)]
    bag = write_episode_bag(st, tmp_path / "lab.mcap", "mcap", "raw", "32FC1", 0,
                            topics=TopicMap(intervention="/teleop/engaged"))
    (tmp_path / "topics.yaml").write_text("intervention: /teleop/engaged\n")
    run_module("ingest", bag, "-o", tmp_path / "lab.h5", "--size", "64", "--config", tmp_path / "topics.yaml",
               check=True)
    run_module("ingest", bag, "-o", tmp_path / "plain.h5", "--size", "64", check=True)  # the default topic: absent
    with h5py.File(tmp_path / "lab.h5") as f, h5py.File(tmp_path / "plain.h5") as g:
        fr = next(iter(f[schema.EPISODES].values()))["frames"]
        t = fr["t"][()]
        np.testing.assert_array_equal(fr["intervention"][()], (t >= 1.0 - 1e-6) & (t < 1.6 - 1e-6))
        assert "intervention" not in next(iter(g[schema.EPISODES].values()))["frames"]
    (tmp_path / "bad.yaml").write_text("intervention: /adl/task\n")
    line = one_line_error(run_module("ingest", bag, "-o", tmp_path / "bad.h5", "--size", "64", "--config",
                                     tmp_path / "bad.yaml"))
    assert "/adl/task has type std_msgs/msg/String, expected std_msgs/msg/Bool" in line
    assert not (tmp_path / "bad.h5").exists()


def test_a_round_warm_starts_on_the_demonstrations_and_rollouts_with_the_test_split_kept(
        rollouts: dict, closed_loop_model: tuple, ingested: Path, mcap_bags: list[Path], tmp_path: Path) -> None:
    split, model = closed_loop_model
    data = tmp_path / "round.h5"
    run_module("ingest", *mcap_bags, *rollouts["dagger"]["bags"], "-o", data, "--size", "64", check=True)
    earlier = json.loads(split.read_text())
    run_module("split", data, "--extend", split, check=True)
    extended = json.loads(data.with_name("split.json").read_text())
    assert extended["test"] == earlier["test"] and len(extended["train"]) == 2
    run_module("train", "--model", "fm_cnn", "--closed-loop", "--target", "recovery", "--data", data, "--split",
               data.with_name("split.json"), "--out", tmp_path / "r1", "--init", model / "best.pt", "--steps", "3",
               "--batch-size", "1", "--val-fraction", "0", check=True)
    m = json.loads((tmp_path / "r1/metrics.json").read_text())
    assert m["optimizer_steps"] >= 3
    import torch

    start = torch.load(model / "best.pt", weights_only=False)
    after = torch.load(tmp_path / "r1/best.pt", weights_only=False)
    assert after["stats"] == start["stats"]  # the warm start keeps the normalisation its weights learnt
    line = one_line_error(run_module("train", "--model", "dp_cnn", "--closed-loop", "--data", data, "--split",
                                     data.with_name("split.json"), "--out", tmp_path / "bad", "--init",
                                     model / "best.pt", "--steps", "1"))
    assert "--init" in line and "model" in line
    (tmp_path / "other.json").write_text(json.dumps({"train": [], "test": ["nope"]}))
    line = one_line_error(run_module("split", data, "--extend", tmp_path / "other.json", "-o", tmp_path / "s.json"))
    assert "nope is not in the data" in line and not (tmp_path / "s.json").exists()


def test_rollout_never_takes_the_test_split_and_says_so_in_one_line(closed_loop_model: tuple, ingested: Path,
                                                                    tmp_path: Path) -> None:
    split, model = closed_loop_model  # every episode in its test part
    line = one_line_error(run_module("rollout", model, "--data", ingested, "--split", split, "--out", tmp_path / "o"))
    assert "no train episodes to roll out on" in line and not (tmp_path / "o").exists()
