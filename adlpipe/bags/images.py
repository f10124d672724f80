"""Decoding sensor_msgs/Image and CompressedImage with every size checked before anything is allocated."""

from __future__ import annotations

import contextlib
import os
import struct
from collections.abc import Iterator

import cv2
import numpy as np

from ..plumbing.errors import AdlError

MAX_PIXELS = 8192 * 8192  # larger claims are rejected, never allocated

# encoding -> (numpy dtype, channels as stored in the message)
ENCODINGS = {
    "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
    "rgb16": (np.uint16, 3), "bgr16": (np.uint16, 3),
    "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "8UC3": (np.uint8, 3), "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1),
    "bayer_rggb8": (np.uint8, 1), "bayer_bggr8": (np.uint8, 1), "bayer_gbrg8": (np.uint8, 1),
    "bayer_grbg8": (np.uint8, 1),
    "yuv422": (np.uint8, 2), "uyvy": (np.uint8, 2), "yuv422_yuy2": (np.uint8, 2), "yuyv": (np.uint8, 2),
}
# Encodings only a colour camera publishes, converted to RGB when decoded, as cv_bridge does: raw Bayer mosaics
# demosaiced (OpenCV names a pattern by its second row: ROS's RGGB is OpenCV's BG), 4:2:2 YUV (ROS's yuv422 is
# UYVY byte order, yuv422_yuy2 YUYV) converted with BT.601.
TO_RGB = {
    "bayer_rggb8": cv2.COLOR_BayerBG2RGB, "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
    "bayer_gbrg8": cv2.COLOR_BayerGR2RGB, "bayer_grbg8": cv2.COLOR_BayerGB2RGB,
    "yuv422": cv2.COLOR_YUV2RGB_UYVY, "uyvy": cv2.COLOR_YUV2RGB_UYVY,
    "yuv422_yuy2": cv2.COLOR_YUV2RGB_YUY2, "yuyv": cv2.COLOR_YUV2RGB_YUY2,
}


def as_bytes(data: object) -> memoryview:
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
    data = as_bytes(msg.data)
    row = w * ch * np.dtype(dtype).itemsize
    if h <= 0 or w <= 0 or h * w > MAX_PIXELS:
        raise AdlError(f"{where}: image header claims {w}x{h} pixels (limit {MAX_PIXELS})")
    if step < row or h * step > len(data):
        raise AdlError(f"{where}: image header claims {w}x{h} {enc} (step {step}) but data has {len(data)} bytes")
    buf = np.frombuffer(data, np.uint8, count=h * step).reshape(h, step)[:, :row]
    arr = np.ascontiguousarray(buf).view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<"))
    arr = arr.astype(dtype, copy=False).reshape(h, w, ch) if ch > 1 else arr.astype(dtype, copy=False).reshape(h, w)
    if enc in TO_RGB:
        if enc.startswith("bayer") and (h < 2 or w < 2) or not enc.startswith("bayer") and w % 2:
            raise AdlError(f"{where}: a {w}x{h} {enc} image cannot be converted (Bayer needs 2x2, 4:2:2 an even "
                           "width)")
        arr = cv2.cvtColor(np.ascontiguousarray(arr), TO_RGB[enc])
    elif enc.startswith("bgr"):
        arr = arr[..., [2, 1, 0]]
    elif enc == "rgba8":
        arr = arr[..., :3]
    elif enc == "bgra8":
        arr = arr[..., [2, 1, 0]]
    elif ch == 1 and dtype == np.uint8 and enc == "mono8":
        arr = np.repeat(arr[..., None], 3, axis=2)
    return np.ascontiguousarray(arr)


def compressed_size(data: bytes | memoryview) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header without decoding; None if neither format is recognised.

    A JPEG is walked segment by segment (by their lengths, no copy), so a frame header behind large metadata
    segments (EXIF, ICC profiles, as some cameras write) is still found; the scan stops at the image data (SOS)."""
    b = data if isinstance(data, memoryview) else memoryview(data)
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
            if marker == 0xDA:  # start of scan before any frame header: not a JPEG we can size
                return None
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
    data = as_bytes(msg.data)
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


def as_rgb8(image: np.ndarray, where: str) -> np.ndarray:
    """A camera image as H x W x 3 uint8 RGB: 16-bit colour or grey scaled to 8 bits (the top byte, as cv_bridge
    converts 16 to 8 bits), grey repeated into three channels; a float image is not a colour image."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise AdlError(f"{where}: a {image.dtype} image is not a colour camera image (an rgb8-like encoding is)")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    return image


