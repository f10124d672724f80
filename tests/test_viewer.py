"""inspect --dataset: a Rerun recording of the dataset's frames, read back with rerun's own reader."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from adlpipe.dataset import schema


def rows_and_values(rrd: Path) -> tuple[Counter, dict[str, list], list]:
    from rerun.chunk import RrdReader

    reader = RrdReader(str(rrd))
    rows: Counter = Counter()
    values: dict[str, list] = {}
    timelines: set = set()
    for chunk in reader.stream().to_chunks():
        rb = chunk.to_record_batch()
        entity = str(chunk.entity_path)
        rows[entity] += rb.num_rows
        timelines |= set(rb.schema.names)
        for name in rb.schema.names:
            if name in ("Scalars:scalars", "Points3D:positions", "LineStrips3D:strips"):
                values.setdefault(entity, []).extend(rb.column(name).to_pylist())
    return rows, values, reader.blueprints()


def test_the_dataset_recording_holds_every_frame_of_the_selection(ingested: Path, tmp_path: Path) -> None:
    from conftest import run_module

    with schema.open_dataset(ingested) as f:
        names = [r["name"] for r in schema.read_catalog(f)]  # catalog order: what --episodes indices count in
        frames = {n: len(f[schema.EPISODES][n]["frames/t"]) for n in names}
        joint1 = np.concatenate([f[schema.EPISODES][n]["frames/joint_pos"][:, 0] for n in names])
        ee = {n: f[schema.EPISODES][n]["frames/ee_pos"][()] for n in names}
        has_depth = {n: bool((f[schema.EPISODES][n]["frames/depth_index"][()] >= 0).all()) for n in names}
    rrd = tmp_path / "data.rrd"
    proc = run_module("inspect", "--dataset", "--data", ingested, "-o", rrd, check=True)
    total = sum(frames.values())
    assert f"{len(names)} episode(s), {total} frames" in proc.stdout
    rows, values, blueprints = rows_and_values(rrd)
    for entity in ("/world/camera/image/rgb", "/world/camera/image/ee", "/world/ee", "/joints/joint1", "/gripper"):
        assert rows[entity] == total, (entity, rows)
    assert all(has_depth.values()) and rows["/world/camera/image/depth"] == total
    for entity in ("/world/camera", "/world/camera/image", "/world/ee_path", "/task"):
        assert rows[entity] == len(names), (entity, rows)  # once per episode: camera, frustum, path, task
    assert rows["/world/camera/image/affordance"] >= len(names)
    np.testing.assert_allclose(np.ravel(values["/joints/joint1"]), joint1, rtol=1e-6)
    assert len(blueprints) == 1

    one = tmp_path / "one.rrd"  # a selection by index and by name
    run_module("inspect", "--dataset", "--data", ingested, "--episodes", "2", names[0], "-o", one, check=True)
    rows, values, _ = rows_and_values(one)
    assert rows["/world/camera/image/rgb"] == frames[names[2]] + frames[names[0]]
    first = np.array(values["/world/ee"][0]).reshape(-1)
    np.testing.assert_allclose(first, ee[names[2]][0], rtol=1e-5)  # in the order asked for


def test_asking_for_a_missing_episode_is_one_line(ingested: Path, tmp_path: Path) -> None:
    from conftest import one_line_error, run_module

    line = one_line_error(run_module("inspect", "--dataset", "--data", ingested, "--episodes", "7", "-o",
                                     tmp_path / "x.rrd"))
    assert "episode index 7 out of range" in line and not (tmp_path / "x.rrd").exists()
