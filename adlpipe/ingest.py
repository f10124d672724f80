"""Ingest ROS bags into one HDF5 dataset (schema: adlpipe.dataset.schema, docs/reference/hdf5_schema.md).

    python -m adlpipe.ingest data/bags/*.mcap -o data/adl.h5 [--config topics.yaml] [--waypoints 32]

Reads ROS2 MCAP (CDR) and ROS1-in-MCAP with the mcap decoders, ROS1 .bag and ROS2 folders/.db3 with rosbags,
streaming: every camera frame is resized to --size and appended to the bag's episode file as it is read, so memory
stays flat in bag length. Messages are synced by header.stamp within `sync_tolerance_s`: depth, affordance, joint
states and the end-effector pose (interpolated in tf) to every frame (adlpipe.dataset.frames). For the seed's
first-frame setting the end-effector path from the first frame to its last pose is also resampled to N waypoints
evenly in time (traj3d, base frame, metres) and projected into the stored image (traj2d, pixels).

The output is an index (-o FILE) and a folder of episode files beside it (FILE's stem + .shards): one file per bag,
one folder per run (adlpipe.dataset.shards). Appending writes only the new bags; re-ingesting a bag already in the
dataset (same sha256) is a no-op. The index is replaced last, by a rename, so a failure or a kill leaves the old
dataset (or none) whole.

Across machines: every machine (a Slurm array task, a Ray or Dask task) runs the same command with its own
--shard I/N and takes every N-th bag of the sorted list, starting at the I-th, into its own share folder; the index
is untouched until `--gather` links every finished share into it:

    python -m adlpipe.ingest data/bags/* -o data/adl.h5 --shard 1/8     # ... through 8/8, in parallel
    python -m adlpipe.ingest --gather -o data/adl.h5                     # once all shares have finished
"""

from __future__ import annotations

import argparse
import errno
import os
import shutil
import stat
import sys
import traceback
from collections.abc import Iterable
from pathlib import Path

import h5py
from tqdm import tqdm

from .bags.segments import find_segments
from .bags.splits import recording_parts, recordings
from .bags.survey import list_lines, suggest_config, survey
from .bags.topics import TopicMap
from .dataset import schema, shards
from .dataset.frames import FrameWriter
from .dataset.from_bag import extract_episode, sha256_of
from .plumbing.atomic import check_outputs
from .plumbing.cli import Parser, int_range
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, one_line, run_cli
from .plumbing.lock import exclusive
from .plumbing.workers import stoppable_pool


def check_bag_path(bag: Path) -> None:
    """Bags are regular files or rosbag2 folders: a FIFO, a device (a link to /dev/zero) or a socket would block or
    never end."""
    try:
        mode = bag.stat().st_mode
    except FileNotFoundError:
        return  # the reader says "no such bag" with the formats it knows
    except OSError as exc:
        raise AdlError(f"{bag}: cannot read ({exc.strerror})") from None
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise AdlError(f"{bag}: not a regular file or folder (a pipe, device or socket); give a bag file")


def _report_full_disk_once() -> None:
    """After the disk filled, every HDF5 object released on the way out tries its write again and fails in a
    Cython destructor, which prints the error (through sys.excepthook) and then reports it as unraisable, each
    time; the full disk is already the stage's one error line, so those two hooks pass over it."""
    def full_disk(exc: BaseException | None) -> bool:
        return isinstance(exc, OSError) and exc.errno == errno.ENOSPC

    # anything else goes on to the hooks set before (run_cli's, which keeps a Ctrl-C in a finaliser quiet)
    previous_unraisable, previous_excepthook = sys.unraisablehook, sys.excepthook

    def ref_count(exc: BaseException | None) -> bool:
        # h5py's destructors also report "Can't decrement id ref count" once HDF5 failed to write (seen about one
        # run in ten when the disk fills in a pool worker, through either hook): the same full disk, said again
        return isinstance(exc, RuntimeError) and "ref count" in str(exc)

    def unraisable(u: sys.UnraisableHookArgs) -> None:
        if not full_disk(u.exc_value) and not (ref_count(u.exc_value) and "h5py" in str(u.object)):
            previous_unraisable(u)

    def excepthook(kind: type[BaseException], exc: BaseException, tb: object) -> None:
        in_h5py = any("h5py" in frame.filename for frame in traceback.extract_tb(tb))  # type: ignore[arg-type]
        if not full_disk(exc) and not (ref_count(exc) and in_h5py):
            previous_excepthook(kind, exc, tb)

    sys.unraisablehook, sys.excepthook = unraisable, excepthook


