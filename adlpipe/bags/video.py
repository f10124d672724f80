"""Camera topics that carry compressed video instead of images, decoded in order with PyAV (issue E.4):

- foxglove_msgs/msg/CompressedVideo (Foxglove's recommended image transport): timestamp, frame_id, format
  ("h264", "h265", "vp9", "av1"), data: one access unit per message, Annex B for H.264/H.265;
- ffmpeg_image_transport_msgs/msg/FFMPEGPacket (ffmpeg_image_transport): header, encoding (the encoder's name, e.g.
  "libx264", "h264_nvenc", "hevc_nvenc"), pts, flags (1: keyframe), data.

A video stream can only be decoded from a keyframe on: a recording that starts between keyframes skips its packets
up to the first one (counted, and said in the episode's note). Frames come out in decode order, each with the
stamp of the message that carried it (streaming encoders send no B-frames; if one did, frames would still pair
with stamps in order).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from ..plumbing.errors import AdlError
from .images import as_bytes

VIDEO_TYPES = {"foxglove_msgs/msg/CompressedVideo", "ffmpeg_image_transport_msgs/msg/FFMPEGPacket"}
CODECS = {"h264": "h264", "avc": "h264", "h265": "hevc", "hevc": "hevc", "vp9": "vp9", "av1": "av1"}


def is_video(msg: object) -> bool:
    """A CompressedVideo (no header: timestamp and frame_id of its own) or an FFMPEGPacket (pts and flags)."""
    return (hasattr(msg, "timestamp") and hasattr(msg, "frame_id") and not hasattr(msg, "header")) or \
        (hasattr(msg, "pts") and hasattr(msg, "flags") and hasattr(msg, "encoding"))


def codec_of(msg: object, where: str) -> str:
    name = str(msg.format if hasattr(msg, "format") else msg.encoding).lower()
    for key, codec in CODECS.items():  # "h264", "libx264", "h264_nvenc", "hevc_nvenc", "libsvtav1" ...
        if key in name or (key == "h264" and "x264" in name) or (key == "hevc" and "x265" in name):
            return codec
    raise AdlError(f"{where}: video format {name!r} is not one adlpipe decodes (h264, h265, vp9, av1)")


class VideoDecoder:
    """One topic's decoder: fed every message in order, it returns the frames decoded so far with their stamps."""

    def __init__(self, where: str) -> None:
        import av  # PyAV: only a video topic needs it

        self.av, self.where = av, where
        self.context = None
        self.stamps: deque[float] = deque()
        self.skipped = 0  # packets before the first keyframe
        self.started = False

    def feed(self, msg: object, stamp: float) -> list[tuple[float, np.ndarray]]:
        av = self.av
        if self.context is None:
            self.context = av.CodecContext.create(codec_of(msg, self.where), "r")
        data = bytes(as_bytes(msg.data))
        if not self.started and hasattr(msg, "flags") and not int(msg.flags) & 1:
            self.skipped += 1  # FFMPEGPacket says it is no keyframe: nothing to decode it from yet
            return []
        self.stamps.append(stamp)
        try:
            frames = self.context.decode(av.Packet(data))
        except av.error.FFmpegError as exc:
            if self.started:
                raise AdlError(f"{self.where}: cannot decode the video packet at {stamp:.3f} s ({exc})") from exc
            frames = []
        if not self.started and not any(f.key_frame for f in frames):  # no keyframe yet: this packet is lost
            self.stamps.pop()  # (a decoder may still make a picture of it, from references it never had)
            self.skipped += 1
            return []
        self.started = True
        return [(self.stamps.popleft(), f.to_ndarray(format="rgb24")) for f in frames if self.stamps]
