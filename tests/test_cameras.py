"""Several cameras per episode (issue P.3): a scene camera and a wrist camera moving with the arm, recorded into one
bag with the real writers (mcap, rosbags); each camera's frames, model, pose per frame and trajectory pixels."""

from __future__ import annotations

from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import yaml
from conftest import one_line_error, run_module
from layouts import WRIST, Layout, topic_map, wrist_image, wrist_K, wrist_pose, write_layout_bag

from adlpipe.bags.topics import TopicMap
from adlpipe.dataset import schema
from adlpipe.geometry.transforms import in_camera, scale_intrinsics
from adlpipe.ingest import ingest
from adlpipe.plumbing.errors import AdlError

SIZE = 48
NAMES = {"mcap": "c.mcap", "bag": "c.bag", "db3": "c"}


def _map(tmp_path: Path, lay: Layout, **over: object) -> Path:
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(lay, **over)))
    return cfg


def _two_camera_dataset(tmp_path: Path, fmt: str) -> tuple[Path, Path, Layout]:
    lay = Layout(fmt=fmt, wrist=True)
    bag, _t, _p = write_layout_bag(tmp_path / NAMES[fmt], lay)
    out = tmp_path / "two.h5"
    c = ingest([bag], out, TopicMap.load(_map(tmp_path, lay)), n_waypoints=32, size=SIZE)
    assert c["new"] == 1, c
    return bag, out, lay


@pytest.mark.parametrize("fmt", ["mcap", "bag", "db3"])
def test_a_scene_and_a_wrist_camera_in_one_episode(tmp_path: Path, fmt: str) -> None:
    bag, out, lay = _two_camera_dataset(tmp_path, fmt)
    one = tmp_path / "one.h5"  # the same bag through a one-camera map: the wrist's topics are not read
    assert ingest([bag], one, TopicMap.load(_map(tmp_path, Layout(fmt=fmt))), n_waypoints=32, size=SIZE)["new"] == 1
    with h5py.File(out) as f, h5py.File(one) as g1:
        name = schema.episode_names(f)[0]
        g, s = f["episodes"][name], g1["episodes"][name]
        assert schema.camera_names(g) == ["scene", "wrist"] and schema.camera_names(s) == ["camera"]
        # the scene camera is stored exactly as a one-camera ingest stores it
        for key in ("rgb", "traj2d", "traj3d", "K", "T_base_camera", "frames/rgb", "frames/t", "frames/ee_pos"):
            assert np.array_equal(g[key][()], s[key][()]), key
        ep = schema.read_episode(f, name)
        wrist = ep.cameras[0]
        assert wrist.name == "wrist" and wrist.camera_frame == WRIST["frame"]
        fr = g["cameras/wrist/frames"]
        t = fr["t"][()]
        k = np.round(t * lay.wrist_hz).astype(int)
        assert np.allclose(t, k / lay.wrist_hz, atol=1e-6) and len(t) >= 40
        assert k[0] == 0 and np.all(np.diff(k) == 1)  # every wrist frame from the first image to the path's end
        for i in (0, len(t) // 2, len(t) - 1):  # its own frames, resized as the scene camera's are
            want = cv2.resize(wrist_image(int(k[i])), (SIZE, SIZE), interpolation=cv2.INTER_AREA)
            assert np.array_equal(fr["rgb"][i], want), i
        # it moves with the arm: its pose per frame is the true wrist pose (tf interpolated at 50 Hz)
        truth = np.stack([wrist_pose(float(x), lay) for x in t])
        assert np.abs(fr["T_base_camera"][()] - truth).max() < 1e-3
        assert np.linalg.norm(truth[-1, :3, 3] - truth[0, :3, 3]) > 0.1
        # per scene frame, the wrist frame nearest in time (10 Hz against 15 Hz)
        scene_t = g["frames/t"][()]
        index = fr["index"][()]
        assert np.all(index >= 0) and np.abs(t[index] - scene_t).max() <= 1 / (2 * lay.wrist_hz) + 1e-6
        # its depth, synced to its own frames
        assert np.array_equal(fr["depth"][fr["depth_index"][()]][:, 0, 0], 400 + k)
        # the trajectory in the wrist camera's pixels, against OpenCV at its first-frame pose
        K = scale_intrinsics(wrist_K(), SIZE / WRIST["size"][0], SIZE / WRIST["size"][1])
        pc = in_camera(ep.traj3d.astype(float), wrist_pose(0.0, lay))
        want, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), K, np.zeros(5))
        assert np.abs(wrist.traj2d - want.reshape(-1, 2)).max() < 1e-3
        assert np.allclose(wrist.K, K)


def test_a_missing_camera_topic_is_one_line(tmp_path: Path) -> None:
    lay = Layout(wrist=False)
    bag, _t, _p = write_layout_bag(tmp_path / "c.mcap", lay)
    cfg = _map(tmp_path, Layout(wrist=True))
    with pytest.raises(AdlError, match="missing required topic.*/wrist/color/image_raw"):
        ingest([bag], tmp_path / "x.h5", TopicMap.load(cfg), size=SIZE)
    assert not (tmp_path / "x.h5").exists()