def _worker(job: tuple) -> tuple[str, list[dict[str, str]], str, str | None]:
    """(bag, catalog rows of its episodes (none if already ingested), note, error line or None). Runs in a pool
    process: it streams the bag's episodes into their own file, `out`, and removes it on failure."""
    bag, tm, n, size, task, recover, known_shas, allow_gaps, segments_file, out = job
    try:
        check_bag_path(Path(bag))
        sha = sha256_of(Path(bag)) if Path(bag).exists() else None
        if sha is not None and sha in known_shas:
            return bag, [], "already ingested", None
        windows = find_segments(Path(bag), tm, segments_file) if not recover else None
        rows, notes = [], []
        with h5py.File(out, "w") as f:
            for k, w in enumerate(windows or [None]):
                g = f.create_group("pending")
                ep, note = extract_episode(Path(bag), tm, n, size, task, recover, sha, allow_gaps, w,
                                           k if windows else -1, FrameWriter(g, size))
                schema.write_episode(g, ep)
                f.move("pending", f"{schema.EPISODES}/{ep.name}")
                rows.append({"name": ep.name, "key": ep.key, "task": ep.task, "file": Path(out).name})
                notes += [f"segment {k}: {note}" if windows else note] if note else []
        if windows is None:
            return bag, rows, "; ".join(notes), None
        return bag, rows, f"{len(rows)} demonstrations" + (f" ({'; '.join(notes)})" if notes else ""), None
    except AdlError as exc:
        error = str(exc)
    except MemoryError:
        error = f"{bag}: out of memory while reading the bag"
    except Exception as exc:  # noqa: BLE001 - one bag's unforeseen failure must not take the batch down
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:  # the disk filled while writing: no bag's
            Path(out).unlink(missing_ok=True)  # fault, and no later bag fares better; the run stops
            raise
        error = f"{bag}: cannot ingest ({type(exc).__name__}: {one_line(exc, 200)})"
    Path(out).unlink(missing_ok=True)
    return bag, [], "", error


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = Parser("python -m adlpipe.ingest", __doc__)
    p.add_argument("bags", nargs="*", type=Path, help=".mcap / .bag files, rosbag2 folders or .db3 files")
    p.add_argument("-o", "--output", type=Path, help="HDF5 file to create or extend (required unless --list)")
    p.add_argument("--list", action="store_true",
                   help="print each bag's topics: type, declared and read counts, rate, largest gap between "
                   "messages and the offset of header.stamp from log time; write nothing")
    p.add_argument("--suggest-config", action="store_true",
                   help="print a topic-map YAML guessed from the (first) bag, with comments; write nothing")
    p.add_argument("--config", type=Path, action="append",
                   help="topic map YAML (keys of adlpipe.bags.topics.TopicMap); repeat it to combine, later ones "
                   "override: --config pipelines/presets/azure_kinect.yaml --config pipelines/presets/kinova_gen3.yaml")
    p.add_argument("--waypoints", type=int_range(2, 4096), default=32, help="waypoints per trajectory (default 32)")
    p.add_argument("--size", type=int_range(16, 4096), default=224, help="stored image width and height (default 224)")
    p.add_argument("--task", help="task name for bags without a task topic")
    p.add_argument("--workers", type=int_range(1, 256), default=min(4, os.cpu_count() or 1))
    p.add_argument("--skip-bad", action="store_true",
                   help="write the good bags and report the bad ones (exit 1) instead of writing nothing")
    p.add_argument("--allow-tf-gaps", action="store_true",
                   help="keep a bag whose end-effector tf has a gap over max_tf_gap_s, with a note, instead of "
                   "refusing it")
    p.add_argument("--segments", type=Path,
                   help="segments YAML for a bag holding several demonstrations (default: <bag>.segments.yaml "
                   "beside it, if there)")
    p.add_argument("--recover", action="store_true",
                   help="read what is complete in a truncated MCAP and report what was lost")
    p.add_argument("--shard", type=share_arg, metavar="I/N",
                   help="take the I-th of N disjoint shares of the bags (every N-th of the sorted list) into a share "
                   "folder of the dataset, leaving the index to --gather (one share per machine or task)")
    p.add_argument("--gather", action="store_true",
                   help="link every finished share (--shard) into the index; give no bags")
    p.add_force()
    p.io(inputs=["bags", "config", "segments"], outputs=["output"], writes_datasets=True)
    args = p.parse_args(argv)
    if not (args.list or args.suggest_config) and args.output is None:
        p.error("the following arguments are required: -o/--output")
    if args.gather and (args.bags or args.shard):
        p.error("--gather takes no bags and no --shard: it links the shares already written")
    if not args.gather and not args.bags:
        p.error("the following arguments are required: bags")
    return args


