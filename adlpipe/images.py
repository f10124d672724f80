"""Decoding sensor_msgs/Image and CompressedImage with every size checked before anything is allocated."""

from __future__ import annotations

import contextlib
import os
import struct
from collections.abc import Iterator

import cv2
import numpy as np

from .errors import AdlError

MAX_PIXELS = 8192 * 8192  # larger claims are rejected, never allocated

# encoding -> (numpy dtype, channels)
ENCODINGS = {
    "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
    "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "8UC3": (np.uint8, 3), "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1),
}


def _as_bytes(data: object) -> memoryview:
    """uint8[] fields decode to bytes (mcap) or numpy arrays (rosbags)."""
    if isinstance(data, np.ndarray):
        return memoryview(np.ascontiguousarray(data, dtype=np.uint8)).cast("B")
    return memoryview(bytes(data) if not isinstance(data, bytes | bytearray | memoryview) else data).cast("B")


def decode_raw(msg: object, where: str) -> np.ndarray:
    """sensor_msgs/Image -> HxW or HxWxC array; RGB order for colour images."""
    enc = str(msg.encoding)
    if enc not in ENCODINGS:
        raise AdlError(f"{where}: unsupported image encoding {enc!r} (supported: {', '.join(ENCODINGS)})")
    dtype, ch = ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = _as_bytes(msg.data)
    row = w * ch * np.dtype(dtype).itemsize
    if h <= 0 or w <= 0 or h * w > MAX_PIXELS:
        raise AdlError(f"{where}: image header claims {w}x{h} pixels (limit {MAX_PIXELS})")
    if step < row or h * step > len(data):
        raise AdlError(f"{where}: image header claims {w}x{h} {enc} (step {step}) but data has {len(data)} bytes")
    buf = np.frombuffer(data, np.uint8, count=h * step).reshape(h, step)[:, :row]
    arr = np.ascontiguousarray(buf).view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<"))
    arr = arr.astype(dtype, copy=False).reshape(h, w, ch) if ch > 1 else arr.astype(dtype, copy=False).reshape(h, w)
    if enc.startswith("bgr"):
        arr = arr[..., [2, 1, 0]]
    elif enc == "rgba8":
        arr = arr[..., :3]
    elif enc == "bgra8":
        arr = arr[..., [2, 1, 0]]
    elif ch == 1 and dtype == np.uint8 and enc == "mono8":
        arr = np.repeat(arr[..., None], 3, axis=2)
    return np.ascontiguousarray(arr)


def compressed_size(data: bytes | memoryview) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header without decoding; None if neither format is recognised."""
    b = bytes(data[:65536])
    if b[:8] == b"\x89PNG\r\n\x1a\n" and len(b) >= 24:
        return struct.unpack(">II", b[16:24])
    if b[:2] == b"\xff\xd8":
        i = 2
        while i + 9 < len(b):
            if b[i] != 0xFF:
                i += 1
                continue
            marker = b[i + 1]
            if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                h, w = struct.unpack(">HH", b[i + 5:i + 9])
                return w, h
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                i += 2
                continue
            i += 2 + struct.unpack(">H", b[i + 2:i + 4])[0]
    return None


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence C libraries writing to file descriptor 2 (not Python's sys.stderr object) for a moment."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def decode_compressed(msg: object, where: str) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg/png) -> HxWx3 RGB."""
    data = _as_bytes(msg.data)
    size = compressed_size(data)
    if size is None:
        raise AdlError(f"{where}: CompressedImage (format {msg.format!r}) is neither PNG nor JPEG data")
    w, h = size
    if w <= 0 or h <= 0 or w * h > MAX_PIXELS:
        raise AdlError(f"{where}: compressed image header claims {w}x{h} pixels (limit {MAX_PIXELS})")
    with _quiet_stderr():  # libpng/libjpeg print their own complaints; ours is the one line that counts
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise AdlError(f"{where}: cannot decode CompressedImage data (format {msg.format!r})")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_image(msg: object, where: str) -> np.ndarray:
    if hasattr(msg, "encoding"):
        return decode_raw(msg, where)
    if hasattr(msg, "format"):
        return decode_compressed(msg, where)
    raise AdlError(f"{where}: expected sensor_msgs/Image or CompressedImage, got {type(msg).__name__}")


def depth_to_metres(arr: np.ndarray, where: str) -> np.ndarray:
    """16UC1 depth is millimetres (REP 118), 32FC1 metres; 0 means no return and becomes NaN."""
    if arr.ndim != 2:
        raise AdlError(f"{where}: depth image must be single channel, got shape {arr.shape}")
    d = arr.astype(np.float32) / 1000.0 if arr.dtype == np.uint16 else arr.astype(np.float32)
    d[d <= 0] = np.nan
    return d
