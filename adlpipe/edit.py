"""Edit a dataset without ingesting its bags again: drop, merge, rename, re-task. The result is a new index OUT
beside DATA that shares DATA's episode files (hard links; adlpipe/curation/edit.py); DATA is never changed.

    python -m adlpipe.edit data/adl.h5 -o data/clean.h5 --drop-flagged doctor.json      # what doctor flagged
    python -m adlpipe.edit data/adl.h5 -o data/clean.h5 --drop NAME ... --drop-list bad.txt
    python -m adlpipe.edit data/adl.h5 -o data/all.h5 --merge data/more.h5
    python -m adlpipe.edit data/adl.h5 -o data/fixed.h5 --retask NAME="wipe the table" --rename OLD=NEW

A split made for DATA names the dropped episodes and is refused on OUT in one line: run python -m adlpipe.split
on OUT.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from .curation.edit import Edits, edit
from .plumbing.cli import Parser
from .plumbing.errors import AdlError, run_cli
from .plumbing.lock import exclusive


def pairs(items: list[str] | None, flag: str) -> dict[str, str]:
    """NAME=VALUE arguments as a mapping; one line for an item without '='."""
    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or not name or not value:
            raise AdlError(f"{flag} {item!r}: give NAME=VALUE")
        out[name] = value
    return out


def names_in(path: Path) -> set[str]:
    """Episode names of a list file: one per line; blank lines and # comments are skipped."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise AdlError(f"{path}: cannot read the list of episodes ({exc})") from None
    return {ln.split("#", 1)[0].strip() for ln in lines} - {""}


def flagged_in(path: Path, kinds: list[str] | None) -> set[str]:
    """The episodes a doctor --json report flagged (only flags of `kinds`, if given)."""
    try:
        episodes = json.loads(path.read_text())["episodes"]
        return {n for n, f in episodes.items()
                if any(kinds is None or fl.split(":", 1)[0] in kinds for fl in f["flags"])}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise AdlError(f"{path}: not a doctor report (python -m adlpipe.doctor DATA --json FILE): "
                       f"{type(exc).__name__}") from None


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.edit", __doc__)
    p.add_argument("data", type=Path, help="the dataset index to start from (left unchanged)")
    p.add_argument("-o", "--output", type=Path, required=True, help="the new index (must not exist)")
    p.add_argument("--drop", nargs="+", default=[], metavar="NAME", help="episodes to leave out")
    p.add_argument("--drop-list", type=Path, help="a file of episode names to leave out, one per line")
    p.add_argument("--drop-flagged", type=Path, metavar="DOCTOR_JSON",
                   help="leave out the episodes a doctor report flagged")
    p.add_argument("--flags", nargs="+", metavar="KIND",
                   help="with --drop-flagged: only these kinds of flag (e.g. 'frozen camera' 'tf glitch')")
    p.add_argument("--merge", nargs="+", type=Path, default=[], help="datasets whose episodes are added")
    p.add_argument("--rename", nargs="+", metavar="OLD=NEW")
    p.add_argument("--retask", nargs="+", metavar="NAME=TASK", help="give an episode another task (and the name "
                   "that goes with it)")
    p.io(inputs=["data", "drop_list", "drop_flagged", "merge"], outputs=["output"], writes_datasets=True)
    args = p.parse_args(argv)
    if args.flags and not args.drop_flagged:
        raise AdlError("--flags: chooses which doctor flags --drop-flagged drops; give --drop-flagged DOCTOR_JSON")
    drop = set(args.drop)
    if args.drop_list:
        drop |= names_in(args.drop_list)
    if args.drop_flagged:
        drop |= flagged_in(args.drop_flagged, args.flags)
    edits = Edits(drop=drop, rename=pairs(args.rename, "--rename"), retask=pairs(args.retask, "--retask"),
                  merge=args.merge)
    with exclusive(args.output):
        c = edit(args.data, args.output, edits)
    for note in c["notes"]:
        print(f"note: {note}", file=sys.stderr)
    print(f"{args.output}: {c['episodes']} episode(s) ({c['dropped']} dropped, {c['renamed']} renamed, "
          f"{c['retasked']} re-tasked), sharing the episode files of {args.data}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.edit", main))
