"""Trials on a real robot: CSVs and trial bags written by the real writers, decided after every trial."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from adlpipe.bags import messages as M
from adlpipe.sim.recording import write_episode_bag
from tests.conftest import one_line_error, run_module


def write_csv(path: Path, rates: dict[str, float], rounds: int, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    rows = ["policy,trial,success,force_n"]
    for r in range(rounds):
        for i, (policy, rate) in enumerate(rates.items()):
            rows.append(f"{policy},{r * len(rates) + i + 1},{int(rng.random() < rate)},{rng.random() * 10:.1f}")
    path.write_text("\n".join(rows) + "\n")
    return path


def test_trials_stop_as_soon_as_the_rule_decides(tmp_path: Path) -> None:
    csv = write_csv(tmp_path / "trials.csv", {"fm_cnn": 0.85, "dp_cnn": 0.35}, rounds=100)
    out = tmp_path / "decision.json"
    proc = run_module("trials", csv, "--policies", "fm_cnn", "dp_cnn", "--latency", "fm_cnn=3.5", "dp_cnn=31",
                      "-o", out, check=True)
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("trial 1 (fm_cnn: ") and lines[0].endswith("continue: run dp_cnn next")
    stop = next(i for i, line in enumerate(lines) if ": stop: fm_cnn" in line)
    assert 10 < stop < 120  # long before the 200 trials in the file
    assert "not needed for it" in lines[stop + 1]
    decision = json.loads(out.read_text())
    assert decision["recommended"] == "fm_cnn" and decision["next"] is None


def test_equal_policies_keep_the_trials_going_and_alternate(tmp_path: Path) -> None:
    csv = write_csv(tmp_path / "trials.csv", {"a": 0.6, "b": 0.6}, rounds=10, seed=1)
    proc = run_module("trials", csv, "--policies", "a", "b", check=True)
    nexts = [line.rsplit("run ", 1)[1].split()[0] for line in proc.stdout.splitlines() if "continue: run" in line]
    assert len(nexts) == 20 and nexts[:4] == ["b", "a", "b", "a"]
    assert "**Undecided** after 10 trials" in proc.stdout


def test_a_policy_that_hurts_the_person_is_out(tmp_path: Path) -> None:
    rows = ["policy,success,force_n"] + [f"{p},1,{f}" for _ in range(60) for p, f in (("rough", 35.0), ("gentle", 4.0))]
    (tmp_path / "t.csv").write_text("\n".join(rows) + "\n")
    proc = run_module("trials", tmp_path / "t.csv", check=True)
    assert "trial 22 (gentle: success, 4.0 N): stop: gentle" in proc.stdout  # 11 unsafe in 11: enough
    assert "rough: 11 of 11 (100.0 %), **out**: resolved above gentle" in proc.stdout


@pytest.mark.parametrize(("content", "expect"), [
    ("policy,ok\na,1\n", "no column success"),
    ("policy,success\na,maybe\n", "t.csv:2: success 'maybe' is not one of"),
    ("policy,success,force_n\na,1,-3\n", "t.csv:2: force_n -3.0 is outside"),
    ("trial,policy,success\n1,a,1\n1,b,0\n", "t.csv:3: trial 1 again (first on line 2)"),
    ("trial,policy,success\n1,a,1\n,b,0\n", "t.csv:3: empty trial number"),
])
def test_a_bad_trials_csv_is_one_line_naming_the_place(tmp_path: Path, content: str, expect: str) -> None:
    (tmp_path / "t.csv").write_text(content)
    assert expect in one_line_error(run_module("trials", tmp_path / "t.csv"))


def test_the_output_is_never_an_input(tmp_path: Path) -> None:
    csv = write_csv(tmp_path / "trials.csv", {"a": 0.5, "b": 0.5}, rounds=2)
    before = csv.read_text()
    assert "is an input of this command" in one_line_error(run_module("trials", csv, "-o", csv))
    assert csv.read_text() == before


@pytest.fixture(scope="module")
def trial_bags(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Trial bags: one recorded demonstration written as five trials by the recorder's own writer, each with its
    outcome: JSON on /adl/outcome (ROS2 MCAP), or a Bool with the policy on /adl/policy (ROS1 .bag)."""
    from adlpipe.sim.episode import record_demo

    out = tmp_path_factory.mktemp("trials")
    st = record_demo("wipe the nose", np.random.default_rng(0), 32, 32, camera_hz=2.0)
    bags = []
    for i, (policy, ok) in enumerate([("fm_cnn", True), ("dp_cnn", False), ("fm_cnn", True), ("dp_cnn", True)]):
        doc = json.dumps({"policy": policy, "success": ok, "force_n": 3.0 + i})
        bags.append(write_episode_bag(st, out / f"trial_{i}.mcap", "mcap", "raw", "32FC1", i,
                                      outcome=[("/adl/outcome", M.STRING, doc)]))
    bags.append(write_episode_bag(st, out / "trial_4.bag", "bag", "raw", "32FC1", 4,
                                  outcome=[("/adl/policy", M.STRING, "fm_cnn"), ("/adl/outcome", M.BOOL, False)]))
    return bags


