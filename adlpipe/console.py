"""The `adlpipe` console command: `adlpipe <stage> [options]` is `python -m adlpipe.<stage> [options]`.

    adlpipe ingest bags/*.mcap -o data/adl.h5
    adlpipe --help          # the stages
"""

from __future__ import annotations

import importlib
import sys

from .plumbing.errors import CONSOLE, missing_extra, run_cli

STAGES = ("record", "ingest", "split", "train", "evaluate", "replay", "report", "trials", "seeds", "inspect",
          "export", "doctor", "edit", "assess", "benchmark", "results", "serve", "rollout")


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] in (["--version"], ["-V"]):
        from . import __version__

        print(f"adlpipe {__version__}")
        return 0
    if args[:1] == ["help"] and len(args) > 1:  # adlpipe help train == adlpipe train --help
        args = [args[1], "--help"]
    if not args or args[0] in ("-h", "--help", "help"):
        print(f"usage: adlpipe <stage> [options]  (each stage: adlpipe <stage> --help; adlpipe --version)\n"
              f"stages: {', '.join(STAGES)}")
        return 0
    if args[0] not in STAGES:
        print(f"adlpipe: error: {args[0]!r} is not a stage (one of {', '.join(STAGES)})", file=sys.stderr)
        return 2
    stage = args[0]
    try:
        module = importlib.import_module(f"adlpipe.{stage}")
    except ModuleNotFoundError as exc:  # a stage whose optional extra is not installed (torch, mujoco, ...)
        if (line := missing_extra(exc)) is None:
            raise
        print(f"adlpipe.{stage}: error: {line}", file=sys.stderr)
        return 2
    CONSOLE.append(f"adlpipe.{stage}")
    return run_cli(f"adlpipe.{stage}", module.main, args[1:])


if __name__ == "__main__":
    sys.exit(main())
