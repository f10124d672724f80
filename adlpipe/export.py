"""Export the dataset for other tools: a LeRobotDataset v3.0 of every frame.

    python -m adlpipe.export --format lerobot data/adl.h5 exports/adl_lerobot [--episodes NAME ...] [--split-part train]

Layout and columns: adlpipe/interchange/lerobot.py. Every frame of every episode (or of the named ones, or of one part
of the split), one episode in memory at a time. The export is written into a hidden folder beside OUT and renamed
into place when complete: an interrupted export leaves nothing at OUT. Read it with LeRobot:
LeRobotDataset("adl", root="exports/adl_lerobot").
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from tqdm import tqdm

from .dataset import schema
from .dataset.splits import load_split
from .interchange.lerobot import Export, plan
from .plumbing.cli import Parser
from .plumbing.errors import AdlError, check_interrupted, note_committed, run_cli
from .plumbing.lock import exclusive


def export_lerobot(data: Path, out: Path, names: list[str] | None = None, progress: bool = False,
                   video: bool = True, maps: str = "png") -> dict:
    """Write the LeRobot v3 export of `names` (default: every episode) to `out`, its cameras as MP4 video (or PNG
    images), its depth and affordance maps as `maps` (png, video or none); returns its info.json."""
    if out.exists():
        raise AdlError(f"{out}: already exists; export into a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    if names:
        names = list(dict.fromkeys(names))  # an episode named twice is exported once
    with exclusive(out):  # a second export into the same OUT stops at once instead of deleting this one's work
        if out.exists():
            raise AdlError(f"{out}: already exists; export into a new folder")
        try:
            return _export_locked(data, out, names, progress, video, maps)
        except OSError as exc:  # name OUT, not the hidden folder the export is written in before it is renamed
            tmp = _hidden(out)
            if exc.filename is not None and str(exc.filename).startswith(str(tmp)):
                raise OSError(exc.errno, exc.strerror, str(out / Path(exc.filename).relative_to(tmp))) from None
            raise


def _hidden(out: Path) -> Path:
    """The folder an export is written in, beside OUT, until it is renamed into place."""
    return out.with_name(f".{out.name}.tmp")


def _export_locked(data: Path, out: Path, names: list[str] | None, progress: bool, video: bool,
                   maps: str) -> dict:
    tmp = _hidden(out)
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        with schema.open_dataset(data, names or None) as f:  # every episode it reads is checked
            names = names or schema.episode_names(f)
            if not names:
                raise AdlError(f"{data}: no episodes to export")
            layout = plan(f, names, video, maps)
            tasks = sorted({str(f[schema.EPISODES][n].attrs["task"]) for n in names})
            export = Export(tmp, layout, tasks)
            try:
                for i, n in enumerate(tqdm(names, desc="export", unit="episode", file=sys.stderr,
                                           disable=None if progress else True)):
                    export.add(f[schema.EPISODES][n], i)
                info = export.finish()
            except BaseException:
                export.abort()
                raise
        check_interrupted()  # a Ctrl-C that landed in a finaliser (PyAV's, h5py's) was swallowed: commit nothing
        tmp.rename(out)
        note_committed(out)
        return info
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.export", __doc__)
    p.add_argument("data", type=Path, help="the dataset (index file written by ingest)")
    p.add_argument("out", type=Path, help="folder to create")
    p.add_argument("--format", choices=["lerobot"], default="lerobot", help="lerobot: LeRobotDataset v3.0")
    p.add_argument("--episodes", nargs="+", help="episode names to export (default: all)")
    p.add_argument("--split", type=Path, help="split JSON for --split-part (default: split.json beside the data)")
    p.add_argument("--split-part", choices=["train", "test"], help="export only this part of the split")
    p.add_argument("--images", choices=["video", "png"], default="video",
                   help="the cameras as MP4 video, as LeRobot records them (default), or as lossless PNG images "
                        "in the data files (the depth and affordance maps: --maps)")
    p.add_argument("--maps", choices=["png", "video", "none"], default="png",
                   help="the depth and affordance maps: lossless PNG images in the data files (default), MP4 "
                        "video beside the cameras' (8-bit grey, depth 2 cm a level: lossy; for readers of video "
                        "features only), or left out (for readers that take no image features, such as kalanos 0.8.2)")
    p.add_argument("--skip-bad", action="store_true",
                   help="leave out episodes whose files cannot be read (each named) instead of stopping")
    p.io(inputs=["data", "split"], outputs=["out"])
    args = p.parse_args(argv)
    names = args.episodes
    if args.split_part:
        names = load_split(args.split or args.data.with_name("split.json"))[args.split_part]
        if not names:
            raise AdlError(f"the {args.split_part} split is empty")
    if args.skip_bad:
        names, bad = schema.readable_episodes(args.data, list(dict.fromkeys(names)) if names else None)
        for line in bad:
            print(f"adlpipe.export: skipped bad episode: {line}", file=sys.stderr)
        if not names:
            raise AdlError(f"{args.data}: no readable episodes to export")
    info = export_lerobot(args.data, args.out, names, progress=True, video=args.images == "video",
                          maps=args.maps)
    print(f"{args.out}: LeRobotDataset {info['codebase_version']}, {info['total_episodes']} episode(s), "
          f"{info['total_frames']} frames at {info['fps']} fps, {info['total_tasks']} task(s)")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.export", main))
