"""The cameras of a LeRobot v3 export as LeRobot records them: MP4 files of many episodes each, under
videos/<key>/chunk-000/file-NNN.mp4, encoded with PyAV (H.264, yuv420p, a keyframe every 2 frames for random
access, as LeRobot's encoder settings do).

At a constant frame rate, as LeRobot writes them: frame k of a file is shown at k / fps, an episode's frames follow
the one before it, and a frame's `timestamp` is frame_index / fps, because LeRobot's decoder finds a frame at
(from_timestamp + timestamp) x fps and checks it within 1e-4 s (the camera's own stamps, jitter and dropped
stretches included, are kept in observation.camera_timestamp). Frames are encoded as they are read: one in memory.
"""

from __future__ import annotations

from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path

import numpy as np

from ..plumbing.errors import AdlError

VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
VIDEO_FILE_MB = 200
CODEC, PIX_FMT = "h264", "yuv420p"
CRF = 15  # near lossless: decoded frames within about 2 grey levels (mean, 64 px; yuv420p halves the colour)
GOP = 2


def video_feature(size: int, fps: int, depth_mm_per_level: int | None = None) -> dict:
    """A video feature of info.json; depth_mm_per_level: a depth map's, one grey level (in all 3 channels) is this
    many mm."""
    info = {"video.height": size, "video.width": size, "video.codec": CODEC, "video.pix_fmt": PIX_FMT,
            "video.is_depth_map": depth_mm_per_level is not None, "video.fps": fps, "video.channels": 3,
            "has_audio": False}
    if depth_mm_per_level:
        info.update({"unit": "mm", "mm_per_level": depth_mm_per_level})
    return {"dtype": "video", "shape": [size, size, 3], "names": ["height", "width", "channels"], "info": info}


class VideoFiles:
    """One camera key's MP4 files: episodes appended one after another, a new file past VIDEO_FILE_MB."""

    def __init__(self, root: Path, key: str, size: int, fps: int) -> None:
        import av  # PyAV: only an export of videos needs it

        if size % 2:
            raise AdlError(f"a {size} px image cannot be encoded as {PIX_FMT} video (even sizes only); export "
                           "with --images png")
        self.av, self.root, self.key, self.size, self.fps = av, root, key, size, fps
        self.file, self.container, self.stream, self.count = -1, None, None, 0

    def _path(self) -> Path:
        return self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=0, file_index=self.file)

    def _open(self) -> None:
        self.file += 1
        path = self._path()
        path.parent.mkdir(parents=True, exist_ok=True)
        self.container = self.av.open(str(path), "w", format="mp4")
        self.stream = self.container.add_stream("libx264", rate=self.fps,
                                                options={"crf": str(CRF), "g": str(GOP), "bf": "0"})
        self.stream.width = self.stream.height = self.size
        self.stream.pix_fmt = PIX_FMT
        self.stream.codec_context.time_base = Fraction(1, self.fps)
        self.count = 0  # frames in this file

    def add(self, frames: Iterable[np.ndarray]) -> dict:
        """Encode one episode's frames (RGB, uint8); its columns of the episodes table."""
        if self.container is None or self._path().stat().st_size > VIDEO_FILE_MB * 1e6:
            self.close()
            self._open()
        start = self.count
        for image in frames:
            frame = self.av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            frame.pts, frame.time_base = self.count, Fraction(1, self.fps)
            self.count += 1
            for packet in self.stream.encode(frame):
                self.container.mux(packet)
        return {f"videos/{self.key}/chunk_index": 0, f"videos/{self.key}/file_index": self.file,
                f"videos/{self.key}/from_timestamp": start / self.fps,
                f"videos/{self.key}/to_timestamp": self.count / self.fps}

    def close(self) -> None:
        if self.container is not None:
            for packet in self.stream.encode():
                self.container.mux(packet)
            self.container.close()
            self.container = None
