"""Bags laid out as real robots publish them (issue H), written with the real writers: a Kinova Gen3 with an Azure
Kinect, RealSense and ZED cameras, Franka and UR frames; static tool frames, optional topics absent or null, tf
gaps, compressedDepth (PNG and RVL)."""

from __future__ import annotations

import itertools
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from conftest import REPO, one_line_error, run_module
from layouts import Layout, topic_map, write_layout_bag

from adlpipe.bags.topics import TopicMap
from adlpipe.dataset import schema
from adlpipe.ingest import ingest
from adlpipe.plumbing.errors import AdlError

PRESETS = REPO / "pipelines" / "presets"


def _ingest(bag: Path, tmp_path: Path, tm: TopicMap, **kw: object) -> schema.Episode:
    out = tmp_path / "x.h5"
    c = ingest([bag], out, tm, n_waypoints=32, size=48, **kw)
    assert c["new"] == 1, c
    with h5py.File(out) as f:
        return schema.read_episode(f, schema.episode_names(f)[0])


def _expected_path(ee_t: np.ndarray, ee_p: np.ndarray, ep: schema.Episode) -> np.ndarray:
    tq = np.linspace(0, ep.duration_s, 32)
    return np.stack([np.interp(tq, ee_t, ee_p[:, k]) for k in range(3)], axis=1)


@pytest.mark.parametrize("fmt", ["mcap", "db3", "bag"])
def test_kinova_azure_kinect_with_tool_frame_on_tf_static(tmp_path: Path, fmt: str) -> None:
    """tool_frame hangs 18 cm (plus 6 cm) off the moving bracelet_link by fixed joints on /tf_static: its path is the
    bracelet's path composed with the offsets, within 1 mm of the truth."""
    lay = Layout(fmt=fmt)
    bag, ee_t, ee_p = write_layout_bag(tmp_path / ("k.mcap" if fmt == "mcap" else "k.bag" if fmt == "bag" else "k"),
                                       lay)
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(lay)))
    ep = _ingest(bag, tmp_path, TopicMap.load(cfg))
    err = np.linalg.norm(ep.traj3d - _expected_path(ee_t, ee_p, ep), axis=1).max()
    assert err < 1e-3, err
    # the bracelet alone would be 24 cm away: the offset is really there
    assert np.linalg.norm(ep.traj3d[0] - ee_p[0]) < 1e-3
    assert ep.depth is not None and ep.joint_pos.shape[1] == 7


@pytest.mark.parametrize(("fmt", "root"), [("mcap", "world"), ("bag", "map"), ("db3", "odom")])
def test_camera_and_robot_under_a_common_root(tmp_path: Path, fmt: str, root: str) -> None:
    """A scene camera fixed to the room and the robot base both hang below world/map/odom: the camera's pose in the
    base frame is composed through their common ancestor, and the episode equals the one whose camera hangs off the
    base directly (same pose, same trajectory, same pixels)."""
    name = {"mcap": "r.mcap", "bag": "r.bag", "db3": "r"}[fmt]
    (tmp_path / "direct").mkdir()
    (tmp_path / "rooted").mkdir()
    direct, _t, _p = write_layout_bag(tmp_path / "direct" / name, Layout(fmt=fmt))
    rooted, ee_t, ee_p = write_layout_bag(tmp_path / "rooted" / name, Layout(fmt=fmt, root=root))
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(Layout(fmt=fmt))))
    a = _ingest(direct, tmp_path / "direct", TopicMap.load(cfg))
    b = _ingest(rooted, tmp_path / "rooted", TopicMap.load(cfg))
    assert np.allclose(a.T_base_camera, b.T_base_camera, atol=1e-9)
    assert np.abs(b.traj2d - a.traj2d).max() < 1e-6 and np.abs(b.traj3d - a.traj3d).max() < 1e-9
    assert np.linalg.norm(b.traj3d - _expected_path(ee_t, ee_p, b), axis=1).max() < 1e-3


