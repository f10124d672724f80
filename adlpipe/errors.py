"""User-facing errors and the CLI wrapper that turns them into one clear line and a non-zero exit."""

from __future__ import annotations

import errno
import signal
import sys
from collections.abc import Callable


class AdlError(Exception):
    """An error caused by the user's input (a bad bag, a missing topic, a wrong option).

    Its message is printed as one line; no traceback is shown.
    """


def os_error_message(exc: OSError) -> str:
    """One line for an operating-system error (disk full, permissions, a folder where a file should be)."""
    where = exc.filename or "an output file"
    if exc.errno == errno.ENOSPC:
        return f"no space left on device writing {where}"
    if exc.errno == errno.EROFS:
        return f"cannot write {where}: read-only file system"
    reason = exc.strerror or str(exc)
    return f"{where}: {reason}" if exc.filename else reason


def run_cli(prog: str, main: Callable[[list[str] | None], int], argv: list[str] | None = None) -> int:
    """Run a stage's main(); AdlError, OS errors and KeyboardInterrupt become one line on stderr. Outputs are
    written atomically (adlpipe.atomic), so whatever stopped the stage, the old files are still there."""
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return main(argv)
    except AdlError as exc:
        return _fail(prog, str(exc))
    except OSError as exc:
        return _fail(prog, os_error_message(exc))
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


def _fail(prog: str, message: str) -> int:
    print(f"{prog}: error: {' '.join(message.split())}", file=sys.stderr)  # always a single line
    return 2
