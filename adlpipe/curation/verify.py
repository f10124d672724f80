"""Check a dataset against its bags: each episode's source bag (found among the given ones by its sha256) is read
again the way ingest read it, into a temporary file, and every stored array and camera attribute is compared with
what the bag gives. One line per mismatch.

Tolerances: stored frames are resized from the bag's images, so a frame may differ by TOLERANCE_LEVELS grey levels
(another OpenCV build may round a resize differently); everything else is compared exactly where lossless (integer
arrays, indices, depth in millimetres, names and stamps in ns) and within FLOAT_TOLERANCE otherwise (stamps in s,
poses, intrinsics, trajectories).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import h5py
import numpy as np

from ..bags.segments import find_segments
from ..bags.splits import recordings
from ..bags.topics import TopicMap
from ..dataset import schema
from ..dataset.frames import FrameWriter
from ..dataset.from_bag import extract_episode, sha256_of
from ..plumbing.errors import AdlError

TOLERANCE_LEVELS = 1  # grey levels a resized frame may differ by
FLOAT_TOLERANCE = 1e-6  # seconds, metres, pixels
ATTRS = ("camera_frame", "base_frame", "stamp0_ns", "duration_s", "distortion_model", "segment", "source_format",
         "camera_name")


def bags_by_sha(bags: list[Path]) -> dict[str, Path]:
    """The given bags (files, folders of them, split recordings) by their sha256, as ingest keys them."""
    return {sha256_of(b): b for b in recordings(bag_files(bags))}


def bag_files(paths: list[Path]) -> list[Path]:
    """Files and rosbag2 folders as given; a folder of recordings (data/bags/, as record writes them) becomes its
    .mcap and .bag files and rosbag2 folders. A device or a pipe (/dev/zero) is refused: hashing it never ends."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir() and not (p / "metadata.yaml").exists():
            found = sorted([*p.glob("*.mcap"), *p.glob("*.bag"),
                            *(d for d in p.iterdir() if (d / "metadata.yaml").exists())])
            if not found:
                raise AdlError(f"{p}: folder holds no bags (.mcap or .bag files, or rosbag2 folders)")
            out += found
        elif p.exists() and not p.is_dir() and not p.is_file():
            raise AdlError(f"{p}: not a regular file (a device or a pipe); give bag files or folders of them")
        else:
            out.append(p)
    return out


def verify_episode(g: h5py.Group, bag: Path, config: list[Path] | None, n_waypoints: int, size: int) -> list[str]:
    """Mismatches between a stored episode group and what its bag gives when read again."""
    name = g.name.rpartition("/")[2]
    tm = topic_map_of(g, config)
    note = str(g.attrs.get("note", ""))
    segment = int(g.attrs.get("segment", -1))
    window: tuple[int, int] | None = ((int(g.attrs["window_ns"][0]), int(g.attrs["window_ns"][1]))
                                      if "window_ns" in g.attrs else None)
    if segment >= 0 and window is None:  # ingested before the span was kept: find the segments again
        spans = find_segments(bag, tm, None) or []
        if segment >= len(spans):
            return [f"{name}: the bag {bag} no longer splits into {segment + 1} demonstrations"]
        window = spans[segment]
    with tempfile.TemporaryDirectory(prefix="adlpipe-verify-") as d, h5py.File(Path(d) / "e.h5", "w") as f:
        fresh = f.create_group("e")
        try:
            ep, _ = extract_episode(bag, tm, n_waypoints, size, str(g.attrs["task"]), "recovered" in note,
                                    str(g.attrs["source_sha256"]), "bridged" in note, window, segment,
                                    FrameWriter(fresh, size))
        except AdlError as exc:
            return [f"{name}: its bag cannot be read as it was ingested: {exc}"]
        schema.write_episode(fresh, ep)
        return compare(g, fresh, name)


def topic_map_of(g: h5py.Group, config: list[Path] | None) -> TopicMap:
    """The topic map given (--config), else the one the episode was ingested with, else the defaults."""
    if config:
        return TopicMap.load(config)
    text = str(g.attrs.get("topic_map", ""))
    if not text:
        return TopicMap()
    try:
        return TopicMap(**json.loads(text))
    except (TypeError, ValueError) as exc:  # written by another adlpipe version
        raise AdlError(f"episode {g.name.rpartition('/')[2]}: the topic map it was ingested with cannot be read by "
                       f"this adlpipe ({' '.join(str(exc).split())[:80]}); pass the map with --config") from None


def compare(stored: h5py.Group, fresh: h5py.Group, name: str) -> list[str]:
    """One line per array or attribute of `fresh` that `stored` lacks or holds differently."""
    out = []
    for key in ATTRS:
        a, b = stored.attrs.get(key), fresh.attrs.get(key)
        if b is not None and (a is None or str(a) != str(b)):
            out.append(f"{name}: attribute {key} is {a!r}, the bag gives {b!r}")
    paths: list[str] = []
    fresh.visititems(lambda k, obj: paths.append(k) if isinstance(obj, h5py.Dataset) else None)
    for key in paths:
        if key not in stored:
            out.append(f"{name}: {key} is missing from the dataset; the bag gives {fresh[key].shape}")
            continue
        line = _differs(stored[key], fresh[key])
        if line:
            out.append(f"{name}: {key}: {line}")
    return out


def _differs(a: h5py.Dataset, b: h5py.Dataset) -> str:
    if a.shape != b.shape:
        return f"shape {a.shape} stored, {b.shape} from the bag"
    if a.dtype.kind in "OSU" or b.dtype.kind in "OSU":
        return "" if np.array_equal(a[()], b[()]) else "text differs from the bag"
    frames = a.ndim == 4 and a.dtype == np.uint8  # (T, S, S, 3): compared a frame at a time, memory flat
    rows = range(a.shape[0]) if frames else [slice(None)]
    for i in rows:
        x, y = a[i].astype(np.float64), b[i].astype(np.float64)
        if a.dtype.kind == "f" or b.dtype.kind == "f":
            bad = ~np.isclose(x, y, rtol=0, atol=FLOAT_TOLERANCE, equal_nan=True)
            if bad.any():
                return (f"{int(bad.sum())} value(s) differ from the bag by up to "
                        f"{float(np.nanmax(np.abs(x - y)[bad])):.3g} (tolerance {FLOAT_TOLERANCE})")
            continue
        diff = np.abs(x - y)
        limit = TOLERANCE_LEVELS if a.dtype == np.uint8 and a.ndim >= 3 else 0
        if diff.max(initial=0) > limit:
            where = f"frame {i} " if frames else ""
            return f"{where}differs from the bag by up to {diff.max():.0f} (tolerance {limit})"
    return ""


def verify(path: Path, bags: list[Path], config: list[Path] | None = None,
           names: list[str] | None = None) -> tuple[list[str], int, list[str]]:
    """(mismatch lines, episodes verified, episodes whose bag was not given) of a dataset against bags."""
    by_sha = bags_by_sha(bags)
    lines, checked, missing = [], 0, []
    with schema.open_dataset(path, names) as f:
        n_waypoints, size = int(f.attrs["n_waypoints"]), int(f.attrs["image_size"])
        for n in names if names is not None else schema.episode_names(f):
            g = f[schema.EPISODES][n]
            bag = by_sha.get(str(g.attrs["source_sha256"]))
            if bag is None:
                missing.append(n)
                continue
            lines += verify_episode(g, bag, config, n_waypoints, size)
            checked += 1
    return lines, checked, missing