LENSES = {  # a typical plumb_bob lens, an Azure Kinect's rational_polynomial colour camera, a fisheye
    "plumb_bob": (-0.28, 0.07, 1e-4, -2e-4, 0.0),
    "rational_polynomial": (0.52, -2.6, 6e-4, -3e-4, 1.5, 0.4, -2.4, 1.4),
    "equidistant": (-0.02, 0.03, -0.01, 0.002),
}


@pytest.mark.parametrize(("fmt", "model"), [("mcap", "plumb_bob"), ("bag", "rational_polynomial"),
                                            ("db3", "equidistant")])
def test_traj2d_is_where_the_point_appears_through_the_lens(tmp_path: Path, fmt: str, model: str) -> None:
    """CameraInfo's distortion model and d are kept beside K, and traj2d is the distorted projection, as
    cv2.projectPoints (cv2.fisheye for equidistant) computes it from the stored K and camera pose."""
    import cv2

    name = {"mcap": "l.mcap", "bag": "l.bag", "db3": "l"}[fmt]
    bag, _t, _p = write_layout_bag(tmp_path / name, Layout(fmt=fmt, lens=(model, LENSES[model]),
                                                                top_down=True))
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(Layout(fmt=fmt))))
    ep = _ingest(bag, tmp_path, TopicMap.load(cfg))
    assert ep.lens.model == model and ep.lens.D == pytest.approx(LENSES[model])
    inv = np.linalg.inv(ep.T_base_camera)
    pc = ep.traj3d.astype(float) @ inv[:3, :3].T + inv[:3, 3]
    zero = np.zeros(3)
    if model == "equidistant":
        want, _ = cv2.fisheye.projectPoints(pc[:, None], zero, zero, ep.K, np.array(LENSES[model]))
    else:
        want, _ = cv2.projectPoints(pc, zero, zero, ep.K, np.array(LENSES[model]))
    pinhole = pc @ ep.K.T
    pinhole = pinhole[:, :2] / pinhole[:, 2:]
    inside = ((pinhole >= -0.5) & (pinhole <= 47.5)).all(1) & (pc[:, 2] > 0)
    assert inside.sum() >= 8  # most of the path is in view
    assert np.abs(ep.traj2d[inside] - want.reshape(-1, 2)[inside]).max() < 1e-3
    shift = np.linalg.norm(ep.traj2d[inside] - pinhole[inside], axis=1).max()
    assert shift > 0.3, shift  # the lens really moves the points at this 48 px size
    # outside the image the lens model does not hold: a point whose distorted and pinhole projections both leave
    # the image keeps its pinhole projection (finite); one a barrel lens still shows at the image's edge has its
    # distorted one
    want = want.reshape(-1, 2)
    shown = (((want >= -0.5) & (want <= 47.5)).all(1) | inside) & (pc[:, 2] > 0)
    assert np.allclose(ep.traj2d[~shown], pinhole[~shown], atol=1e-2)
    either = np.isclose(ep.traj2d, want, atol=1e-3).all(1) | np.isclose(ep.traj2d, pinhole, atol=1e-2).all(1)
    assert either.all() and np.isfinite(ep.traj2d).all()
    with h5py.File(tmp_path / "x.h5") as f:  # stored beside K
        g = f["episodes"][schema.episode_names(f)[0]]
        assert g.attrs["distortion_model"] == model and len(g["D"]) == len(LENSES[model])


def test_an_unknown_distortion_model_is_one_line(tmp_path: Path) -> None:
    bag, _t, _p = write_layout_bag(tmp_path / "u.mcap", Layout(lens=("kannala_brandt_x", (0.1, 0.1, 0.0, 0.0))))
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(Layout())))
    proc = run_module("ingest", bag, "-o", tmp_path / "x.h5", "--config", cfg, "--size", "48")
    line = one_line_error(proc)
    assert proc.returncode == 2 and "distortion_model 'kannala_brandt_x'" in line and "camera_info" in line
    assert not (tmp_path / "x.h5").exists()