def test_a_camera_without_tf_is_one_line(tmp_path: Path) -> None:
    lay = Layout(wrist=True, wrist_tf=False)
    bag, _t, _p = write_layout_bag(tmp_path / "c.mcap", lay)
    out = one_line_error(run_module("ingest", str(bag), "-o", str(tmp_path / "x.h5"), "--config",
                                    str(_map(tmp_path, lay)), "--size", str(SIZE), "--workers", "1"))
    assert f"no tf chain from camera wrist's camera frame '{WRIST['frame']}'" in out, out
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize(("cameras", "needle"), [
    ([], "empty list"),
    ([{"name": "a b", "image": "/a", "camera_info": "/b"}], "letters, digits"),
    ([{"name": "a", "image": "/a"}], "'camera_info' is required"),
    ([{"name": "a", "image": "/a", "camera_info": "/b"}, {"name": "a", "image": "/c", "camera_info": "/d"}],
     "names repeat"),
    ([{"name": "a", "image": "/a", "camera_info": "/b"}, {"name": "b", "image": "/a", "camera_info": "/d"}],
     "share a topic"),
    ("scene", "must be a list"),
])
def test_a_bad_cameras_list_is_one_line(tmp_path: Path, cameras: object, needle: str) -> None:
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump({"cameras": cameras}))
    with pytest.raises(AdlError, match=needle) as e:
        TopicMap.load(cfg)
    assert str(cfg) in str(e.value)


def test_cameras_and_image_keys_together_are_refused(tmp_path: Path) -> None:
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump({"image": "/x", "cameras": [{"name": "a", "image": "/a", "camera_info": "/b"}]}))
    with pytest.raises(AdlError, match="not both"):
        TopicMap.load(cfg)


@pytest.fixture(scope="module")
def two_cameras(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _two_camera_dataset(tmp_path_factory.mktemp("two"), "mcap")[1]


def test_the_lerobot_export_has_one_image_key_per_camera(two_cameras: Path, tmp_path: Path) -> None:
    import json

    import pyarrow.parquet as pq

    from adlpipe.export import export_lerobot

    export_lerobot(two_cameras, tmp_path / "video")  # the default: one video per camera, depth as PNG
    info = json.loads((tmp_path / "video" / "meta" / "info.json").read_text())
    videos = sorted(k for k, v in info["features"].items() if v["dtype"] == "video")
    assert videos == ["observation.images.scene", "observation.images.wrist"]
    assert all((tmp_path / "video" / "videos" / k / "chunk-000" / "file-000.mp4").exists() for k in videos)
    assert sorted(info["calibration"]) == ["scene", "wrist"]
    export_lerobot(two_cameras, tmp_path / "le", video=False)  # lossless PNG in the data files
    info = json.loads((tmp_path / "le" / "meta" / "info.json").read_text())
    images = sorted(k for k, v in info["features"].items() if v["dtype"] == "image")
    assert images == ["observation.images.depth", "observation.images.scene", "observation.images.wrist"]
    data = pq.read_table(tmp_path / "le" / "data" / "chunk-000" / "file-000.parquet")
    with h5py.File(two_cameras) as f:
        g = f["episodes"][schema.episode_names(f)[0]]
        index = g["cameras/wrist/frames/index"][()]
        for i in (0, 7, len(index) - 1):  # frame i: the scene frame and the wrist frame nearest it, lossless
            for key, want in (("scene", g["frames/rgb"][i]), ("wrist", g["cameras/wrist/frames/rgb"][index[i]])):
                png = data.column(f"observation.images.{key}")[i].as_py()["bytes"]
                got = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)[..., ::-1]
                assert np.array_equal(got, want), (key, i)
    stats = json.loads((tmp_path / "le" / "meta" / "stats.json").read_text())
    assert "observation.images.wrist" in stats


def test_the_dataset_viewer_shows_each_camera(two_cameras: Path, tmp_path: Path) -> None:
    from test_viewer import rows_and_values

    with h5py.File(two_cameras) as f:
        g = f["episodes"][schema.episode_names(f)[0]]
        n_scene, n_wrist = len(g["frames/t"]), len(g["cameras/wrist/frames/t"])
        poses = g["cameras/wrist/frames/T_base_camera"][()]
    rrd = tmp_path / "two.rrd"
    run_module("inspect", "--dataset", "--data", two_cameras, "-o", rrd, check=True)
    rows, _values, blueprints = rows_and_values(rrd)
    assert rows["/world/camera/image/rgb"] == n_scene
    # the wrist camera's own frames, and its pose at each (it moves with the arm)
    assert rows["/world/cameras/wrist/image/rgb"] == rows["/world/cameras/wrist"] == n_wrist != n_scene
    assert rows["/world/cameras/wrist/image/ee"] == n_wrist
    assert np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3]) > 0.1
    assert len(blueprints) == 1


