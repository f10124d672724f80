"""ROS1 split recordings: `rosbag record --split` writes one recording as name_0.bag, name_1.bag, ... (or
name_<date>_0.bag, ...), each part starting where the previous one stopped. Read as one recording, ordered by time,
a demonstration that crosses a part boundary stays whole.

Numbered names alone do not make a split recording: labs also number separate demonstrations demo_0.bag,
demo_1.bag. Parts belong together only when their indices follow each other and each part starts within
SPLIT_GAP_S of the previous part's end (a split is seamless; separate recordings are seconds or minutes apart).
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

from ..plumbing.errors import AdlError

PART = re.compile(r"^(?P<prefix>.+)_(?P<index>\d+)\.bag$")
SPLIT_GAP_S = 1.0  # the longest pause between one part's last message and the next part's first


@lru_cache(maxsize=4096)
def _span(path: Path) -> tuple[int, int] | None:
    """(start, end) log time ns of a ROS1 bag, from its index (no message is read); None if unreadable/empty."""
    from rosbags.rosbag1 import Reader

    try:
        with Reader(path) as r:
            return (int(r.start_time), int(r.end_time)) if r.message_count else None
    except Exception:  # noqa: BLE001 - an unreadable part is not part of a split; its own reading says why
        return None


def _numbered(path: Path) -> tuple[str, int] | None:
    m = PART.match(path.name)
    return (m["prefix"], int(m["index"])) if m else None


def recording_parts(path: Path) -> list[Path]:
    """The parts of the split recording `path` belongs to, in order (just [path] when it is not one)."""
    num = _numbered(path) if path.suffix == ".bag" and path.is_file() else None
    if num is None:
        return [path]
    prefix, index = num
    parts = [path]
    span = _span(path)
    k = index
    while span is not None and k > 0:  # back to the first part
        prev = path.with_name(f"{prefix}_{k - 1}.bag")
        prev_span = _span(prev) if prev.is_file() else None
        if prev_span is None or not 0 <= span[0] - prev_span[1] <= SPLIT_GAP_S * 1e9:
            break
        parts.insert(0, prev)
        span, k = prev_span, k - 1
    span, k = _span(path), index
    while span is not None:  # on to the last part
        nxt = path.with_name(f"{prefix}_{k + 1}.bag")
        nxt_span = _span(nxt) if nxt.is_file() else None
        if nxt_span is None or not 0 <= nxt_span[0] - span[1] <= SPLIT_GAP_S * 1e9:
            break
        parts.append(nxt)
        span, k = nxt_span, k + 1
    return parts


def recordings(paths: list[Path]) -> list[Path]:
    """The recordings among the given bags: a folder of ROS1 .bag files (no rosbag2 metadata.yaml) becomes its
    bags; each part of a split recording becomes the recording's first part, given once."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir() and not (p / "metadata.yaml").exists():
            bags = sorted(p.glob("*.bag"), key=lambda b: (_numbered(b) or (b.name, -1)))
            if not bags:
                raise AdlError(f"{p}: folder is neither a rosbag2 bag (no metadata.yaml) nor holds ROS1 .bag files")
            out += bags
        else:
            out.append(p)
    firsts: list[Path] = []
    for p in out:
        first = recording_parts(p)[0]
        if first not in firsts:
            firsts.append(first)
    return firsts


def split_note(parts: list[Path]) -> str:
    """How --list and an episode's note name a split recording."""
    return f"one split recording of {len(parts)} files ({parts[0].name} .. {parts[-1].name}), read in time order"
