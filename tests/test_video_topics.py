"""Camera topics that carry H.264 video (issue E.4): foxglove_msgs/CompressedVideo and ffmpeg_image_transport's
FFMPEGPacket, written with the real writers (PyAV's libx264 encoder, mcap's writer), ingested frame by frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from layouts import Layout, smooth_rgb, topic_map, write_layout_bag

from adlpipe.bags.topics import TopicMap
from adlpipe.dataset import schema
from adlpipe.ingest import ingest


def _ingest(lay: Layout, tmp_path: Path) -> dict:
    """The episode's frame stamps, frames, first frame and note."""
    bag, _, _ = write_layout_bag(tmp_path / "v.mcap", lay)
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(topic_map(lay)))
    out = tmp_path / "x.h5"
    assert ingest([bag], out, TopicMap.load(cfg), n_waypoints=32, size=64)["new"] == 1
    with schema.open_dataset(out) as f:
        g = f[schema.EPISODES][schema.episode_names(f)[0]]
        return {"t": g["frames/t"][()], "rgb": g["frames/rgb"][()], "first": g["rgb"][()],
                "note": str(g.attrs.get("note", ""))}


@pytest.mark.parametrize("kind", ["CompressedVideo", "FFMPEGPacket"])
def test_a_video_camera_topic_is_decoded_frame_by_frame(tmp_path: Path, kind: str) -> None:
    lay = Layout(video=kind, size=(64, 64), depth=None)
    ep = _ingest(lay, tmp_path)
    t, rgb = ep["t"], ep["rgb"]
    n = int(round(lay.duration_s * lay.camera_hz)) + 1
    assert len(t) == n and t == pytest.approx(np.arange(n) / lay.camera_hz, abs=1e-6)  # every frame, its stamp
    for k in (0, n // 2, n - 1):  # decoded frames against what was encoded (H.264 at CRF 12, yuv420p)
        assert np.abs(rgb[k].astype(float) - smooth_rgb(k, 64, 64)).mean() < 4.0
    assert "skipped" not in ep["note"]


def test_a_stream_that_starts_between_keyframes_skips_to_the_first_with_a_note(tmp_path: Path) -> None:
    lay = Layout(video="CompressedVideo", size=(64, 64), depth=None, video_cut=3)  # keyframes at 0, 10, 20 ...
    ep = _ingest(lay, tmp_path)
    t = ep["t"]
    assert t[0] == 0.0 and len(t) == int(round(lay.duration_s * lay.camera_hz)) + 1 - 10  # from frame 10 on
    assert "skipped 7 video packet(s) on /rgb/image_raw before its first keyframe" in ep["note"]
    assert np.abs(ep["first"].astype(float) - smooth_rgb(10, 64, 64)).mean() < 4.0