def test_a_model_sees_both_cameras_and_evaluate_scores_each(tmp_path: Path) -> None:
    """train --cameras scene wrist: each camera's first frame through the one shared encoder; evaluate gives px in
    the wrist camera too: the predicted 3D waypoints seen through it (the demonstration's own 3D path scores 0)."""
    import json

    bags = []
    for k, (task, duration) in enumerate([("wipe the table", 3.0), ("wipe the table", 3.2), ("pass the cup", 3.0),
                                          ("pass the cup", 3.2)]):
        lay = Layout(wrist=True, task=task, duration_s=duration)
        bags.append(write_layout_bag(tmp_path / f"b{k}.mcap", lay)[0])
    data = tmp_path / "two.h5"
    assert ingest(bags, data, TopicMap.load(_map(tmp_path, Layout(wrist=True))), n_waypoints=16, size=SIZE)["new"] == 4
    with h5py.File(data) as f:
        names = schema.episode_names(f)
    (tmp_path / "split.json").write_text(json.dumps({"train": names[::2], "test": names[1::2]}))
    common = ["--data", data, "--split", tmp_path / "split.json", "--epochs", "2", "--batch-size", "4",
              "--image-size", "32", "--val-fraction", "0"]
    run_module("train", "--model", "fm_cnn", *common, "--cameras", "scene", "wrist", "--out", tmp_path / "fm",
               check=True)
    from adlpipe.policy.checkpoint import load_policy

    policy, _ck = load_policy(tmp_path / "fm" / "model.pt")
    assert policy.cfg.cameras == ("scene", "wrist") and policy.encoder.stem[0].in_channels == 4
    run_module("evaluate", "--models", tmp_path / "fm", "--data", data, "--split", tmp_path / "split.json",
               "--steps", "1", "--best-of", "2", "--repeats", "2", "--metrics", tmp_path / "m.json", "--details",
               tmp_path / "d.json", "--plots", tmp_path / "p.csv", "--table", tmp_path / "t.md", check=True)
    row = json.loads((tmp_path / "d.json").read_text())["models"]["fm"]["best"]["euler/1"]
    wrist = row["px_by_camera"]["wrist"]
    assert wrist["n"] == 2 and wrist["px_ci"][0] <= wrist["px"] <= wrist["px_ci"][1] and wrist["px"] > 0
    assert "wrist px [95 %]" in (tmp_path / "t.md").read_text()
    from adlpipe.evaluation.accuracy import camera_px, other_views

    with h5py.File(data) as f:
        views = other_views(f, names)
        truth = np.stack([np.concatenate([f["episodes"][n]["traj2d"][()], f["episodes"][n]["traj3d"][()]], 1)
                          for n in names])
    assert list(views) == ["wrist"]
    assert camera_px(truth, views, SIZE)["wrist"]["px"] < 1e-3
    assert camera_px(truth + np.array([0, 0, 0.05, 0, 0]), views, SIZE)["wrist"]["px"] > 1.0  # 5 cm off: seen
    # closed loop: each camera's last two frames (the wrist's nearest the scene's), one shared encoder
    run_module("train", "--model", "fm_cnn", *common, "--closed-loop", "--target", "ee", "--cameras", "scene",
               "wrist", "--out", tmp_path / "cl", check=True)
    policy, ck = load_policy(tmp_path / "cl" / "model.pt")
    assert policy.cfg.views == 2 and policy.encoder.stem[0].in_channels == 8
    from adlpipe.dataset.loader import WindowDataset, Windows

    ds = WindowDataset(data, names[:1], ck["stats"], 32, Windows(2, 16, 10.0, "ee"), cameras=("scene", "wrist"))
    (obs, _state), _target = ds[5]
    assert obs.shape == (16, 32, 32)
    with h5py.File(data) as f:
        fr = f["episodes"][names[0]]["cameras/wrist/frames"]
        j = int(fr["index"][5])
        want = cv2.resize(fr["rgb"][j], (32, 32), interpolation=cv2.INTER_AREA).transpose(2, 0, 1) / 127.5 - 1
    np.testing.assert_allclose(obs[12:15].numpy(), want, atol=1e-6)  # the wrist's frame at the current step
    assert float(obs[15].max()) == -1.0  # its blank affordance channel
    # a camera the data lacks is one line
    line = one_line_error(run_module("train", "--model", "fm_cnn", *common, "--cameras", "scene", "side", "--out",
                                     tmp_path / "x"))
    assert "has no camera 'side'" in line


def test_doctor_and_verify_read_a_two_camera_dataset(tmp_path: Path) -> None:
    bag, out, _lay = _two_camera_dataset(tmp_path, "bag")
    proc = run_module("doctor", out, "--verify", bag, check=True)
    assert "1 episode(s) verified against their bags, 0 mismatch(es)" in proc.stdout  # the wrist camera too
    with h5py.File(out) as f:
        name = schema.episode_names(f)[0]
        file = schema.episode_path(out, f, name)
    with h5py.File(file, "r+") as f:
        f["episodes"][name]["cameras/wrist/frames/T_base_camera"][2, 0, 3] += 0.01
    proc = run_module("doctor", out, "--verify", bag)
    assert proc.returncode == 1 and "cameras/wrist/frames/T_base_camera: 1 value(s) differ" in proc.stdout