def decode_image(msg: object, where: str) -> np.ndarray:
    if hasattr(msg, "encoding"):
        return decode_raw(msg, where)
    if hasattr(msg, "format"):
        return decode_compressed(msg, where)
    raise AdlError(f"{where}: expected sensor_msgs/Image or CompressedImage, got {type(msg).__name__}")


def depth_to_metres(arr: np.ndarray, where: str) -> np.ndarray:
    """16UC1 depth is millimetres (REP 118), 32FC1 metres; 0 means no return and becomes NaN, as do the +inf
    (too far) and -inf (too near) REP 117 uses: the dataset promises NaN for every missing return."""
    if arr.ndim != 2:
        raise AdlError(f"{where}: depth image must be single channel, got shape {arr.shape}")
    d = arr.astype(np.float32) / 1000.0 if arr.dtype == np.uint16 else arr.astype(np.float32)
    d[~np.isfinite(d) | (d <= 0)] = np.nan
    return d


# --- depth as real cameras publish it ------------------------------------------------------------------------
# image_transport's compressed_depth plugin: sensor_msgs/CompressedImage whose format reads e.g.
# "16UC1; compressedDepth png" or "32FC1; compressedDepth rvl"; the data starts with a 12-byte ConfigHeader
# (int32 format, float32 depthQuantA, depthQuantB), then a PNG, or for RVL the width and height (uint32 each) and
# the RVL stream. 16UC1 stores millimetres; 32FC1 stores quantised inverse depth: z = A / (q - B), q = 0 no return.
DEPTH_TYPES = {"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"}
_DEPTH_HEADER = struct.Struct("<iff")
_DEPTH_QUANT_A, _DEPTH_QUANT_B = 100.0, 10.0  # the plugin's defaults (depth_max 10 m)


def decode_depth(msg: object, where: str) -> np.ndarray:
    """A depth image (Image 16UC1/32FC1, or compressedDepth PNG/RVL) in metres, NaN where there is no return."""
    if hasattr(msg, "encoding"):
        return depth_to_metres(decode_raw(msg, where), where)
    fmt = str(getattr(msg, "format", ""))
    if "compresseddepth" not in fmt.lower().replace(" ", ""):
        raise AdlError(f"{where}: depth CompressedImage has format {fmt!r}; expected '16UC1; compressedDepth png' "
                       "or '...; compressedDepth rvl'")
    data = bytes(as_bytes(msg.data))
    if len(data) < _DEPTH_HEADER.size + 8:
        raise AdlError(f"{where}: compressedDepth message too short ({len(data)} bytes)")
    _kind, quant_a, quant_b = _DEPTH_HEADER.unpack_from(data)
    body = data[_DEPTH_HEADER.size:]
    if "rvl" in fmt.lower():
        w, h = struct.unpack_from("<II", body)
        if w * h > MAX_PIXELS or w == 0 or h == 0:
            raise AdlError(f"{where}: RVL depth header claims {w}x{h} pixels")
        q = decode_rvl(body[8:], w * h, where).reshape(h, w)
    else:
        size = compressed_size(body)
        if size is None or size[0] * size[1] > MAX_PIXELS:
            raise AdlError(f"{where}: compressedDepth data is not a PNG of a sensible size")
        with _quiet_stderr():
            q = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_UNCHANGED)
        if q is None or q.dtype != np.uint16 or q.ndim != 2:
            raise AdlError(f"{where}: compressedDepth PNG does not decode to a 16-bit single-channel image")
    if fmt.strip().upper().startswith("32FC1"):
        out = np.full(q.shape, np.nan, np.float32)
        valid = q > 0
        out[valid] = quant_a / (q[valid].astype(np.float32) - quant_b)
        return out
    return depth_to_metres(q, where)


