"""Bags -> HDF5: round trips in all three formats, projection, idempotence, atomicity and bad input."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import copy_dataset, one_line_error, public_bag, run_module

from adlpipe.bags.topics import TopicMap
from adlpipe.dataset import schema
from adlpipe.ingest import ingest
from adlpipe.plumbing.errors import AdlError
from adlpipe.sim.episode import record_demo
from adlpipe.sim.recording import write_episode_bag


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def demo():
    """One demonstration held in memory, to compare what comes out of each bag format with what went in."""
    return record_demo("put on the hat", np.random.default_rng(7), 64, 64, camera_hz=5)


@pytest.mark.parametrize(("fmt", "image_format", "depth_format"),
                         [("mcap", "raw", "32FC1"), ("bag", "jpeg", "16UC1"), ("db3", "png", "32FC1")])
def test_round_trip_each_bag_format(demo, tmp_path: Path, fmt: str, image_format: str, depth_format: str) -> None:
    bag = write_episode_bag(demo, tmp_path / f"ep.{fmt}" if fmt != "db3" else tmp_path / "ep", fmt, image_format,
                            depth_format, episode_index=0)
    out = tmp_path / "x.h5"
    counts = ingest([bag], out, TopicMap(), n_waypoints=32, size=64)
    assert counts["new"] == 1
    with h5py.File(out) as f:
        ep = schema.read_episode(f, schema.episode_names(f)[0])
    assert ep.task == "put on the hat"
    assert ep.source_format == {"mcap": "mcap", "bag": "ros1", "db3": "rosbag2"}[fmt]
    # Trajectory: starts at the first recorded end-effector pose and ends at the last one (metres).
    ee = np.array([p for _t, p, _q in demo.ee])
    assert np.abs(ep.traj3d[0] - ee[0]).max() < 1e-6
    assert np.abs(ep.traj3d[-1] - ee[-1]).max() < 1e-6
    assert ep.traj3d.shape == (32, 3) and ep.traj2d.shape == (32, 2)
    assert ep.duration_s == pytest.approx(demo.ee[-1][0], abs=1e-6)
    # Images: lossless formats round-trip exactly; jpeg stays close.
    err = np.abs(ep.rgb.astype(int) - demo.camera[0][1].astype(int)).mean()
    assert err < (4.0 if image_format == "jpeg" else 1e-9)
    assert np.array_equal(np.isnan(ep.depth), np.isnan(demo.camera[0][2]))  # no-return pixels stay NaN
    depth_err = np.nanmax(np.abs(ep.depth - demo.camera[0][2]))
    assert depth_err < (6e-4 if depth_format == "16UC1" else 1e-6)
    np.testing.assert_allclose(ep.affordance, demo.affordance, atol=1e-6)
    np.testing.assert_allclose(ep.K, demo.K, atol=1e-9)
    np.testing.assert_allclose(ep.T_base_camera, demo.T_base_camera, atol=1e-6)
    assert set(ep.object_names) == {"hat", "manikin"}
    assert len(ep.joint_t) == len(demo.joints) and ep.joint_pos.shape[1] == 9


def test_projection_lands_on_a_rendered_marker(ingested: Path) -> None:
    """Render a marker at traj3d[k] with the recorder's camera: its pixel centroid is traj2d[k]."""
    import mujoco

    from adlpipe.sim.episode import make_scene, spec_from_objects
    from adlpipe.sim.world import MARKER_GROUP

    with h5py.File(ingested) as f:
        ep = schema.read_episode(f, schema.episode_names(f)[0])
    scale = 8  # render finer than stored for a sharp centroid; pixels scale back
    size = ep.rgb.shape[0] * scale
    opt = mujoco.MjvOption()
    opt.geomgroup[:] = 0
    opt.geomgroup[MARKER_GROUP] = 1  # only the marker is drawn: nothing can hide it
    for k in (0, 10, 20, 31):
        spec = spec_from_objects(ep.task, ep.object_names, ep.objects)
        ctrl, _ = make_scene(spec, size, size, markers=[ep.traj3d[k]])
        r = mujoco.Renderer(ctrl.m, size, size)
        r.update_scene(ctrl.d, camera="rgbd", scene_option=opt)
        img = r.render().astype(int)
        r.close()
        mask = (img[..., 1] > 60) & (img[..., 0] < 40) & (img[..., 2] < 40)
        assert mask.sum() > 20, f"marker {k} not visible"
        vs, us = np.nonzero(mask)
        u = (us.mean() + 0.5) / scale - 0.5
        v = (vs.mean() + 0.5) / scale - 0.5
        assert abs(u - ep.traj2d[k, 0]) < 0.3 and abs(v - ep.traj2d[k, 1]) < 0.3, (k, u, v, ep.traj2d[k])


