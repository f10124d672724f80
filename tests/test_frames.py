"""Every frame: the synced frame store, the sharded dataset that grows by appending, the windowed dataset and
augmentation."""

from __future__ import annotations

import hashlib
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import copy_dataset, one_line_error, run_module

from adlpipe.dataset import schema, shards
from adlpipe.dataset.frames import CODEC, FrameWriter, chunk_bytes, nearest_index, read_frame
from adlpipe.dataset.loader import (
    Augment,
    WindowDataset,
    Windows,
    compute_stats,
    compute_window_stats,
    observation_from_arrays,
)


def _names(path: Path) -> list[str]:
    with h5py.File(path) as f:
        return sorted(f["episodes"])


def test_every_frame_is_stored_and_synced(ingested: Path) -> None:
    with h5py.File(ingested) as f:
        for name in sorted(f["episodes"]):
            g = f["episodes"][name]
            fr = g["frames"]
            t = fr["t"][()]
            n = len(t)
            assert n >= 10 and fr["rgb"].shape == (n, 64, 64, 3) and fr["rgb"].chunks == (1, 64, 64, 3)
            assert fr["rgb"].compression == "gzip"
            assert t[0] == 0 and np.all(np.diff(t) > 0) and t[-1] <= g.attrs["duration_s"] + 0.05
            np.testing.assert_allclose(np.diff(t), 0.2, atol=3e-3)  # recorded at 5 Hz (physics steps of 2 ms)
            assert np.array_equal(fr["rgb"][0], g["rgb"][()])  # the first frame is the seed's Table 1 input
            s = g["series"]
            for k in (0, n // 2, n - 1):  # the end effector at each frame's stamp, interpolated in tf
                want = [np.interp(t[k], s["ee_t"][()], s["ee_pos"][:, d]) for d in range(3)]
                np.testing.assert_allclose(fr["ee_pos"][k], want, atol=1e-6)
            assert np.all(np.abs(fr["depth_t"][()][fr["depth_index"][()]] - t) <= 0.05)
            assert set(fr["affordance_index"][()]) == {0}  # the map is published once: every frame uses it
            jt = s["joint_t"][()]
            k = n // 2
            j = int(np.argmin(np.abs(jt - t[k])))
            np.testing.assert_allclose(fr["joint_pos"][k], s["joint_pos"][j], atol=1e-6)
            assert np.isfinite(fr["gripper"][()]).all() and fr["gripper"][()].max() <= 0.0401
            rgb, aff, depth = read_frame(g, k)
            assert rgb.shape == (64, 64, 3) and aff.shape == (64, 64) and depth.dtype == np.float32
            np.testing.assert_allclose(np.nanmedian(depth), np.nanmedian(g["depth"][()]), atol=0.05)


def test_frames_compressed_in_threads_are_the_chunks_hdf5_writes(tmp_path: Path) -> None:
    """Frames are compressed off the reading thread and stored with write_direct_chunk: the stored chunks are
    byte-identical to HDF5's own shuffle + gzip 4 of the same frames (RGB, depth mm, affordance), in log order."""
    rng = np.random.default_rng(3)
    frames = {"rgb": rng.integers(0, 255, (23, 16, 16, 3), dtype=np.uint8),
              "depth": rng.integers(0, 4000, (11, 16, 16), dtype=np.uint16),
              "affordance": rng.random((5, 16, 16)).astype(np.float32)}
    with h5py.File(tmp_path / "a.h5", "w") as f:
        w = FrameWriter(f.create_group("ep"), 16)
        for i, img in enumerate(frames["rgb"]):
            w.rgb(i / 15, img)
            if i < len(frames["depth"]):
                w.depth(i / 15, frames["depth"][i] / 1000.0)
            if i < len(frames["affordance"]):
                w.affordance(i / 15, frames["affordance"][i])
        w.flush("a bag")
        for key, want in frames.items():
            d = f["ep/frames"][key]
            assert np.array_equal(d[()], want), key
            reference = f.create_dataset(f"ref_{key}", data=want, chunks=(1, *want.shape[1:]), **CODEC)
            for i in range(len(want)):
                corner = (i,) + (0,) * (want.ndim - 1)
                assert d.id.read_direct_chunk(corner) == reference.id.read_direct_chunk(corner), (key, i)
                assert d.id.read_direct_chunk(corner)[1] == chunk_bytes(want[i])


def _write_frames(path: Path) -> int:
    with h5py.File(path, "w") as f:
        w = FrameWriter(f.create_group("ep"), 16)
        for i in range(20):
            w.rgb(i / 15, np.full((16, 16, 3), i, np.uint8))
        w.flush("a bag")
        return int(f["ep/frames/rgb"][()].sum())


def test_a_forked_process_compresses_with_its_own_threads(tmp_path: Path) -> None:
    """Ingest forks its pool workers, possibly after it has compressed frames itself: a child inherits the
    compression pool's object but not its threads, and waited forever on it before the pool was reset at fork."""
    import multiprocessing

    want = _write_frames(tmp_path / "parent.h5")  # the parent's compression threads exist now
    with multiprocessing.get_context("fork").Pool(2) as pool:
        got = pool.map_async(_write_frames, [tmp_path / "a.h5", tmp_path / "b.h5"]).get(timeout=120)
    assert got == [want, want]


def test_nearest_index_keeps_to_the_tolerance() -> None:
    ts = np.array([0.0, 0.1, 0.2, 0.5])
    t = np.array([0.01, 0.14, 0.33, 0.5, 0.9])
    assert nearest_index(t, ts, 0.05).tolist() == [0, 1, -1, 3, -1]
    assert nearest_index(t, ts, 0.05, or_latest=True).tolist() == [0, 1, 2, 3, 3]
    assert nearest_index(t, np.zeros(0), 0.05).tolist() == [-1] * 5


def _files(path: Path) -> dict[str, str]:
    root = shards.shards_dir(path)
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*.h5")}


def test_path_at_interpolates_every_axis_and_holds_the_ends() -> None:
    """The one helper behind every "path at these times" (loader, recovery, replay, doctor): scipy's linear
    interpolation per axis inside the path, its first and last point outside, any shape of times."""
    from scipy.interpolate import interp1d

    from adlpipe.geometry.transforms import path_at

    rng = np.random.default_rng(3)
    times, values = np.sort(rng.uniform(0, 5, 40)), rng.normal(size=(40, 3))
    t = rng.uniform(-1, 6, (7, 16))
    expected = interp1d(times, values, axis=0, bounds_error=False, fill_value=(values[0], values[-1]))(t)
    assert path_at(t, times, values).shape == (7, 16, 3)
    np.testing.assert_allclose(path_at(t, times, values), expected, atol=1e-12)
    np.testing.assert_allclose(path_at(-1.0, times, values), values[0])


def test_appending_writes_only_the_new_bags(mcap_bags: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "adl.h5"
    run_module("ingest", mcap_bags[0], "-o", out, "--size", "64", check=True)
    before = _files(out)
    proc = run_module("ingest", *mcap_bags, "-o", out, "--size", "64", check=True)
    assert "2 episode(s) added, 1 already present" in proc.stdout
    after = _files(out)
    assert {k: after[k] for k in before} == before  # the first run's file is not touched
    assert len(after) == 3 and len({Path(k).parts[0] for k in after}) == 2  # one folder per run
    with h5py.File(out) as f:
        rows = schema.read_catalog(f)
        assert len(rows) == 3 and {r["name"] for r in rows} == set(f["episodes"])
        assert out.stat().st_size < 64_000  # the index holds links and a catalog, not data


def test_a_run_that_never_reached_the_index_is_removed(mcap_bags: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "adl.h5"
    run_module("ingest", mcap_bags[0], "-o", out, "--size", "64", check=True)
    # A kill after the run folder was renamed into place but before the index was replaced: the old index
    # still names only its own episodes, so the dataset is the old one, whole.
    orphan = shards.shards_dir(out) / "run-20000101-000000-1"
    orphan.mkdir()
    (orphan / "000000.h5").write_bytes(b"half")
    dead = shards.shards_dir(out) / ".run-20000101-000001-999999999.tmp"
    dead.mkdir()
    stale_index = out.with_name(f".{out.name}.tmp999999999")  # an index being replaced when the kill came
    stale_index.write_bytes(b"half")
    assert len(_names(out)) == 1
    run_module("ingest", mcap_bags[1], "-o", out, "--size", "64", check=True)
    assert not orphan.exists() and not dead.exists() and not stale_index.exists()
    assert len(_names(out)) == 2


def test_a_format_1_dataset_says_how_to_re_ingest(tmp_path: Path) -> None:
    old = tmp_path / "old.h5"
    with h5py.File(old, "w") as f:
        f.attrs.update(format_version=1, n_waypoints=32, image_size=64)
        f.create_group("episodes")
    line = one_line_error(run_module("split", old, "-o", tmp_path / "s.json"))
    assert "format version 1" in line and "re-ingest" in line and str(old) in line


@pytest.fixture(scope="module")
def windows(ingested: Path) -> WindowDataset:
    names = _names(ingested)
    stats = compute_window_stats(ingested, names, Windows(2, 8, 10.0, "ee"))  # the measured end effector's target
    return WindowDataset(ingested, names, stats, 32, Windows(2, 8, 10.0, "ee"))


def test_windows_cover_every_frame_with_padding(windows: WindowDataset, ingested: Path) -> None:
    with h5py.File(ingested) as f:
        counts = [int(np.sum(f["episodes"][n]["frames/t"][()] <= f["episodes"][n].attrs["duration_s"]))
                  for n in windows.names]
        assert len(windows) == sum(counts)
        g = f["episodes"][windows.names[0]]
        obs, state, target = windows.raw(0, 0)
        assert obs.shape == (8, 32, 32) and target.shape == (8, 5)
        np.testing.assert_array_equal(obs[:4], obs[4:])  # before the start: the first frame repeated
        obs, state, target = windows.raw(0, 3)
        np.testing.assert_allclose(state[:, :3], g["frames/ee_pos"][2:4])  # where the arm is at each obs frame
        np.testing.assert_allclose(state[:, 3], g["frames/gripper"][2:4])  # and the gripper
        frames = g["frames"]
        want = observation_from_arrays(frames["rgb"][3], frames["affordance"][0], None, 32, False)
        np.testing.assert_allclose(obs[4:], want)
        prev = observation_from_arrays(frames["rgb"][2], frames["affordance"][0], None, 32, False)
        np.testing.assert_allclose(obs[:4], prev)
        deep = WindowDataset(ingested, windows.names[:1], windows.stats, 32, windows.w, use_depth=True)
        with_depth = deep.raw(0, 3)[0]  # 5 channels a frame; the same depth channel as at inference
        _, aff, depth = read_frame(g, 3)
        np.testing.assert_allclose(with_depth[5:], observation_from_arrays(frames["rgb"][3], aff, depth, 32, True))
        s = g["series"]
        now = frames["ee_pos"][3]
        t1 = frames["t"][3] + 0.1  # the first target waypoint: one step after the frame, relative to the arm now
        want = [np.interp(t1, s["ee_t"][()], s["ee_pos"][:, d]) for d in range(3)] - now
        np.testing.assert_allclose(target[0, 2:], want, atol=1e-5)
        assert np.linalg.norm(target[1, 2:] - target[0, 2:]) > 0  # the arm moves there
        _, _, end = windows.raw(0, counts[0] - 1)
        last = frames["ee_pos"][counts[0] - 1]
        np.testing.assert_allclose(end[-1, 2:] + last, s["ee_pos"][-1], atol=1e-5)  # after the end: the last pose
        np.testing.assert_allclose(end[-1], end[-2], atol=1e-5)
        from adlpipe.geometry.transforms import project

        K, T = g["K"][()], g["T_base_camera"][()]
        np.testing.assert_allclose(target[:, :2], project(target[:, 2:] + now, K, T) - project(now[None], K, T),
                                   atol=1e-3)
        stats = windows.stats  # every relative target of the data lies inside the normalisation range
        assert np.all(np.asarray(stats["min"]) < target.min(0)) and np.all(target.max(0) < np.asarray(stats["max"]))


def test_training_windows_are_drawn_uniformly_over_every_frame(ingested: Path) -> None:
    names = _names(ingested)
    stats = compute_stats(str(ingested), names)
    ds = WindowDataset(ingested, names, stats, 32, Windows(), draws_per_epoch=len(names), seed=3)
    assert len(ds) == len(names)  # as many optimiser steps per epoch as a first-frame model
    total = len(ds.items)
    assert total > 4 * len(names)
    first = [ds.window(i) for i in range(len(ds))]
    assert first == [ds.window(i) for i in range(len(ds))]  # the same epoch: the same windows (resumable)
    epochs = -(-total // len(names))  # enough epochs for one pass over every window
    seen = [ds.window(i, epoch) for epoch in range(epochs) for i in range(len(ds))]
    assert set(seen[:total]) == set(ds.items)  # one pass: every window exactly once, before any repeats
    assert len(set(seen[:total])) == total
    per_episode = np.bincount([e for e, _ in seen[:total]], minlength=len(names))
    assert per_episode.tolist() == ds.lengths.tolist()  # long episodes weigh as many windows as they have


def test_augmentation_moves_the_pixel_targets_with_the_image() -> None:
    obs = -np.ones((8, 32, 32), np.float32)
    obs[3, 10, 20] = 1.0  # a bright affordance pixel at (u=20, v=10) of the 32 px input, in both frames
    obs[7, 10, 20] = 1.0
    target = np.zeros((4, 5), np.float32)
    target[:, 0], target[:, 1] = 20 * 4, 10 * 4  # the same point in pixels of the 128 px stored image
    aug = Augment(128, shift=0.1, jitter=0.2)
    moved = 0
    for seed in range(20):
        o, t = aug(obs.copy(), target.copy(), np.random.default_rng(seed), 4)
        for ch in (3, 7):
            v, u = np.unravel_index(np.argmax(o[ch]), o[ch].shape)
            assert (u * 4, v * 4) == pytest.approx((t[0, 0], t[0, 1]))
        moved += (t[0, 0], t[0, 1]) != (80, 40)
        assert np.all(t[:, 2:] == 0)  # metres do not move
        assert set(np.unique(o[3]).tolist()) == {-1.0, 1.0}  # the affordance map moves but is not jittered
        assert o[:3].min() >= -1 and o[:3].max() <= 1
    assert moved >= 15


def test_copy_of_a_dataset_reads_like_the_original(ingested: Path, tmp_path: Path) -> None:
    copy = copy_dataset(ingested, tmp_path / "adl.h5")
    with h5py.File(copy) as f, h5py.File(ingested) as g:
        n = sorted(f["episodes"])[0]
        assert np.array_equal(f["episodes"][n]["frames/rgb"][2], g["episodes"][n]["frames/rgb"][2])
        assert shards.episode_file(copy, f, n).is_relative_to(tmp_path)