OPTIONAL = ["depth", "affordance", "joints", "task", "tf_static"]


@pytest.mark.parametrize(("key", "how"), list(itertools.product(OPTIONAL, ["absent", "null"])))
def test_every_optional_topic_may_be_absent_or_null(tmp_path: Path, key: str, how: str) -> None:
    lay = Layout(depth=None if key == "depth" and how == "absent" else "16UC1",
                 joints=not (key == "joints" and how == "absent"),
                 task=None if key == "task" and how == "absent" else "wipe the table")
    if key == "tf_static":  # without /tf_static the end effector must be a moving frame
        lay = Layout(robot="ur", depth="16UC1")
    bag, _t, _p = write_layout_bag(tmp_path / "b.mcap", lay)
    m = topic_map(lay)
    if key == "tf_static":
        m.update(ee_frame="wrist_3_link", tf_static=None if how == "null" else "/not_recorded_static")
        m["base_frame"] = "base_link"
    elif how == "null":
        m[key] = None
    elif key == "affordance":
        m[key] = "/adl/affordance"  # the map names it, the bag lacks it
    elif key == "joints":
        m[key] = "/joint_states"  # default name while the bag has /my_gen3/joint_states: absent
    tm = TopicMap(**m)
    if key == "tf_static":  # the camera hangs off tf_static: without it there is no camera pose, said in one line
        with pytest.raises(AdlError, match="no tf chain from camera frame"):
            _ingest(bag, tmp_path, tm)
        return
    ep = _ingest(bag, tmp_path, tm, task=None if key != "task" else "wipe the table")
    if key == "joints":
        assert ep.joint_pos.shape == (0, 0) and ep.joint_names == []
    if key == "depth":
        assert ep.depth is None
    assert ep.traj3d.shape == (32, 3)


def test_absent_joint_states_do_not_take_down_a_parallel_batch(tmp_path: Path) -> None:
    bags = []
    for i, joints in enumerate([True, False, True]):
        bags.append(write_layout_bag(tmp_path / f"b{i}.mcap", Layout(joints=joints, duration_s=1.0 + i))[0])
    cfg = tmp_path / "m.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(Layout())))
    proc = run_module("ingest", *bags, "-o", tmp_path / "x.h5", "--config", cfg, "--workers", "2", "--size", "48",
                      check=True)
    assert "3 episode(s) added" in proc.stdout


def test_a_gap_in_the_end_effector_tf_is_refused_or_kept_with_a_note(tmp_path: Path) -> None:
    lay = Layout(tf_gap=(1.0, 3.0), duration_s=4.0)
    bag, _t, _p = write_layout_bag(tmp_path / "g.mcap", lay)
    tm = TopicMap(**topic_map(lay))
    with pytest.raises(AdlError, match=r"g.mcap: 2\.0\d s gap in the tf of 'bracelet_link'.*max_tf_gap_s 0.2"):
        _ingest(bag, tmp_path, tm)
    ep = _ingest(bag, tmp_path, tm, allow_tf_gaps=True)
    assert "bridged a 2.0" in ep.note
    assert _ingest(bag, tmp_path / "wide", TopicMap(**topic_map(lay, max_tf_gap_s=2.5))).note == ""


@pytest.mark.parametrize("depth", ["compressed16", "compressed32", "rvl16", "rvl32", "32FC1"])
def test_depth_as_real_cameras_publish_it(tmp_path: Path, depth: str) -> None:
    lay = Layout(depth=depth, size=(40, 30))
    bag, _t, _p = write_layout_bag(tmp_path / "d.mcap", lay)
    ep = _ingest(bag, tmp_path, TopicMap(**topic_map(lay)))
    truth = np.full((30, 40), 1.5, np.float32) + np.linspace(0, 1, 40, dtype=np.float32)
    # quantised inverse depth (32FC1 compressedDepth) is coarse far away, as image_transport makes it
    tol = 0.2 if depth.endswith("32") else 1e-3
    d = ep.depth  # stored at 48 px (nearest neighbour): compare row statistics
    assert np.isnan(d[0]).all() and not np.isnan(d[-1]).any()
    assert abs(float(np.nanmin(d)) - 1.5) < tol and abs(float(np.nanmax(d)) - float(truth.max())) < tol