def test_reingest_is_a_no_op(mcap_bags: list[Path], ingested: Path, tmp_path: Path) -> None:
    copy = tmp_path / "adl.h5"
    copy_dataset(ingested, copy)
    before = _sha(copy)
    proc = run_module("ingest", *mcap_bags, "-o", copy, "--size", "64", check=True)
    assert "0 episode(s) added, 3 already present" in proc.stdout
    assert _sha(copy) == before
    named = [ln for ln in proc.stderr.splitlines() if ln.startswith("note: ") and "already in" in ln]
    assert sorted(ln.split(": ")[1] for ln in named) == sorted(map(str, mcap_bags))  # each one named


def test_the_same_recording_under_another_name_is_named_as_a_duplicate(mcap_bags: list[Path],
                                                                        tmp_path: Path) -> None:
    twin = tmp_path / "renamed_copy.mcap"
    shutil.copyfile(mcap_bags[0], twin)
    proc = run_module("ingest", *mcap_bags, twin, "-o", tmp_path / "d.h5", "--size", "64", check=True)
    assert "3 episode(s) added, 1 already present, 0 bad" in proc.stdout
    line = next(ln for ln in proc.stderr.splitlines() if "same recording" in ln)
    assert line.startswith(f"note: {twin}: the same recording as {mcap_bags[0]}") and "kept once" in line


