"""User-facing errors and the CLI wrapper that turns them into one clear line and a non-zero exit."""

from __future__ import annotations

import sys
from collections.abc import Callable


class AdlError(Exception):
    """An error caused by the user's input (a bad bag, a missing topic, a wrong option).

    Its message is printed as one line; no traceback is shown.
    """


def run_cli(prog: str, main: Callable[[list[str] | None], int], argv: list[str] | None = None) -> int:
    """Run a stage's main(); AdlError and KeyboardInterrupt become one line on stderr."""
    try:
        return main(argv)
    except AdlError as exc:
        msg = " ".join(str(exc).split())  # always a single line
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