@pytest.mark.parametrize(("camera", "robot"), [("azure_kinect", "kinova_gen3"), ("realsense", "kinova_gen3"),
                                               ("zed", "kinova_gen3"), ("azure_kinect", "franka"),
                                               ("azure_kinect", "ur")])
def test_presets_read_bags_with_their_drivers_names(tmp_path: Path, camera: str, robot: str) -> None:
    lay = Layout(camera=camera, robot=robot, depth="32FC1" if camera == "zed" else "16UC1")
    bag, ee_t, ee_p = write_layout_bag(tmp_path / "p.mcap", lay)
    proc = run_module("ingest", bag, "-o", tmp_path / "x.h5", "--config", PRESETS / f"{camera}.yaml", "--config",
                      PRESETS / f"{robot}.yaml", "--size", "48", "--task", "wipe", check=True)
    assert "1 episode(s) added" in proc.stdout
    with h5py.File(tmp_path / "x.h5") as f:
        ep = schema.read_episode(f, schema.episode_names(f)[0])
    assert np.linalg.norm(ep.traj3d - _expected_path(ee_t, ee_p, ep), axis=1).max() < 1e-3
    assert ep.depth is not None


BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi", strict=True))


@pytest.mark.parametrize(("content", "needle"), [
    ("image: 5\n", "'image' must be a topic or frame name"),
    ("sync_tolerance_s: fast\n", "'sync_tolerance_s' must be a non-negative number"),
    ("image: null\n", "'image' cannot be null"),
    ("ee_frame: [a, b]\n", "'ee_frame' must be a topic or frame name"),
    # a billion-laughs alias bomb: refused before it is expanded (it would take minutes and gigabytes)
    (BOMB, "uses YAML aliases"),
    ("image: " + "x" * (1 << 21) + "\n", "over 1 MB; not read"),
])
def test_a_topic_map_with_wrong_types_is_one_line(tmp_path: Path, content: str, needle: str) -> None:
    cfg = tmp_path / "m.yaml"
    cfg.write_text(content)
    line = one_line_error(run_module("ingest", tmp_path / "none.mcap", "-o", tmp_path / "x.h5", "--config", cfg))
    assert needle in line


def test_a_foxy_era_rosbag2_with_old_type_names_reads(tmp_path: Path) -> None:
    """metadata.yaml and the db3 topics table name types 'sensor_msgs/Image' (no /msg/), as older rosbag2 wrote."""
    import re
    import sqlite3

    lay = Layout(fmt="db3", duration_s=1.0)
    bag, ee_t, ee_p = write_layout_bag(tmp_path / "old", lay)
    old = lambda text: re.sub(r"(\w+)/msg/(\w+)", r"\1/\2", text)  # noqa: E731
    meta = bag / "metadata.yaml"
    meta.write_text(old(meta.read_text()))
    con = sqlite3.connect(next(bag.glob("*.db3")))
    for i, ty in con.execute("select id, type from topics").fetchall():
        con.execute("update topics set type=? where id=?", (old(ty), i))
    con.commit()
    con.close()
    assert "sensor_msgs/Image" in meta.read_text()
    ep = _ingest(bag, tmp_path, TopicMap(**topic_map(lay)))
    assert np.linalg.norm(ep.traj3d - _expected_path(ee_t, ee_p, ep), axis=1).max() < 1e-3