def share_arg(text: str) -> tuple[int, int]:
    """'I/N' -> (I, N), 1 <= I <= N."""
    i, sep, n = text.partition("/")
    if not (sep and i.strip().isdigit() and n.strip().isdigit()) or not 1 <= int(i) <= int(n):
        raise argparse.ArgumentTypeError(f"{text!r} is not a share I/N with 1 <= I <= N (e.g. 3/8)")
    return int(i), int(n)


def share_of(bags: list[Path], share: tuple[int, int]) -> list[Path]:
    """The I-th of N disjoint shares: every N-th bag of the sorted list from the I-th on. Every machine that is given
    the same bags (in any order) takes the same share."""
    i, n = share
    return sorted(bags, key=lambda b: str(b))[i - 1::n]


def ingest(bags: list[Path], output: Path, tm: TopicMap, n_waypoints: int = 32, size: int = 224,
           task: str | None = None, workers: int = 1, skip_bad: bool = False, recover: bool = False,
           progress: bool = False, allow_tf_gaps: bool = False, segments: Path | None = None,
           share: tuple[int, int] | None = None) -> dict:
    """Ingest bags into the dataset `output` (an index; episode files in adl.shards beside it). Each bag streams
    into its own file as it is read; the index is replaced only when every bag is in. Returns counts; raises
    AdlError (dataset untouched) on a bad bag. share (I, N): only that share of the bags, committed as a share
    folder for shards.gather, the index untouched."""
    bags = recordings(bags)
    if share:
        bags = share_of(bags, share)
    known: set[str] = set()
    if output.exists():
        try:
            with h5py.File(output, "r") as f:
                schema.check_file(f, str(output), n_waypoints, size)
                known = schema.episode_keys(f)
        except OSError as exc:
            raise AdlError(f"{output}: existing output is not a readable HDF5 file ({exc})") from exc
        try:  # every episode it holds readable: an append never builds on a damaged dataset
            with schema.open_dataset(output):
                pass
        except AdlError as exc:
            raise AdlError(f"cannot append to a damaged dataset: {exc}") from None
    known_shas = {k.split("#")[0] for k in known}  # a bag whose sha is in the file is skipped whole
    output.parent.mkdir(parents=True, exist_ok=True)
    if not share:  # a share never cleans up: other shares write beside it, on other machines
        shards.remove_unreferenced(output)
    check_free_space(output, bags)
    root_existed = share is not None or shards.shards_dir(output).exists()
    run, tmp_dir = shards.new_run(output, share)
    try:
        jobs = [(str(b), tm, n_waypoints, size, task, recover, known_shas, allow_tf_gaps, segments,
                 str(tmp_dir / f"{i:06d}.h5")) for i, b in enumerate(bags)]
        try:
            results = _run_jobs(jobs, workers, progress)
        except OSError as exc:
            if exc.errno == errno.ENOSPC:  # name the dataset, not a temp file of the run (removed below)
                raise OSError(errno.ENOSPC, "No space left on device", str(output)) from None
            raise
        errors = [err for _b, _r, _n, err in results if err]
        if errors and not skip_bad:
            more = f" (and {len(errors) - 1} more bad bag(s))" if len(errors) > 1 else ""
            raise AdlError(errors[0] + more)
        new: dict[str, dict[str, str]] = {}
        first: dict[str, str] = {}  # key -> the bag it was first read from in this run
        duplicates = []
        for bag, rows, _note, _err in results:
            if rows and all(r["key"] in known or r["key"] in new for r in rows):
                (tmp_dir / rows[0]["file"]).unlink()  # the same recording given twice is ingested once: say so
                duplicates.append(f"{bag}: the same recording as {first.get(rows[0]['key'], 'one')} (same sha256, "
                                  f"episode {rows[0]['name']}); kept once")
                continue
            new.update((r["key"], r) for r in rows)
            first.update((r["key"], bag) for r in rows)
        notes = [f"{b}: {n}" for b, rows, n, _ in results if n and rows] + duplicates
        notes += [f"{b}: already in {output} (the same sha256); skipped" for b, rows, n, err in results
                  if not rows and not err and n == "already ingested"]
        skipped = sum(1 for _b, rows, _n, err in results if not rows and not err) + len(duplicates)
        counts = {"new": len(new), "skipped": skipped, "bad": len(errors), "errors": errors, "notes": notes}
        if new and share:
            shards.commit_share(output, run, tmp_dir, list(new.values()), n_waypoints, size)
        elif new:
            shards.commit(output, run, tmp_dir, list(new.values()), n_waypoints, size)
        return counts
    finally:
        if tmp_dir.exists():  # not committed: nothing of this run may stay
            shutil.rmtree(tmp_dir, ignore_errors=True)
            if not root_existed:
                shutil.rmtree(shards.shards_dir(output), ignore_errors=True)