def test_trial_bags_are_read_in_recording_order(trial_bags: list[Path]) -> None:
    proc = run_module("trials", *reversed(trial_bags), "--policies", "fm_cnn", "dp_cnn", check=True)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("trial ")]
    assert [line.split(":")[0] for line in lines] == ["trial 1 (fm_cnn", "trial 2 (dp_cnn", "trial 3 (fm_cnn",
                                                       "trial 4 (dp_cnn", "trial 5 (fm_cnn"]
    assert "trial 2 (dp_cnn: failure, 4.0 N): continue: run fm_cnn next" in proc.stdout
    assert "trial 5 (fm_cnn: failure): continue: run dp_cnn next" in proc.stdout  # the Bool, its policy beside


def test_a_trial_bag_is_a_recording_ingest_keeps_whole(trial_bags: list[Path], tmp_path: Path) -> None:
    run_module("ingest", trial_bags[1], "-o", tmp_path / "trials.h5", "--size", "32", check=True)
    with h5py.File(tmp_path / "trials.h5") as f:
        (name,) = list(f["episodes"])
        frames = len(f["episodes"][name]["frames/t"])
    from adlpipe.bags.reader import BagSource

    images = sum(1 for _ in BagSource(trial_bags[1]).messages(["/camera/color/image_raw"]))
    assert frames == images >= 5  # every camera frame of the trial, not only the first


def test_a_bag_without_an_outcome_is_named(tmp_path: Path, trial_bags: list[Path]) -> None:
    from adlpipe.sim.episode import record_demo

    st = record_demo("wipe the nose", np.random.default_rng(1), 32, 32, camera_hz=1.0)
    plain = write_episode_bag(st, tmp_path / "plain.mcap", "mcap", "raw", "32FC1", 0)
    assert "plain.mcap: no /adl/outcome topic" in one_line_error(run_module("trials", trial_bags[0], plain))


def test_a_byte_order_mark_does_not_hide_the_first_column(tmp_path: Path) -> None:
    (tmp_path / "t.csv").write_bytes(b"\xef\xbb\xbftrial,policy,success\n2,b,0\n1,a,1\n")
    out = run_module("trials", tmp_path / "t.csv", check=True).stdout
    assert out.splitlines()[0].startswith("trial 1 (a: success)")  # ordered by the trial column, not the rows


@pytest.mark.parametrize(("args", "expect"), [
    (["--latency", "a=nan"], "finite ms >= 0"),
    (["--latency", "a=-1"], "finite ms >= 0"),
    (["--latency", "a=inf"], "finite ms >= 0"),
    (["--latency", "=3"], "with a policy name"),
    (["--latency", "ghost=3"], "--latency ghost: no such policy among the trials"),
    (["--policies", "a", ""], "--policies: an empty policy name"),
])
def test_bad_latencies_and_policy_names_are_refused(tmp_path: Path, args: list[str], expect: str) -> None:
    (tmp_path / "t.csv").write_text("policy,success\na,1\nb,0\n")
    assert expect in one_line_error(run_module("trials", tmp_path / "t.csv", *args))


def test_the_same_file_twice_a_fifo_and_a_device_are_refused(tmp_path: Path) -> None:
    import os

    (tmp_path / "t.csv").write_text("policy,success\na,1\nb,0\n")
    assert "given twice" in one_line_error(run_module("trials", tmp_path / "t.csv", tmp_path / "t.csv"))
    os.mkfifo(tmp_path / "f.csv")
    assert "f.csv: not a regular file" in one_line_error(run_module("trials", tmp_path / "f.csv", timeout=60))
    (tmp_path / "z.csv").symlink_to("/dev/zero")
    assert "z.csv: not a regular file" in one_line_error(run_module("trials", tmp_path / "z.csv", timeout=60))


