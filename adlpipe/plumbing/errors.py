"""User-facing errors and the CLI wrapper that turns them into one clear line and a non-zero exit."""

from __future__ import annotations

import errno
import gc
import json
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path


class AdlError(Exception):
    """An error caused by the user's input (a bad bag, a missing topic, a wrong option).

    Its message is printed as one line; no traceback is shown.
    """


class NoDecoder(AdlError):
    """A bag's channel whose message encoding no installed decoder reads (protobuf, JSON, ...)."""

    def __init__(self, message: str, encoding: str) -> None:
        super().__init__(message)
        self.encoding = encoding


def read_json_object(path: Path, what: str, key: str | None = None) -> dict:
    """A JSON object from `path` (holding `key`, if given), or one line naming the file and what is wrong."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise AdlError(f"{path}: cannot read {what} ({exc})") from exc
    if not isinstance(data, dict) or (key is not None and key not in data):
        raise AdlError(f"{path}: not {what} (expected a JSON object{f' with {key!r}' if key else ''})")
    return data


MAX_YAML_BYTES = 1 << 20  # a topic map or segments file is a few lines; a larger one is not read


def read_small_yaml(path: Path, what: str) -> object:
    """A small YAML file a user wrote (a topic map, a segments sidecar), parsed safely: over MAX_YAML_BYTES or
    using aliases (a billion-laughs bomb expands them exponentially) it is refused before anything is built."""
    import yaml

    try:
        if path.stat().st_size > MAX_YAML_BYTES:
            raise AdlError(f"{path}: {what} is over {MAX_YAML_BYTES >> 20} MB; not read")
        text = path.read_text()
        if any(isinstance(e, yaml.AliasEvent) for e in yaml.parse(text)):
            raise AdlError(f"{path}: {what} uses YAML aliases (*name); write each value out")
        return yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise AdlError(f"{path}: cannot read {what}: {' '.join(str(exc).split())[:200]}") from None


# What each optional extra installs (pyproject.toml): a stage that needs one names it instead of a traceback.
EXTRAS = {"torch": "train", "mujoco": "sim", "rerun": "viz", "dvc": "pipeline"}


def missing_extra(exc: ModuleNotFoundError) -> str | None:
    """One line for a missing optional dependency (its module and the extra that installs it), else None."""
    root = (exc.name or "").split(".")[0]
    if root not in EXTRAS:
        return None
    return f"this needs {root}, which is not installed: pip install 'adlpipe[{EXTRAS[root]}]' (or 'adlpipe[all]')"


def one_line(exc: BaseException, limit: int = 100) -> str:
    """An exception's text on one line, at most `limit` characters (for a message that names it)."""
    return " ".join(str(exc).split())[:limit]


def os_error_message(exc: OSError) -> str:
    """One line for an operating-system error (disk full, permissions, a folder where a file should be)."""
    where = exc.filename or "an output file"
    if exc.errno == errno.ENOSPC:
        return f"no space left on device writing {where}"
    if exc.errno == errno.EROFS:
        return f"cannot write {where}: read-only file system"
    reason = exc.strerror or str(exc)
    return f"{where}: {reason}" if exc.filename else reason


# A Ctrl-C is remembered as well as raised: Python drops a KeyboardInterrupt that lands in a finaliser or a weakref
# callback ("Exception ignored in ..."), and h5py's and torch's objects run many. Every atomic commit checks the flag
# first (adlpipe.plumbing.atomic), so a swallowed Ctrl-C still stops the stage before it replaces an output.
_INTERRUPTED = threading.Event()
_COMMITTED: list[str] = []  # outputs replaced in full since the stage started, in order


def _on_sigint(signum: int, frame: object) -> None:
    _INTERRUPTED.set()
    raise KeyboardInterrupt


