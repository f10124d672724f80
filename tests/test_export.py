"""The LeRobot v3 export, read back with pyarrow and PyAV against the source dataset and the v3 layout (LeRobot
itself does not install beside torch 2.13: bench/lerobot_check.py loads the export with LeRobotDataset in its own
venv). Its cameras as video (the default) and as PNG images."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from adlpipe.dataset import schema
from adlpipe.export import export_lerobot


@pytest.fixture(scope="module")
def exported(ingested: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("lerobot") / "adl"
    export_lerobot(ingested, out, video=False)
    return out


def test_the_cameras_are_video_as_lerobot_records_them(ingested: Path, tmp_path: Path) -> None:
    import av

    out = tmp_path / "adl"
    export_lerobot(ingested, out)
    info = json.loads((out / "meta" / "info.json").read_text())
    feat = info["features"]["observation.images.rgb"]
    assert feat["dtype"] == "video" and feat["info"]["video.codec"] == "h264" and feat["info"]["video.fps"] == 5
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    data = pq.read_table(out / "data" / "chunk-000" / "file-000.parquet")
    assert "observation.images.rgb" not in data.column_names  # the frames live in the video
    assert "observation.images.depth" in data.column_names  # depth stays lossless PNG
    eps = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    with av.open(str(out / "videos" / "observation.images.rgb" / "chunk-000" / "file-000.mp4")) as c:
        decoded = [(float(fr.pts * fr.time_base), fr.to_ndarray(format="rgb24")) for fr in c.decode(video=0)]
    assert len(decoded) == info["total_frames"]
    stamps = np.array([t for t, _ in decoded])
    ts = data.column("timestamp").to_numpy().astype(np.float64)
    errors = []
    with schema.open_dataset(ingested) as f:
        for ep in eps:
            g = f[schema.EPISODES][ep["adlpipe/name"]]
            rgb = g["frames/rgb"][()]
            for k, t in enumerate(ts[ep["dataset_from_index"]:ep["dataset_to_index"]]):
                # where LeRobot's decoder looks for the frame: the episode's offset in the file plus its timestamp
                j = int(np.abs(stamps - (ep["videos/observation.images.rgb/from_timestamp"] + t)).argmin())
                assert abs(stamps[j] - ep["videos/observation.images.rgb/from_timestamp"] - t) < 1e-4
                errors.append(np.abs(decoded[j][1].astype(float) - rgb[k]).mean())
            lo, hi = ep["dataset_from_index"], ep["dataset_to_index"]
            cam_t = data.column("observation.camera_timestamp").to_numpy()[lo:hi]
            assert cam_t == pytest.approx(g["frames/t"][()], abs=1e-6)  # the camera's stamps kept beside LeRobot's
            K = g["K"][()]
            assert ep["adlpipe/camera/K"] == pytest.approx(K.ravel().tolist())
    assert max(errors) < 4.0  # grey levels: H.264 at CRF 15, yuv420p
    cal = info["calibration"]["camera"]
    assert cal["intrinsics"]["fx"] > 0 and len(cal["extrinsics"]) == 16 and cal["extrinsics_frames"]["parent"]
    card = (out / "README.md").read_text()
    assert card.startswith("---\nlicense: other\ntask_categories:\n- robotics\ntags:\n- LeRobot")
    assert '"codebase_version": "v3.0"' in card


def source(ingested: Path) -> list[dict]:
    """Per episode, in catalog order: task, frame count, state, first RGB frame, first depth image (mm)."""
    out = []
    with schema.open_dataset(ingested) as f:
        for n in schema.episode_names(f):
            g = f[schema.EPISODES][n]
            fr = g["frames"]
            state = np.concatenate([fr["ee_pos"][()], fr["joint_pos"][()], fr["gripper"][()][:, None]], 1)
            out.append({"task": str(g.attrs["task"]), "T": len(fr["t"]), "state": state, "rgb0": fr["rgb"][0],
                        "t": fr["t"][()],
                        "depth0": fr["depth"][int(fr["depth_index"][0])] if fr["depth_index"][0] >= 0 else None})
    return out


def test_the_v3_layout_holds_every_frame_with_its_task(exported: Path, ingested: Path) -> None:
    src = source(ingested)
    info = json.loads((exported / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0"
    assert info["total_episodes"] == len(src) == 3
    assert info["total_frames"] == sum(e["T"] for e in src)
    assert info["fps"] == 5 and info["video_path"] is None
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    for key in ("observation.images.rgb", "observation.state", "action", "timestamp", "frame_index",
                "episode_index", "index", "task_index"):
        assert key in info["features"], key
    tasks = pq.read_table(exported / "meta" / "tasks.parquet")
    assert tasks.column("task").to_pylist() == sorted({e["task"] for e in src})
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["task"]
    eps = pq.read_table(exported / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    data = pq.read_table(exported / "data" / "chunk-000" / "file-000.parquet")
    assert data.num_rows == info["total_frames"]
    assert data.column("index").to_pylist() == list(range(data.num_rows))
    task_of = dict(zip(tasks.column("task").to_pylist(), tasks.column("task_index").to_pylist(), strict=True))
    ep_col, ti_col = data.column("episode_index").to_pylist(), data.column("task_index").to_pylist()
    for i, (ep, s) in enumerate(zip(eps, src, strict=True)):
        assert ep["episode_index"] == i and ep["length"] == s["T"] and ep["tasks"] == [s["task"]]
        lo, hi = ep["dataset_from_index"], ep["dataset_to_index"]
        assert hi - lo == s["T"] and ep_col[lo:hi] == [i] * s["T"] and ti_col[lo:hi] == [task_of[s["task"]]] * s["T"]
        frames = data.column("frame_index").to_pylist()[lo:hi]
        assert frames == list(range(s["T"]))
        state = np.array(data.column("observation.state").to_pylist()[lo:hi], np.float32)
        np.testing.assert_array_equal(state, s["state"].astype(np.float32))
        action = np.array(data.column("action").to_pylist()[lo:hi], np.float32)
        np.testing.assert_array_equal(action[:-1], state[1:, :3])  # the next end-effector position
        rgb = cv2.imdecode(np.frombuffer(data.column("observation.images.rgb")[lo].as_py()["bytes"], np.uint8),
                           cv2.IMREAD_UNCHANGED)[..., ::-1]
        np.testing.assert_array_equal(rgb, s["rgb0"])  # PNG: lossless
        if s["depth0"] is not None:
            d = cv2.imdecode(np.frombuffer(data.column("observation.images.depth")[lo].as_py()["bytes"], np.uint8),
                             cv2.IMREAD_UNCHANGED)
            assert d.dtype == np.uint16
            np.testing.assert_array_equal(d, s["depth0"])
    hf = json.loads(data.schema.metadata[b"huggingface"])["info"]["features"]
    assert hf["observation.images.rgb"] == {"_type": "Image"}


def test_stats_equal_the_source(exported: Path, ingested: Path) -> None:
    src = source(ingested)
    stats = json.loads((exported / "meta" / "stats.json").read_text())
    state = np.concatenate([e["state"] for e in src]).astype(np.float64)
    s = stats["observation.state"]
    np.testing.assert_allclose(s["min"], np.nanmin(state, 0), rtol=1e-6)
    np.testing.assert_allclose(s["max"], np.nanmax(state, 0), rtol=1e-6)
    np.testing.assert_allclose(s["mean"], np.nanmean(state, 0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(s["std"], np.nanstd(state, 0), rtol=1e-4, atol=1e-6)
    assert s["count"] == [len(state)]
    with schema.open_dataset(ingested) as f:  # 64 px frames: every pixel counts (larger ones are subsampled)
        pixels = np.concatenate([f[schema.EPISODES][n]["frames/rgb"][()].reshape(-1, 3) / 255.0
                                 for n in schema.episode_names(f)])
    rgb = stats["observation.images.rgb"]
    assert np.array(rgb["mean"]).shape == (3, 1, 1)  # per channel, as LeRobot keeps image statistics
    np.testing.assert_allclose(np.ravel(rgb["mean"]), pixels.mean(0), rtol=1e-6)
    np.testing.assert_allclose(np.ravel(rgb["std"]), pixels.std(0), rtol=1e-5)
    np.testing.assert_allclose(np.ravel(rgb["max"]), pixels.max(0))
    stamps = np.concatenate([e["t"] for e in src])  # the camera's own stamps, as exported
    cam = stats["observation.camera_timestamp"]
    assert cam["count"] == [len(stamps)] and cam["min"] == [0.0]
    np.testing.assert_allclose(cam["max"], [stamps.max()], rtol=1e-6)


def test_an_export_never_overwrites_and_leaves_nothing_when_it_fails(ingested: Path, tmp_path: Path) -> None:
    from conftest import one_line_error, run_module

    (tmp_path / "taken").mkdir()
    assert "already exists" in one_line_error(run_module("export", ingested, tmp_path / "taken"))
    line = one_line_error(run_module("export", ingested, tmp_path / "new", "--episodes", "no-such-episode"))
    assert "no-such-episode" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


@pytest.mark.parametrize(("damage", "needle"), [
    ("no-frames", "no frames group"),
    ("no-gripper", "frames lack gripper"),
    ("short-ee", "ee_pos"),
    ("nan-stamp", "not finite or go backwards"),
])
def test_a_malformed_episode_is_one_line_and_leaves_nothing(ingested: Path, tmp_path: Path, damage: str,
                                                            needle: str) -> None:
    import h5py
    from conftest import copy_dataset, one_line_error, run_module

    data = copy_dataset(ingested, tmp_path / "adl.h5")
    with h5py.File(data) as f:
        name = schema.episode_names(f)[1]
        path = schema.episode_path(data, f, name)
    with h5py.File(path, "r+") as f:
        fr = f[schema.EPISODES][name]["frames"]
        if damage == "no-frames":
            del f[schema.EPISODES][name]["frames"]
        elif damage == "no-gripper":
            del fr["gripper"]
        elif damage == "short-ee":
            ee = fr["ee_pos"][()][:-2]
            del fr["ee_pos"]
            fr["ee_pos"] = ee
        else:
            t = fr["t"][()]
            t[3] = np.nan
            fr["t"][...] = t
    line = one_line_error(run_module("export", data, tmp_path / "out"))
    assert name in line and needle in line
    assert not (tmp_path / "out").exists() and not (tmp_path / ".out.tmp").exists()


def test_an_episode_named_twice_is_exported_once_and_a_second_export_waits_its_turn(ingested: Path,
                                                                                     tmp_path: Path) -> None:
    from conftest import one_line_error, run_module

    from adlpipe.plumbing.lock import exclusive

    with schema.open_dataset(ingested) as f:
        name = schema.episode_names(f)[0]
    info = export_lerobot(ingested, tmp_path / "twice", [name, name])
    assert info["total_episodes"] == 1
    with exclusive(tmp_path / "busy"):  # another export holds this OUT: the second stops, deleting nothing
        line = one_line_error(run_module("export", ingested, tmp_path / "busy"))
    assert "in use by pid" in line and not (tmp_path / "busy").exists()


def test_maps_as_video_or_left_out(ingested: Path, tmp_path: Path) -> None:
    """--maps video: depth (a grey level = 20 mm) and affordance (0-255) as MP4 beside the camera's, none in the data
    files; --maps none: neither anywhere. The decoded depth matches the source within the 1 cm step and the codec."""
    import av

    out = tmp_path / "video"
    export_lerobot(ingested, out, maps="video")
    info = json.loads((out / "meta" / "info.json").read_text())
    depth, aff = info["features"]["observation.images.depth"], info["features"]["observation.images.affordance"]
    assert depth["dtype"] == aff["dtype"] == "video"
    assert depth["info"]["video.is_depth_map"] and depth["info"]["mm_per_level"] == 20
    assert not aff["info"]["video.is_depth_map"]
    data = pq.read_table(out / "data" / "chunk-000" / "file-000.parquet")
    assert not {"observation.images.depth", "observation.images.affordance"} & set(data.column_names)
    with av.open(str(out / "videos" / "observation.images.depth" / "chunk-000" / "file-000.mp4")) as c:
        frames = [fr.to_ndarray(format="rgb24") for fr in c.decode(video=0)]
    assert len(frames) == info["total_frames"]
    first = source(ingested)[0]
    assert first["depth0"] is not None  # the recorder's bags carry depth
    level = first["depth0"].astype(float) / 20
    seen = level < 255
    assert seen.mean() > 0.9 and np.abs(frames[0][..., 0].astype(float) - level)[seen].mean() < 1.5  # grey levels
    stats = json.loads((out / "meta" / "stats.json").read_text())
    assert "observation.images.affordance" in stats and "observation.images.depth" in stats

    bare = tmp_path / "none"
    export_lerobot(ingested, bare, maps="none")
    feats = json.loads((bare / "meta" / "info.json").read_text())["features"]
    assert "observation.images.depth" not in feats and "observation.images.affordance" not in feats
    assert not (bare / "videos" / "observation.images.depth").exists()
