"""How to store every camera frame: bytes per frame and random-read frames per second of the options.

    python bench/frame_storage.py [--size 128] [--frames 300]

Frames are real MuJoCo ADL renders (RGB and depth of a recorded demonstration, several tasks). Each option writes
them one frame per HDF5 chunk, then reads a random frame T times in a fresh file handle (as a DataLoader worker
would). Options: gzip (built into every HDF5), lzf (built into h5py), PNG bytes per frame (a variable-length
uint8 dataset), JPEG bytes (lossy; RGB only), blosc-lz4 and blosc-zstd via hdf5plugin (readers need the plugin).
The choice and its figures are in docs/reference/frame_storage.md.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import h5py
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def frames(size: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    from adlpipe.sim.episode import record_demo
    from adlpipe.sim.tasks import TASK_NAMES

    rgb, depth = [], []
    for k, task in enumerate(TASK_NAMES[::2]):
        st = record_demo(task, np.random.default_rng(k), size, size, camera_hz=15.0)
        rgb += [c[1] for c in st.camera]
        depth += [np.clip(np.round(np.nan_to_num(c[2]) * 1000), 0, 65535).astype(np.uint16) for c in st.camera]
        if len(rgb) >= n:
            break
    return np.stack(rgb[:n]), np.stack(depth[:n])


def options() -> dict[str, dict]:
    opts = {"gzip-4": {"compression": "gzip", "compression_opts": 4, "shuffle": True},
            "gzip-1": {"compression": "gzip", "compression_opts": 1, "shuffle": True},
            "lzf": {"compression": "lzf", "shuffle": True}}
    try:
        import hdf5plugin

        opts["blosc-lz4"] = dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE))
        opts["blosc-zstd"] = dict(hdf5plugin.Blosc(cname="zstd", clevel=3, shuffle=hdf5plugin.Blosc.SHUFFLE))
    except ImportError:
        print("hdf5plugin not installed: blosc options skipped", file=sys.stderr)
    return opts


def bench(path: Path, arr: np.ndarray, reads: int, dataset: dict, encode: Callable = lambda a: a,
          decode: Callable = lambda b: b) -> tuple[float, float, float]:
    """(bytes per frame, write frames/s, random-read frames/s): frames appended one at a time as ingest streams
    them, then `reads` random frames read back and decoded in one file handle."""
    t = time.perf_counter()
    with h5py.File(path, "w") as f:
        d = f.create_dataset("x", **dataset)
        for i, a in enumerate(arr):
            d.resize(i + 1, axis=0)
            d[i] = encode(a)
    write_fps = len(arr) / (time.perf_counter() - t)
    idx = np.random.default_rng(0).integers(0, len(arr), reads)
    with h5py.File(path, "r") as f:
        d = f["x"]
        t = time.perf_counter()
        for i in idx:
            decode(d[int(i)])
        read_fps = reads / (time.perf_counter() - t)
    return os.path.getsize(path) / len(arr), write_fps, read_fps


def bench_chunked(path: Path, arr: np.ndarray, opts: dict, reads: int) -> tuple[float, float, float]:
    shape = arr.shape[1:]
    return bench(path, arr, reads, dict(shape=(0, *shape), maxshape=(None, *shape), dtype=arr.dtype,
                                        chunks=(1, *shape), **opts))


def bench_encoded(path: Path, arr: np.ndarray, ext: str, reads: int) -> tuple[float, float, float]:
    params = [cv2.IMWRITE_JPEG_QUALITY, 90] if ext == ".jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 3]

    def encode(a: np.ndarray) -> np.ndarray:
        img = a[..., ::-1] if a.ndim == 3 else a  # cv2 encodes BGR
        return np.frombuffer(cv2.imencode(ext, img, params)[1].tobytes(), np.uint8)

    return bench(path, arr, reads, dict(shape=(0,), maxshape=(None,), dtype=h5py.vlen_dtype(np.uint8), chunks=(64,)),
                 encode, lambda b: cv2.imdecode(b, cv2.IMREAD_UNCHANGED))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--reads", type=int, default=2000)
    a = p.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    rgb, depth = frames(a.size, a.frames)
    raw = rgb[0].nbytes, depth[0].nbytes
    print(f"{len(rgb)} frames of {a.size}x{a.size}: raw RGB {raw[0]} B, depth (uint16 mm) {raw[1]} B per frame\n")
    print("| option | RGB bytes/frame | depth bytes/frame | RGB write fps | RGB random-read fps | depth read fps |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    with tempfile.TemporaryDirectory() as tmp:
        for name, opts in options().items():
            r = bench_chunked(Path(tmp) / f"{name}-rgb.h5", rgb, opts, a.reads)
            d = bench_chunked(Path(tmp) / f"{name}-d.h5", depth, opts, a.reads)
            print(f"| {name} | {r[0]:.0f} | {d[0]:.0f} | {r[1]:.0f} | {r[2]:.0f} | {d[2]:.0f} |")
        r = bench_encoded(Path(tmp) / "png-rgb.h5", rgb, ".png", a.reads)
        d = bench_encoded(Path(tmp) / "png-d.h5", depth, ".png", a.reads)
        print(f"| PNG bytes | {r[0]:.0f} | {d[0]:.0f} | {r[1]:.0f} | {r[2]:.0f} | {d[2]:.0f} |")
        r = bench_encoded(Path(tmp) / "jpg-rgb.h5", rgb, ".jpg", a.reads)
        print(f"| JPEG q90 bytes (lossy) | {r[0]:.0f} | – | {r[1]:.0f} | {r[2]:.0f} | – |")


if __name__ == "__main__":
    main()