def encode_compressed_depth(depth_m: np.ndarray, encoding: str = "16UC1", codec: str = "png") -> tuple[str, bytes]:
    """(format, data) of a compressedDepth message, as image_transport writes them (for tests and the recorder)."""
    d = np.nan_to_num(np.asarray(depth_m, np.float32), nan=0.0)
    if encoding == "16UC1":
        q = np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16)
    else:
        q = np.zeros(d.shape, np.uint16)
        valid = d > 0
        q[valid] = np.clip(np.round(_DEPTH_QUANT_A / d[valid] + _DEPTH_QUANT_B), 0, 65535).astype(np.uint16)
    header = _DEPTH_HEADER.pack(0, _DEPTH_QUANT_A, _DEPTH_QUANT_B)
    if codec == "rvl":
        body = struct.pack("<II", q.shape[1], q.shape[0]) + encode_rvl(q.reshape(-1))
    else:
        ok, buf = cv2.imencode(".png", q)
        assert ok
        body = buf.tobytes()
    return f"{encoding}; compressedDepth {codec}", header + body


def encode_rvl(values: np.ndarray) -> bytes:
    """Wilson's RVL (run-length of zeros, then zigzag deltas in 3-bit variable-length nibbles, 8 per int32)."""
    words: list[int] = []
    state = [0, 0]  # (current word, nibbles in it)

    def vle(v: int) -> None:
        while True:
            nibble = v & 0x7
            v >>= 3
            if v:
                nibble |= 0x8
            state[0] = ((state[0] << 4) | nibble) & 0xFFFFFFFF
            state[1] += 1
            if state[1] == 8:
                words.append(state[0])
                state[0], state[1] = 0, 0
            if not v:
                return

    vals = [int(x) for x in values]
    i, n, previous = 0, len(vals), 0
    while i < n:
        zeros = 0
        while i < n and vals[i] == 0:
            zeros, i = zeros + 1, i + 1
        vle(zeros)
        j = i
        while j < n and vals[j] != 0:
            j += 1
        vle(j - i)
        for current in vals[i:j]:
            delta = current - previous
            vle((delta << 1) ^ (delta >> 31))
            previous = current
        i = j
    if state[1]:
        words.append((state[0] << 4 * (8 - state[1])) & 0xFFFFFFFF)
    return struct.pack(f"<{len(words)}I", *words)


def decode_rvl(data: bytes, n: int, where: str) -> np.ndarray:
    """The inverse of encode_rvl for n pixels; a stream that ends early or overruns is an error, not a guess."""
    words = struct.unpack(f"<{len(data) // 4}I", data[: len(data) // 4 * 4])
    out = np.zeros(n, np.uint16)
    pos = [0, 0, 0]  # (word index, current word, nibbles left)

    def vle() -> int:
        value, bits = 0, 29
        while True:
            if not pos[2]:
                if pos[0] >= len(words):
                    raise AdlError(f"{where}: RVL depth stream ends early")
                pos[1], pos[2] = words[pos[0]], 8
                pos[0] += 1
            nibble = pos[1] & 0xF0000000
            data_bits = (nibble << 1) & 0xFFFFFFFF  # drop the continuation bit, as the C uint32 shift does
            value |= data_bits >> bits if bits >= 0 else data_bits << -bits
            pos[1] = (pos[1] << 4) & 0xFFFFFFFF
            pos[2] -= 1
            bits -= 3
            if not nibble & 0x80000000:
                return value & 0xFFFFFFFF

    i, previous = 0, 0
    while i < n:
        zeros = vle()
        i += zeros
        nonzeros = vle()
        if i + nonzeros > n or zeros + nonzeros == 0:
            raise AdlError(f"{where}: RVL depth stream overruns the {n}-pixel image")
        for k in range(nonzeros):
            positive = vle()
            delta = (positive >> 1) ^ -(positive & 1)
            previous = (previous + delta) & 0xFFFF
            out[i + k] = previous
        i += nonzeros
    return out