@pytest.mark.parametrize("mode", ["MESSAGE", "FILE"])
def test_a_compressed_rosbag2_split_given_as_a_bare_file_says_so(tmp_path: Path, mode: str) -> None:
    """rosbag2 with MCAP storage, per-message zstd or the whole file zstd (.mcap.zstd): the folder ingests; its
    split alone is one clear line (the file mode's said "unknown bag format")."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    lay = Layout(fmt="db3", duration_s=1.0)
    src, _t, _p = write_layout_bag(tmp_path / "src", lay)
    dst = tmp_path / "split"
    writer = Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(getattr(CompressionMode, mode), CompressionFormat.ZSTD)
    with AnyReader([src]) as reader, writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=reader.typestore)
                 for c in reader.connections}
        for c, t, raw in reader.messages():
            writer.write(conns[c.id], t, raw)
    cfg = tmp_path / "m.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(lay)))
    run_module("ingest", dst, "-o", tmp_path / "ok.h5", "--config", cfg, "--size", "48", check=True)
    bare = next(dst.glob("*.mcap*"))
    line = one_line_error(run_module("ingest", bare, "-o", tmp_path / "x.h5", "--config", cfg, "--size", "48"))
    assert "compressed rosbag2 split" in line and "give its folder" in line


@pytest.mark.parametrize(("camera", "robot"), [("azure_kinect", "kinova_gen3"), ("realsense", "franka"),
                                               ("zed", "ur")])
def test_the_suggested_config_ingests_a_new_robots_bag(tmp_path: Path, camera: str, robot: str) -> None:
    """The first hour with a new robot: --suggest-config guesses the map, and that map ingests the bag."""
    lay = Layout(camera=camera, robot=robot, depth="compressed16" if camera == "azure_kinect" else "32FC1")
    bag, ee_t, ee_p = write_layout_bag(tmp_path / "new.mcap", lay)
    proc = run_module("ingest", "--suggest-config", bag, check=True)
    guessed = yaml.safe_load(proc.stdout)
    want = topic_map(lay)
    for key in ("image", "camera_info", "depth", "joints", "base_frame", "ee_frame"):
        assert guessed[key] == want[key], (key, proc.stdout)
    assert "# end-effector candidates" in proc.stdout and "is connected to the base" in proc.stdout
    cfg = tmp_path / "guessed.yaml"
    cfg.write_text(proc.stdout)
    run_module("ingest", bag, "-o", tmp_path / "x.h5", "--config", cfg, "--size", "48", check=True)
    with h5py.File(tmp_path / "x.h5") as f:
        ep = schema.read_episode(f, schema.episode_names(f)[0])
    assert np.linalg.norm(ep.traj3d - _expected_path(ee_t, ee_p, ep), axis=1).max() < 1e-3


def test_list_audits_rates_gaps_and_stamp_offsets(tmp_path: Path) -> None:
    bag, _t, _p = write_layout_bag(tmp_path / "a.mcap", Layout(tf_gap=(1.0, 2.0), duration_s=3.0))
    out = run_module("ingest", "--list", bag, check=True).stdout
    rows = {ln.split()[0]: ln.split() for ln in out.splitlines()[2:]}
    tf = rows["/tf"]  # topic type declared N read N rate gap offset
    assert tf[3] == tf[5] and abs(float(tf[6]) - 50 * 101 / 151) < 2  # 101 stamps over 3 s, the hole
    assert abs(float(tf[7]) - 1.0) < 1e-3 and abs(float(tf[8])) < 1e-6  # the hole; stamps = log times here
    assert abs(float(rows["/rgb/image_raw"][6]) - 10.0) < 0.01


def _segment_truth(ee_t: np.ndarray, ee_p: np.ndarray, lay: Layout, k: int) -> np.ndarray:
    a = k * (lay.duration_s + lay.pause_s)
    tq = np.linspace(a, a + lay.duration_s, 32)
    return np.stack([np.interp(tq, ee_t, ee_p[:, i]) for i in range(3)], axis=1)


@pytest.mark.parametrize("how", ["markers", "sidecar", "motion"])
def test_several_demonstrations_in_one_bag(tmp_path: Path, how: str) -> None:
    lay = Layout(demos=3, duration_s=2.0, pause_s=1.5, markers=how == "markers")
    bag, ee_t, ee_p = write_layout_bag(tmp_path / "session.mcap", lay)
    m = topic_map(lay)
    if how == "markers":
        m["segment_topic"] = "/segment"
    elif how == "motion":
        m.update(segment_idle_s=1.0, segment_min_s=0.5)
    else:
        (tmp_path / "session.mcap.segments.yaml").write_text(yaml.safe_dump(
            {"segments": [[k * 3.5, k * 3.5 + 2.0] for k in range(3)]}))
    out = tmp_path / "x.h5"
    tm = TopicMap(**m)
    assert ingest([bag], out, tm, n_waypoints=32, size=48)["new"] == 3
    with h5py.File(out) as f:
        eps = sorted((schema.read_episode(f, n) for n in schema.episode_names(f)), key=lambda e: e.segment)
    assert [e.segment for e in eps] == [0, 1, 2] and len({e.source_sha256 for e in eps}) == 1
    for k, ep in enumerate(eps):
        assert ep.name.endswith(f"-s{k:03d}")
        truth = _segment_truth(ee_t, ee_p, lay, k)
        tol = 1e-3 if how != "motion" else 0.01  # motion edges are found to within a tf sample (20 ms)
        assert np.linalg.norm(ep.traj3d - truth, axis=1).max() < tol, (k, ep.duration_s)
    before = out.read_bytes()
    assert ingest([bag], out, tm, n_waypoints=32, size=48)["new"] == 0  # re-ingest is a no-op
    assert out.read_bytes() == before


def test_a_start_marker_without_stop_is_one_line(tmp_path: Path) -> None:
    from adlpipe.bags.segments import find_segments

    lay = Layout(demos=1, markers=False)
    bag, _t, _p = write_layout_bag(tmp_path / "s.mcap", lay)
    with pytest.raises(AdlError, match="segment_topic /segment is not in the bag"):
        find_segments(bag, TopicMap(**topic_map(lay, segment_topic="/segment")))
    (tmp_path / "s.mcap.segments.yaml").write_text("segments: [[2, 1]]\n")
    with pytest.raises(AdlError, match="0 <= t0 < t1"):
        find_segments(bag, TopicMap(**topic_map(lay)))


def test_the_suggested_config_keeps_the_projects_affordance_map(mcap_bags: list[Path], tmp_path: Path) -> None:
    """On adlpipe's own bags the guessed map names /adl/affordance (a 32FC1 image, not depth), and the dataset it
    ingests holds the recorded map, not zeros."""
    proc = run_module("ingest", "--suggest-config", mcap_bags[0], check=True)
    guessed = yaml.safe_load(proc.stdout)
    assert guessed["affordance"] == "/adl/affordance" and guessed["depth"] == "/camera/depth/image_raw"
    cfg = tmp_path / "guessed.yaml"
    cfg.write_text(proc.stdout)
    run_module("ingest", mcap_bags[0], "-o", tmp_path / "x.h5", "--config", cfg, "--size", "48", check=True)
    with h5py.File(tmp_path / "x.h5") as f:
        ep = schema.read_episode(f, schema.episode_names(f)[0])
    assert ep.has_affordance and ep.affordance.max() > 0.5


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
@pytest.mark.parametrize(("encoding", "tol"), [
    ("rgb16", 0.0), ("bgr16", 0.0), ("8UC3", 0.0), ("bayer_rggb8", 4.0), ("bayer_bggr8", 4.0),
    ("bayer_gbrg8", 4.0), ("bayer_grbg8", 4.0), ("yuv422", 4.0), ("uyvy", 4.0), ("yuv422_yuy2", 4.0),
    ("yuyv", 4.0)])
def test_image_encodings_real_cameras_publish(tmp_path: Path, fmt: str, encoding: str, tol: float) -> None:
    """The same smooth frames published as rgb8 and as a raw camera encoding ingest to the same stored frames:
    exactly for lossless layouts, within a few levels where demosaicing or 4:2:2 chroma lose detail (and never
    with the colour channels swapped)."""
    ref = Layout(fmt=fmt, smooth=True, size=(40, 30), depth=None, duration_s=1.0)
    lay = Layout(fmt=fmt, smooth=True, size=(40, 30), depth=None, duration_s=1.0, encoding=encoding)
    want = _ingest(write_layout_bag(tmp_path / f"ref.{fmt}", ref)[0], tmp_path / "ref", TopicMap(**topic_map(ref)))
    got = _ingest(write_layout_bag(tmp_path / f"enc.{fmt}", lay)[0], tmp_path / "enc", TopicMap(**topic_map(lay)))
    diff = np.abs(got.rgb.astype(int) - want.rgb.astype(int))
    assert got.rgb.shape == want.rgb.shape and got.rgb.dtype == np.uint8
    assert diff.mean() <= tol, (encoding, diff.mean())
    assert all(np.corrcoef(got.rgb[..., c].ravel(), want.rgb[..., c].ravel())[0, 1] > 0.95 for c in range(3))


@pytest.mark.parametrize("encoding", ["mono8", "8UC1", "mono16"])
def test_grey_cameras_store_grey_rgb_frames(tmp_path: Path, encoding: str) -> None:
    import cv2

    ref = Layout(smooth=True, size=(40, 30), depth=None, duration_s=1.0)
    lay = Layout(smooth=True, size=(40, 30), depth=None, duration_s=1.0, encoding=encoding)
    want = _ingest(write_layout_bag(tmp_path / "ref.mcap", ref)[0], tmp_path / "ref", TopicMap(**topic_map(ref)))
    got = _ingest(write_layout_bag(tmp_path / "g.mcap", lay)[0], tmp_path / "g", TopicMap(**topic_map(lay)))
    assert got.rgb.shape == want.rgb.shape and (got.rgb[..., 0] == got.rgb[..., 2]).all()
    grey = cv2.cvtColor(want.rgb, cv2.COLOR_RGB2GRAY)
    assert np.abs(got.rgb[..., 0].astype(int) - grey).mean() <= 1.0


def test_an_odd_width_yuv_frame_is_one_line(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from adlpipe.bags.images import decode_image

    msg = SimpleNamespace(encoding="uyvy", height=2, width=3, step=6, is_bigendian=0, data=bytes(12))
    with pytest.raises(AdlError, match="3x2 uyvy image cannot be converted"):
        decode_image(msg, "x.mcap: topic /cam")


def _frames(h5: Path) -> tuple[np.ndarray, np.ndarray, str]:
    with h5py.File(h5) as f:
        g = f[schema.EPISODES][schema.episode_names(f)[0]]
        return g["frames/t"][()], g["frames/rgb"][()], str(g.attrs["note"])


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
def test_frames_logged_a_little_out_of_order_are_ordered_by_stamp(tmp_path: Path, fmt: str) -> None:
    """Frames 5 and 12 logged 1.5 and 3.5 frames late (a two-thread driver, a bag merged by log time): stored in
    header-stamp order, the same frames as the bag logged in order, with a note; 20 frames late is refused."""
    kw = dict(fmt=fmt, size=(32, 24), depth=None, duration_s=2.0)
    ok_bag = write_layout_bag(tmp_path / f"ok.{fmt}", Layout(**kw))[0]
    late_bag = write_layout_bag(tmp_path / f"late.{fmt}", Layout(**kw, late_frames={5: 1.5, 12: 3.5}))[0]
    for name, bag in (("ok", ok_bag), ("late", late_bag)):
        ingest([bag], tmp_path / f"{name}.h5", TopicMap(**topic_map(Layout(**kw))), n_waypoints=32, size=32)
    t_ok, rgb_ok, note_ok = _frames(tmp_path / "ok.h5")
    t_late, rgb_late, note_late = _frames(tmp_path / "late.h5")
    assert np.all(np.diff(t_late) > 0) and np.array_equal(t_late, t_ok) and np.array_equal(rgb_late, rgb_ok)
    assert note_ok == "" and "ordered 2 frame(s) logged out of header-stamp order" in note_late
    very = write_layout_bag(tmp_path / f"very.{fmt}", Layout(**kw, late_frames={3: 12.5}))[0]
    with pytest.raises(AdlError, match="frames cannot be ordered"):
        ingest([very], tmp_path / "very.h5", TopicMap(**topic_map(Layout(**kw))), n_waypoints=32, size=32)


def test_a_ros1_split_recording_is_one_recording(tmp_path: Path) -> None:
    """`rosbag record --split` cut a 3 s demonstration into rec_0.bag .. rec_2.bag (tf_static and the task only in
    the first part): given as its files or its folder it ingests as the one unsplit recording would; --list says
    so. Separately recorded, numbered demonstrations stay separate."""
    kw = dict(fmt="bag", size=(32, 24), depth="16UC1", duration_s=3.0)
    (tmp_path / "whole").mkdir()
    (tmp_path / "split").mkdir()
    whole = write_layout_bag(tmp_path / "whole" / "rec.bag", Layout(**kw))[0]
    first = write_layout_bag(tmp_path / "split" / "rec.bag", Layout(**kw, split_s=1.2))[0]
    parts = sorted((tmp_path / "split").glob("rec_*.bag"))
    assert first.name == "rec_0.bag" and [p.name for p in parts] == ["rec_0.bag", "rec_1.bag", "rec_2.bag"]
    tm = TopicMap(**topic_map(Layout(**kw)))
    want = _ingest(whole, tmp_path / "w", tm)
    c = ingest(parts, tmp_path / "s.h5", tm, n_waypoints=32, size=48)
    assert c["new"] == 1 and "one split recording of 3 files (rec_0.bag .. rec_2.bag)" in c["notes"][0], c
    with h5py.File(tmp_path / "s.h5") as f:
        got = schema.read_episode(f, schema.episode_names(f)[0])
        frames = f[schema.EPISODES][schema.episode_names(f)[0]]["frames/t"].shape[0]
    assert np.allclose(got.traj3d, want.traj3d, atol=1e-6) and got.duration_s == pytest.approx(want.duration_s)
    assert frames == 31  # every frame of the 3 s at 10 Hz, across both part boundaries
    # the folder: the same recording (already present, by its key)
    proc = run_module("ingest", tmp_path / "split", "-o", tmp_path / "s.h5", "--size", "48", "--config",
                      _write_map(tmp_path, tm))
    assert proc.returncode == 0 and "0 episode(s) added, 1 already present" in proc.stdout, proc.stderr
    listed = run_module("ingest", "--list", *parts, check=True).stdout
    assert listed.count("one split recording of 3 files") == 1
    # numbered demonstrations recorded one after another (not seamless): two recordings
    (tmp_path / "demos").mkdir()
    for k in range(2):
        write_layout_bag(tmp_path / "demos" / f"demo_{k}.bag", Layout(**{**kw, "duration_s": 3.0 - k}))
    assert ingest(sorted((tmp_path / "demos").glob("*.bag")), tmp_path / "d.h5", tm, n_waypoints=32,
                  size=48)["new"] == 2


def _write_map(tmp_path: Path, tm: TopicMap) -> Path:
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(Layout(fmt="bag", depth="16UC1"))))
    return cfg



def test_depth_beyond_range_is_stored_as_no_return() -> None:
    """REP 117: +inf is too far, -inf too near; the dataset promises NaN for every missing return."""
    from types import SimpleNamespace

    from adlpipe.bags.images import decode_depth

    d = np.array([[1.5, np.inf], [-np.inf, 0.0]], np.float32)
    msg = SimpleNamespace(encoding="32FC1", height=2, width=2, step=8, is_bigendian=0, data=d.tobytes())
    out = decode_depth(msg, "x.mcap: topic /depth")
    assert out[0, 0] == pytest.approx(1.5) and np.isnan(out[0, 1]) and np.isnan(out[1, 0]) and np.isnan(out[1, 1])