def test_adding_bags_keeps_existing_episodes(mcap_bags: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "adl.h5"
    run_module("ingest", mcap_bags[0], "-o", out, "--size", "64", check=True)
    run_module("ingest", *mcap_bags, "-o", out, "--size", "64", "--workers", "2", check=True)
    with h5py.File(out) as f:
        assert len(schema.episode_names(f)) == 3
        assert f.attrs["format_version"] == schema.FORMAT_VERSION


PUBLIC = ["example.bag", "example-bz2.bag", "only-a-cube.bag", "bag-with-empty-message-definition.bag",
          "rosbag2_talker_mcap", "rosbag2_talker_sqlite3", "rosbag2_talker_mcap/talker.mcap",
          "rosbag2_talker_sqlite3/talker.db3"]


@pytest.mark.parametrize("name", PUBLIC)
def test_public_bags_fail_with_one_clear_line(name: str, tmp_path: Path) -> None:
    bag = public_bag(name)
    out = tmp_path / "out.h5"
    line = one_line_error(run_module("ingest", bag, "-o", out))
    assert str(bag) in line
    if name == "bag-with-empty-message-definition.bag":
        assert "unreadable" in line
    else:  # names what is missing and what the bag has instead
        assert "missing required topic(s) /camera/color/image_raw" in line and "the bag has: " in line
    if name.startswith("example"):
        assert "/turtle1/pose (turtlesim/msg/Pose)" in line
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # no temp file left either


@pytest.mark.parametrize("name", ["rosbag2_talker_mcap", "rosbag2_talker_sqlite3"])
def test_silent_zero_message_reads_are_caught(name: str) -> None:
    """rosbags yields 0 of the 10 /topic messages of these folders (QoS quirk): the count check says so."""
    proc = run_module("ingest", "--list", public_bag(name))
    assert proc.returncode == 1
    assert any("/topic" in ln and "declared     10 read      0" in ln and "mismatch" in ln
               for ln in proc.stdout.splitlines()), proc.stdout


def test_counts_agree_on_a_good_public_bag() -> None:
    proc = run_module("ingest", "--list", public_bag("example-bz2.bag"), check=True)
    assert "declared   2688 read   2688" in proc.stdout


def test_truncated_mcap_leaves_the_output_unchanged(mcap_bags: list[Path], ingested: Path, tmp_path: Path) -> None:
    bad = tmp_path / "cut.mcap"
    data = mcap_bags[0].read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    out = copy_dataset(ingested, tmp_path / "adl.h5")  # the index with its episode files: a whole dataset
    before = _sha(out)
    line = one_line_error(run_module("ingest", bad, "-o", out, "--size", "64"))
    assert "truncated or corrupt MCAP" in line and "--recover" in line
    assert _sha(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adl.h5", "adl.shards", "cut.mcap"]


def test_a_bad_bag_among_good_ones_writes_nothing(mcap_bags: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "adl.h5"
    cube = public_bag("only-a-cube.bag")
    proc = run_module("ingest", *mcap_bags, cube, "-o", out, "--size", "64")
    assert "only-a-cube.bag" in one_line_error(proc)
    assert not out.exists()
    proc = run_module("ingest", *mcap_bags, cube, "-o", out, "--size", "64",
                      "--skip-bad")
    assert proc.returncode == 1 and "3 episode(s) added" in proc.stdout and "only-a-cube.bag" in proc.stderr


def test_missing_topic_is_named(demo, tmp_path: Path) -> None:
    bag = write_episode_bag(demo, tmp_path / "ep.mcap", "mcap", "raw", "32FC1", 0,
                            topics=TopicMap(camera_info="/cam/info_elsewhere"))
    line = one_line_error(run_module("ingest", bag, "-o", tmp_path / "o.h5"))
    assert "missing required topic(s) /camera/color/camera_info" in line and "/cam/info_elsewhere" in line
    cfg = tmp_path / "topics.yaml"
    cfg.write_text("camera_info: /cam/info_elsewhere\n")
    run_module("ingest", bag, "-o", tmp_path / "o.h5", "--config", cfg, "--size", "64", check=True)


def test_unknown_message_type_is_a_clear_error(tmp_path: Path) -> None:
    """An image topic whose schema no decoder knows (here: a protobuf channel) fails with its type named."""
    from mcap.writer import Writer

    bag = tmp_path / "proto.mcap"
    with open(bag, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        for topic in ("/camera/color/image_raw", "/camera/color/camera_info", "/tf"):
            sid = w.register_schema(name="acme.RawFrame", encoding="protobuf", data=b"\x00")
            cid = w.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid)
            w.add_message(cid, log_time=1, data=b"\x01\x02", publish_time=1)
        w.finish()
    line = one_line_error(run_module("ingest", bag, "-o", tmp_path / "o.h5"))
    assert "/camera/color/image_raw" in line and "acme.RawFrame" in line


def test_existing_output_that_is_not_hdf5_is_left_alone(mcap_bags: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "adl.h5"
    out.write_text("my notes, not a dataset")
    line = one_line_error(run_module("ingest", mcap_bags[0], "-o", out))
    assert "not a readable HDF5 file" in line
    assert out.read_text() == "my notes, not a dataset"


def test_topic_map_rejects_unknown_keys(tmp_path: Path) -> None:
    cfg = tmp_path / "t.yaml"
    cfg.write_text("imgae: /x\n")
    with pytest.raises(AdlError, match="unknown topic-map keys"):
        TopicMap.load(cfg)


def test_sanitised_episode_names() -> None:
    assert schema.episode_name("../../etc/passwd", "ab" * 32) == "etc_passwd-abababababababab"
    assert "/" not in schema.safe_name("a/b\\c .. d")


def test_h5pys_ref_count_errors_after_a_full_disk_print_nothing(capsys: pytest.CaptureFixture[str]) -> None:
    """Once HDF5 failed to write, h5py's destructors print "Can't decrement id ref count" through sys.excepthook or
    sys.unraisablehook (seen once in a full run): ingest's hooks pass over it, as over the full disk itself; any
    other error still prints."""
    import sys

    from adlpipe.ingest import _report_full_disk_once

    def raised(code: str, filename: str) -> tuple[type[BaseException], BaseException, object]:
        try:
            exec(compile(code, filename, "exec"))
        except BaseException as exc:  # noqa: BLE001 - the test raises it on purpose
            return type(exc), exc, exc.__traceback__
        raise AssertionError("nothing raised")

    hooks = sys.excepthook, sys.unraisablehook
    try:
        _report_full_disk_once()
        sys.excepthook(*raised("raise RuntimeError(\"Can't decrement id ref count\")", "h5py/_objects.pyx"))
        assert capsys.readouterr().err == ""
        sys.excepthook(*raised("raise RuntimeError('something else')", "h5py/_objects.pyx"))
        sys.excepthook(*raised("raise RuntimeError(\"Can't decrement id ref count\")", "mine.py"))
        err = capsys.readouterr().err
        assert "something else" in err and err.count("Traceback") == 2
    finally:
        sys.excepthook, sys.unraisablehook = hooks
