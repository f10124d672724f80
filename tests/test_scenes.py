"""The same scenes on every host: the split keyed on the recordings, and replay's fresh scenes drawn by the
recorder's own generator and stored as ingest stores a first frame."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import run_module

from adlpipe.dataset import schema
from adlpipe.evaluation.scenes import fresh_scene, recorded_scene

TASKS = ["comb the hair", "pass the water"]


def record_and_split(root: Path, fmt: str) -> tuple[dict, dict[str, str]]:
    """Record 4 episodes of two tasks in `fmt`, ingest and split them; (split, episode name -> bag stem)."""
    run_module("record", "--out", root / "bags", "--episodes", "4", "--size", "32", "--camera-hz", "2",
               "--format", fmt, "--tasks", *TASKS, check=True)
    run_module("ingest", *sorted((root / "bags").iterdir()), "-o", root / "adl.h5", "--size", "32", check=True)
    run_module("split", root / "adl.h5", "-o", root / "split.json", "--test-fraction", "0.5", check=True)
    with schema.open_dataset(root / "adl.h5") as f:
        stems = {n: Path(str(f[schema.EPISODES][n].attrs["source_path"])).name.split(".")[0]
                 for n in schema.episode_names(f)}
    return json.loads((root / "split.json").read_text()), stems


def test_the_split_follows_the_recordings_not_their_bytes(tmp_path: Path) -> None:
    """The same demonstrations written as MCAP and as ROS1 bags differ in every byte (other sha256, other episode
    names) and split alike: the split is keyed on the recording (bag file name), not on the hash."""
    a, stems_a = record_and_split(tmp_path / "mcap", "mcap")
    b, stems_b = record_and_split(tmp_path / "bag", "bag")
    assert not set(stems_a) & set(stems_b)  # no episode name in common
    for part in ("train", "test"):
        assert sorted(stems_a[n] for n in a[part]) == sorted(stems_b[n] for n in b[part])
    assert len(a["test"]) == 4


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("scenes")
    run_module("record", "--out", root / "bags", "--episodes", "1", "--size", "48", "--camera-hz", "2",
               "--tasks", *TASKS, check=True)
    run_module("ingest", *sorted((root / "bags").iterdir()), "-o", root / "adl.h5", "--size", "32", check=True)
    return root / "adl.h5"


def test_a_scene_drawn_again_is_what_ingest_stored_of_its_recording(recorded: Path) -> None:
    """The recorder's demonstration 0 drawn again by replay's scene builder gives, on this host, the very first frame
    (resized from the 48 px camera to the 32 px store), affordance, depth, object poses and waypoints that record +
    ingest stored: fresh scenes reach the policy by the recordings' path."""
    with schema.open_dataset(recorded) as f:
        eps = [schema.read_episode(f, n) for n in schema.episode_names(f)]
    for ep in eps:
        sc = recorded_scene(ep.task, 0, 0, 48, 32, 32)
        assert np.array_equal(sc.rgb, ep.rgb) and np.array_equal(sc.affordance, ep.affordance)
        assert np.array_equal(np.isnan(sc.depth), np.isnan(ep.depth))
        assert np.nanmax(np.abs(sc.depth - ep.depth)) == 0
        assert sc.object_names == ep.object_names and np.abs(sc.objects - ep.objects).max() < 1e-9
        assert abs(sc.duration_s - ep.duration_s) < 1e-6 and np.abs(sc.traj3d - ep.traj3d).max() < 1e-6
        assert np.abs(sc.traj2d - ep.traj2d).max() < 1e-3


def test_fresh_scenes_are_seeded_and_new() -> None:
    a, b = fresh_scene("pass the water", 0, 0, 32, 32, 32), fresh_scene("pass the water", 0, 0, 32, 32, 32)
    assert a.name == "fresh/pass_the_water/1000000"
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.objects, b.objects)
    other, recorded0 = fresh_scene("pass the water", 1, 0, 32, 32, 32), recorded_scene("pass the water", 0, 0, 32,
                                                                                        32, 32)
    cup = a.object_names.index("cup")
    for s in (other, recorded0):  # another draw puts the cup elsewhere
        assert np.linalg.norm(s.objects[cup, :3] - a.objects[cup, :3]) > 1e-3