def _run_jobs(jobs: list[tuple], workers: int, progress: bool) -> list[tuple]:
    """_worker over the jobs, in a process pool when there are several. Results are a few strings per bag."""
    bar = {"desc": "ingest", "unit": "bag", "file": sys.stderr, "disable": None if progress else True,
           "total": len(jobs)}
    if workers <= 1 or len(jobs) <= 1:
        return [_worker(j) for j in tqdm(jobs, **bar)]
    with stoppable_pool(workers, initializer=_report_full_disk_once) as pool:
        return list(tqdm(pool.imap(_worker, jobs), **bar))


def check_free_space(output: Path, bags: Iterable[Path]) -> None:
    """Refuse to start writing into a file system that cannot hold the result (HDF5 does not fail cleanly on a full
    disk). A bag's episode file holds its frames compressed at the stored size: less than the bag, except for a
    bag of small compressed images stored larger, so the bound is the bags' size plus 10 MB."""
    need = 10 << 20
    for b in bags:
        try:
            files = b.rglob("*") if b.is_dir() else recording_parts(b)
            need += sum(p.stat().st_size for p in files if p.is_file())
        except OSError:
            continue  # the worker reports the bag
    free = shutil.disk_usage(output.parent).free
    if free < need:
        raise AdlError(f"no space left on device writing {output} (needs up to {need / 1e6:.1f} MB, "
                       f"{free / 1e6:.1f} MB free)")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _report_full_disk_once()
    args.bags = recordings(args.bags)  # a folder of ROS1 bags: its bags; a split recording's parts: one recording
    if args.suggest_config:
        print(suggest_config(survey(args.bags[0])), end="")
        return 0
    if args.list:
        bad = 0
        for bag in args.bags:
            s = survey(bag)
            print("\n".join(list_lines(s)))
            bad += sum(t.declared not in (None, t.read) for t in s.topics.values())
        return 1 if bad else 0
    check_outputs(args.output)
    refuse_pipeline_outputs([args.output], args.force)
    if args.gather:
        with exclusive(args.output):
            g = shards.gather(args.output)
        for name in g["unfinished"]:
            print(f"note: {shards.shards_dir(args.output) / name}: a share still being written (or written on "
                  "another machine); left alone: gather again when it has finished, or remove it if it was "
                  "stopped", file=sys.stderr)
        if not args.output.exists():
            raise AdlError(f"{args.output}: nothing to gather: no finished share in {shards.shards_dir(args.output)}"
                           + (f" ({len(g['unfinished'])} still being written)" if g["unfinished"] else "")
                           + "; run ingest --shard first")
        print(f"{args.output}: {g['new']} episode(s) linked from {g['shares']} share(s), {g['episodes']} in all")
        return 0
    tm = TopicMap.load(args.config)
    lock = args.output.with_name(f"{args.output.name}.share-{args.shard[0]}-of-{args.shard[1]}") if args.shard \
        else args.output  # shares run side by side; each excludes only a second run of itself
    with exclusive(lock):
        c = ingest(args.bags, args.output, tm, args.waypoints, args.size, args.task, args.workers, args.skip_bad,
                   args.recover, progress=True, allow_tf_gaps=args.allow_tf_gaps, segments=args.segments,
                   share=args.shard)
    for note in c["notes"]:
        print(f"note: {note}", file=sys.stderr)
    for err in c["errors"]:
        print(f"adlpipe.ingest: skipped bad bag: {err}", file=sys.stderr)
    where = f" into share {args.shard[0]}/{args.shard[1]} (link it with --gather)" if args.shard else ""
    print(f"{args.output}: {c['new']} episode(s) added{where}, {c['skipped']} already present, {c['bad']} bad "
          "bag(s)")
    return 1 if c["bad"] else 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.ingest", main))