def _quiet_interrupts(unraisable: sys.UnraisableHookArgs) -> None:
    """A Ctrl-C that lands in a finaliser cannot propagate: Python prints it as a 5-8 line "Exception ignored"
    trace before the stage's one line. The flag above already holds it; anything else is printed as before."""
    if not isinstance(getattr(unraisable, "exc_value", None), KeyboardInterrupt):
        sys.__unraisablehook__(unraisable)


def check_interrupted() -> None:
    """Raise KeyboardInterrupt if a Ctrl-C came, even one that was swallowed where it landed."""
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt


def note_committed(path: Path | str) -> None:
    """An output was replaced in full (the interrupt message says so)."""
    _COMMITTED.append(str(path))


def interrupted_line(prog: str) -> str:
    """What an interrupted stage leaves: the outputs it had already replaced in full, or none."""
    done = list(dict.fromkeys(_COMMITTED))
    if not done:
        return f"{prog}: interrupted; no output was replaced (every output is as it was before this run)"
    names = ", ".join(done[-3:]) + (f" and {len(done) - 3} earlier" if len(done) > 3 else "")
    return f"{prog}: interrupted; written in full before the interrupt: {names}; every other output is as it was"


def run_cli(prog: str, main: Callable[[list[str] | None], int], argv: list[str] | None = None) -> int:
    """Run a stage's main(); AdlError, OS errors and KeyboardInterrupt become one line on stderr. Outputs are
    written atomically (adlpipe.plumbing.atomic), so whatever stopped the stage, the old files are still there."""
    _INTERRUPTED.clear()
    _COMMITTED.clear()
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGINT) if main_thread else None
    if previous is not None and previous is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, _on_sigint)
        if sys.unraisablehook is sys.__unraisablehook__:  # a hook someone else set is theirs to keep
            sys.unraisablehook = _quiet_interrupts
    if _running_as(prog):
        # The stage's own process: what its imports made (torch's and scipy's modules, about a million objects) is
        # never garbage, so the collector stops scanning it; Python's collections at exit took about 0.5 s of a
        # torch stage's 2 s start-and-end (measured). What the stage itself makes is collected as ever.
        gc.freeze()
    try:
        return main(argv)
    except AdlError as exc:
        return _fail(prog, str(exc))
    except OSError as exc:
        return _fail(prog, os_error_message(exc))
    except ModuleNotFoundError as exc:
        if (line := missing_extra(exc)) is None:
            raise
        return _fail(prog, line)
    except KeyboardInterrupt:
        print(interrupted_line(prog), file=sys.stderr)
        return 130
    except Exception:
        # A Ctrl-C that lands inside a C extension's import comes back as that import's error (mujoco's pybind11
        # init turns it into "ImportError: initialization failed", seen in CI): the flag says it was the Ctrl-C.
        if not _INTERRUPTED.is_set():
            raise
        print(interrupted_line(prog), file=sys.stderr)
        return 130
    finally:
        _INTERRUPTED.clear()  # the stage is over: its Ctrl-C must not stop whatever runs next in this process
        if previous is not None and not _running_as(prog):
            signal.signal(signal.SIGINT, previous)
        if _running_as(prog):
            # The stage is done (its outputs committed, or left as they were): a Ctrl-C now can undo nothing, and
            # during Python's own shutdown it would end the process by SIGINT or print an ignored KeyboardInterrupt
            # from a finaliser (both measured: about 1 in 4 runs when the signal came just after an ingest ended).
            signal.signal(signal.SIGINT, signal.SIG_IGN)


CONSOLE: list[str] = []  # the stage the `adlpipe` console command runs in this process (adlpipe.console)


def _running_as(prog: str) -> bool:
    """Whether this process was started as `python -m <prog>` or `adlpipe <stage>` (not a test calling the stage in
    its own process)."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    started = (spec is not None and spec.name == prog) or prog in CONSOLE
    return started and threading.current_thread() is threading.main_thread()


def _fail(prog: str, message: str) -> int:
    print(f"{prog}: error: {' '.join(message.split())}", file=sys.stderr)  # always a single line
    return 2
