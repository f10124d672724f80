"""Taking care of a dataset (issue T): doctor's figures and flags, --verify against the bags, edits that share the
episode files, and a bag beside its episode in Rerun; on bags written with the real writers (mcap, rosbags)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from conftest import one_line_error, run_module
from layouts import Layout, topic_map, write_layout_bag

from adlpipe.bags.topics import TopicMap
from adlpipe.curation.doctor import Limits, outlier_flags
from adlpipe.dataset import schema
from adlpipe.ingest import ingest

CASES = {  # a clean episode, and one of each problem doctor must flag, in the three bag formats
    "clean": (Layout(fmt="mcap"), "c.mcap"),
    "frozen": (Layout(fmt="bag", frozen=(8, 16), duration_s=3.4), "f.bag"),
    "glitch": (Layout(fmt="db3", tf_glitch_s=1.5), "g"),
    "idle": (Layout(fmt="mcap", idle_start_s=2.0), "i.mcap"),
    # the same motion as the clean one, a little longer each, so none of them repeats another recording
    "spike": (Layout(fmt="mcap", joint_spike_s=1.2, duration_s=3.1), "s.mcap"),
    "nan": (Layout(fmt="mcap", joint_nan_s=1.3, duration_s=3.2), "n.mcap"),
    "stuck": (Layout(fmt="mcap", joint_stuck=(0.5, 2.0), duration_s=3.3), "k.mcap"),
    "copy": (Layout(fmt="mcap", clock_offset_s=3600.0), "d.mcap"),  # the clean one saved again an hour later
}


@pytest.fixture(scope="module")
def curated(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("curate")
    bags, truth = {}, {}
    for case, (lay, name) in CASES.items():
        (root / case).mkdir()
        bags[case], ee_t, ee_p = write_layout_bag(root / case / name, lay)
        truth[case] = (ee_t, ee_p)
    cfg = root / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(Layout())))
    data = root / "x.h5"
    assert ingest(list(bags.values()), data, TopicMap.load(cfg), size=48)["new"] == len(CASES)
    with h5py.File(data) as f:
        name_of = {case: next(n for n in schema.episode_names(f)
                              if Path(str(f["episodes"][n].attrs["source_path"])) == bags[case].resolve())
                   for case in CASES}
    report = root / "doctor.json"
    proc = run_module("doctor", data, "--json", report, "--png", root / "doctor.png", check=True)
    return {"root": root, "data": data, "bags": bags, "truth": truth, "name": name_of, "stdout": proc.stdout,
            "report": json.loads(report.read_text())["episodes"]}


def test_doctor_flags_each_problem_and_not_the_clean_episode(curated: dict) -> None:
    rep, name = curated["report"], curated["name"]
    kinds = {case: sorted({fl.split(":")[0] for fl in rep[name[case]]["flags"]}) for case in CASES}
    # (with 8 episodes of the task, the glitch's peak speed and the idle one's duration are outliers too)
    assert kinds == {"clean": [], "frozen": ["frozen camera"], "glitch": ["outlier", "tf glitch"],
                     "idle": ["idle start", "outlier"],
                     "spike": ["joint spike"], "nan": ["non-finite values"], "stuck": ["joint flatline"],
                     "copy": ["near duplicate"]}
    clean, frozen, glitch, idle = (rep[name[c]] for c in ("clean", "frozen", "glitch", "idle"))
    assert abs(clean["fps"] - 10.0) < 0.01 and clean["repeated_frames"] == 0 and clean["max_frame_gap_s"] < 0.11
    ee_t, ee_p = curated["truth"]["clean"]  # the path length the tf really traced
    inside = ee_t <= clean["duration_s"] + 1e-9
    true_path = float(np.linalg.norm(np.diff(ee_p[inside], axis=0), axis=1).sum())
    assert abs(clean["path_m"] - true_path) < 1e-3 * true_path
    assert clean["sync_tf_s"] < 0.011 and clean["sync_joints_s"] < 0.006 and clean["sync_depth_s"] == 0.0
    assert clean["depth_holes"] == pytest.approx(4 / 48, abs=0.03)  # the layout's rows with no return
    assert frozen["repeated_frames"] == 8 and frozen["frozen_run"] == 9 and frozen["frozen_at_s"] == pytest.approx(0.8)
    assert glitch["peak_speed_mps"] > 20 and abs(glitch["peak_speed_at_s"] - 1.5) < 0.03
    assert idle["idle_start_s"] == pytest.approx(2.0, abs=0.05) and clean["idle_start_s"] < 0.05
    spike, nan, stuck = (rep[name[c]] for c in ("spike", "nan", "stuck"))
    assert spike["joint_spike_joint"] == "joint_3" and spike["joint_spike"] == pytest.approx(1.0, abs=0.02)
    assert spike["joint_spike_at_s"] == pytest.approx(1.2, abs=0.01) and clean["joint_spike_share"] < 0.01
    assert nan["non_finite"] == [f"left out 1 of {round(nan['duration_s'] * 100) + 1} joint states on "
                                 "/my_gen3/joint_states with non-finite values (the first at 1.30 s, in joint_3)"]
    assert stuck["joint_flat_joint"] == "joint_3" and stuck["joint_flat_s"] == pytest.approx(1.5, abs=0.011)
    assert stuck["joint_flat_moved_m"] > 0.05 and clean["joint_flat_s"] == 0.0
    assert rep[name["copy"]]["flags"] == [f"near duplicate: of {name['clean']} (recorded before it): as many "
                                          "frames, the end effector 0.0 um from it (RMS; limit 1000 um)"]
    assert f"| wipe the table | {len(CASES)} | {len(CASES) - 1} |" in curated["stdout"]
    png = (curated["root"] / "doctor.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_outliers_are_robust_z_scores_within_a_task() -> None:
    figs = {f"e{i}": {"task": "a", "duration_s": 3.0 + 0.1 * i, "path_m": 0.6, "peak_speed_mps": 0.3, "fps": 10.0,
                      "flags": []} for i in range(6)}
    figs["e5"]["duration_s"] = 12.0
    figs["b0"] = {"task": "b", "duration_s": 40.0, "path_m": 0.6, "peak_speed_mps": 0.3, "fps": 10.0, "flags": []}
    for i, v in enumerate([0.55, 0.551, 0.552, 0.553, 0.554, 0.58]):  # nearly alike: robust z 13, but 5 % off
        figs[f"c{i}"] = {"task": "c", "duration_s": 3.0, "path_m": 0.6, "peak_speed_mps": v, "fps": 10.0, "flags": []}
    outlier_flags(figs, Limits())
    assert [n for n, f in figs.items() if f["flags"]] == ["e5"]  # task b has one episode: never an outlier
    assert "duration_s 12 against the task's median 3.25" in figs["e5"]["flags"][0]


def test_verify_finds_nothing_on_a_faithful_dataset_and_each_changed_array(curated: dict, tmp_path: Path) -> None:
    bags = [str(b) for b in curated["bags"].values()]
    proc = run_module("doctor", curated["data"], "--verify", *bags, check=True)
    assert f"{len(CASES)} episode(s) verified against their bags, 0 mismatch(es)" in proc.stdout
    copy = tmp_path / "copy"
    shutil.copytree(curated["root"], copy, ignore=shutil.ignore_patterns("*.mcap", "*.bag", "*.db3"))
    name = curated["name"]["clean"]
    with h5py.File(copy / "x.h5") as f:
        file = schema.episode_path(copy / "x.h5", f, name)
    with h5py.File(file, "r+") as f:
        g = f["episodes"][name]
        g["frames/rgb"][3] = 0
        g["traj3d"][5, 0] += 0.01
    proc = run_module("doctor", copy / "x.h5", "--verify", *bags)
    assert proc.returncode == 1
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(name)]
    assert len(lines) == 2 and "frames/rgb: frame 3 differs from the bag" in lines[0]
    assert "traj3d: 1 value(s) differ from the bag by up to 0.01" in lines[1]


def _bytes_of(index: Path) -> dict[str, bytes]:
    return {str(p): p.read_bytes() for p in sorted(index.parent.rglob("*.h5"))}


def test_edits_share_the_files_leave_the_old_dataset_and_refuse_an_old_split(curated: dict, tmp_path: Path) -> None:
    root, data, name = curated["root"], curated["data"], curated["name"]
    before = _bytes_of(data)
    clean = root / "clean.h5"
    run_module("edit", data, "-o", clean, "--drop-flagged", root / "doctor.json", check=True)
    with schema.open_dataset(clean) as f:
        assert schema.episode_names(f) == [name["clean"]]
        new_file = schema.episode_path(clean, f, name["clean"])
    with h5py.File(data) as f:
        old_file = schema.episode_path(data, f, name["clean"])
    assert new_file != old_file and new_file.stat().st_ino == old_file.stat().st_ino  # shared, not copied
    retasked = root / "retasked.h5"
    run_module("edit", data, "-o", retasked, "--retask", f"{name['idle']}=pass the cup", "--drop", name["glitch"],
               check=True)
    with schema.open_dataset(retasked) as f:
        names = schema.episode_names(f)
        new_name = next(n for n in names if n.startswith("pass_the_cup-"))
        assert len(names) == len(CASES) - 1 and f["episodes"][new_name].attrs["task"] == "pass the cup"
        assert {r["name"]: r["task"] for r in schema.read_catalog(f)}[new_name] == "pass the cup"
        assert np.array_equal(f["episodes"][new_name]["frames/rgb"][()],
                              h5py.File(data)["episodes"][name["idle"]]["frames/rgb"][()])
    assert all(Path(k).read_bytes() == v for k, v in before.items())  # no file of the old dataset changed
    with h5py.File(data) as f:
        assert f["episodes"][name["idle"]].attrs["task"] == "wipe the table"  # the old dataset keeps its task
    # a split of the old dataset names episodes the new one dropped: one line
    run_module("split", data, "-o", root / "split.json", check=True)
    line = one_line_error(run_module("train", "--model", "fm_cnn", "--data", clean, "--split", root / "split.json",
                                     "--epochs", "1", "--out", tmp_path / "m"))
    assert "named by the split are not in the dataset" in line


def test_a_merge_adds_the_other_datasets_episodes_once(curated: dict, tmp_path: Path) -> None:
    other_bag, _t, _p = write_layout_bag(tmp_path / "o.mcap", Layout(task="pass the cup"))
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(Layout())))
    other = tmp_path / "o.h5"
    assert ingest([other_bag, curated["bags"]["clean"]], other, TopicMap.load(cfg), size=48)["new"] == 2
    merged = tmp_path / "m.h5"
    proc = run_module("edit", curated["data"], "-o", merged, "--merge", other, check=True)
    assert "1 episode(s) already in" in proc.stderr
    with schema.open_dataset(merged) as f:
        tasks = sorted(str(f["episodes"][n].attrs["task"]) for n in schema.episode_names(f))
    assert tasks == ["pass the cup"] + ["wipe the table"] * len(CASES)


@pytest.mark.parametrize(("args", "needle"), [
    (["--drop", "nobody"], "no episode 'nobody'"),
    (["--rename", "x"], "give NAME=VALUE"),
    (["--drop-flagged", "map.yaml"], "not a doctor report"),
])
def test_a_bad_edit_is_one_line_and_writes_nothing(curated: dict, tmp_path: Path, args: list[str],
                                                   needle: str) -> None:
    args = [str(curated["root"] / a) if a.endswith(".yaml") else a for a in args]
    line = one_line_error(run_module("edit", curated["data"], "-o", tmp_path / "n.h5", *args))
    assert needle in line and not (tmp_path / "n.h5").exists() and not (tmp_path / "n.shards").exists()


def test_a_failed_edit_leaves_no_output(curated: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from adlpipe.curation import edit as edit_module

    def broken(*_a: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(edit_module, "_rewrite", broken)
    out = tmp_path / "n.h5"
    with pytest.raises(OSError):
        edit_module.edit(curated["data"], out, edit_module.Edits(retask={curated["name"]["idle"]: "x"}))
    assert not out.exists() and not (tmp_path / "n.shards").exists()  # no empty folder either (R5)


SHM = Path("/dev/shm")


@pytest.mark.skipif(not SHM.is_dir() or not os.access(SHM, os.W_OK), reason="needs a writable /dev/shm")
def test_an_edit_onto_another_file_system_is_one_line_and_leaves_no_folder(curated: dict, tmp_path: Path) -> None:
    """Hard links cannot cross file systems: one line saying so, and neither the index nor an empty .shards folder
    left there (an empty one was left before)."""
    if SHM.stat().st_dev == curated["data"].stat().st_dev:
        pytest.skip("/dev/shm is on the dataset's file system here")
    out = SHM / f"adlpipe-test-{os.getpid()}" / "n.h5"
    try:
        line = one_line_error(run_module("edit", curated["data"], "-o", out))
        assert "hard link" in line and "same file system" in line
        assert not out.exists() and not out.with_name("n.shards").exists()
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)


def test_inspect_shows_the_bag_beside_its_episode(curated: dict, tmp_path: Path) -> None:
    from test_viewer import rows_and_values

    name = curated["name"]["glitch"]
    rrd = tmp_path / "side.rrd"
    run_module("inspect", "--dataset", "--data", curated["data"], "--episodes", name, "--bag",
               curated["bags"]["glitch"], "-o", rrd, check=True)
    rows, values, blueprints = rows_and_values(rrd)
    with h5py.File(curated["data"]) as f:
        n_frames = len(f["episodes"][name]["frames/t"])
    assert rows["/bag/image"] == 31 and rows["/world/camera/image/rgb"] == n_frames  # every bag image, 3 s at 10 Hz
    assert rows["/world/bag_ee"] == 151 and rows["/bag/joints/joint_1"] == 301
    jump = np.linalg.norm(np.diff(np.array(values["/world/bag_ee"]).reshape(-1, 3), axis=0), axis=1).max()
    assert jump > 0.4  # the glitch is there in the bag's own tf
    line = one_line_error(run_module("inspect", "--dataset", "--data", curated["data"], "--episodes", name, "--bag",
                                     curated["bags"]["clean"], "-o", tmp_path / "x.rrd"))
    assert "not the bag episode" in line and not (tmp_path / "x.rrd").exists()