@pytest.mark.parametrize(("outcome", "expect"), [
    ([("/adl/policy", M.STRING, "a"), ("/adl/outcome", M.STRING, "true")], None),
    ([("/adl/outcome", M.STRING, json.dumps({"policy": ["a"], "success": True}))], "is a list, not a name"),
    ([("/adl/policy", M.BOOL, True), ("/adl/outcome", M.BOOL, True)], "bool, not a std_msgs/String"),
    ([("/adl/policy", M.STRING, "a"), ("/adl/outcome", M.BOOL, True), ("/adl/outcome", M.BOOL, False)],
     "/adl/outcome: 2 messages; a trial bag holds one trial"),
    ([("/adl/policy", M.STRING, "a"), ("/adl/outcome", M.STRING, "[" * 5000 + "]" * 5000)],
     "... (10000 characters) is not one of"),
])
def test_trial_bag_outcomes_read_by_one_schema(tmp_path: Path, trial_bags: list[Path], outcome: list,
                                               expect: str | None) -> None:
    from adlpipe.sim.episode import record_demo

    st = record_demo("wipe the nose", np.random.default_rng(1), 32, 32, camera_hz=1.0)
    bag = write_episode_bag(st, tmp_path / "t.mcap", "mcap", "raw", "32FC1", 0, outcome=outcome)
    proc = run_module("trials", bag)
    if expect is None:
        assert proc.returncode == 0 and "trial 1 (a: success)" in proc.stdout, proc.stderr
    else:
        assert expect in one_line_error(proc)


def test_the_rule_trial_by_trial_is_the_rule_on_all_trials_so_far() -> None:
    """TrialSeries (linear in the trials) against decide() rebuilt from scratch after every trial (the quadratic
    way): the same decision, lines and next policy at every trial, a third policy joining mid-series included."""
    from adlpipe.evaluation.decision import Rule, decide
    from adlpipe.evaluation.trials import Trial, TrialSeries

    rng = np.random.default_rng(3)
    rates = {"a": 0.75, "b": 0.55, "c": 0.45}  # decided after 576 trials, c there from the 11th on
    trials = [Trial(p, bool(rng.random() < rates[p]), float(rng.random() * 30) if rng.random() < 0.5 else None,
                    None, "x") for i in range(300) for p in (["a", "b"] if i < 5 else ["a", "b", "c"])]
    latency = {"a": 3.0, "b": 30.0}
    rule = Rule(0.05, 0.05)
    series = TrialSeries(latency, rule, ["a"])
    for i, t in enumerate(trials, start=1):
        series.add(t)
        got, nxt = series.decision()
        names = list(dict.fromkeys(["a", *(u.policy for u in trials[:i])]))
        success: dict = {p: {} for p in names}
        force: dict = {p: {} for p in names}
        for u in trials[:i]:
            key = f"trial/{len(success[u.policy])}"
            success[u.policy][key] = u.success
            if u.force_n is not None:
                force[u.policy][key] = u.force_n
        want = decide(success, force, {p: latency.get(p) for p in names}, rule, unit="trials")
        assert got["lines"] == want["lines"] and got["recommended"] == want["recommended"], i
        if want["status"] == "decided" and len(names) > 1:
            assert nxt is None and i == 576 and got["recommended"] == "a" and len(names) == 3
            break
        assert nxt is not None
    else:
        raise AssertionError("never decided")


@pytest.mark.parametrize("msgtype", ["std_msgs/msg/Float64", "std_msgs/msg/Int32", "std_msgs/msg/UInt8"])
def test_a_numeric_outcome_message_is_refused_in_one_line(tmp_path: Path, msgtype: str) -> None:
    from collections import Counter

    from adlpipe.bags.writer import BagWriter

    w = BagWriter(tmp_path / "t.mcap", "mcap")
    w.declare_counts(Counter({"/adl/policy": 1, "/adl/outcome": 1}))
    w.write("/adl/policy", M.STRING, 10**9, w.msgs.string("a"))
    w.write("/adl/outcome", msgtype, 2 * 10**9, w.msgs.T[msgtype](data=1))
    bag = w.close()
    err = one_line_error(run_module("trials", bag))
    assert "/adl/outcome: a " in err and "the outcome is a std_msgs/String (JSON, or true/false)" in err


def test_the_guide_shows_what_trials_says_on_its_sample_csv(tmp_path: Path) -> None:
    """docs/guide/decision.md quotes `adlpipe trials examples/trials.csv`: the quoted lines are the command's own."""
    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "outcome.json"
    proc = run_module("trials", root / "examples" / "trials.csv", "--latency", "fm_cnn=3.0", "dp_cnn=31.3",
                      "-o", out, check=True)
    guide = (root / "docs" / "guide" / "decision.md").read_text()
    block = guide[guide.index("$ adlpipe trials examples/trials.csv"):]
    block = block[:block.index("```")]
    said = " ".join(proc.stdout.split())
    quoted = [ln.strip() for ln in block.splitlines()[1:] if ln.strip() and ln.strip() != "..."]
    assert len(quoted) >= 8
    for line in quoted:
        assert line in said or line in proc.stdout, line
    assert json.loads(out.read_text())["needs"] == 83
