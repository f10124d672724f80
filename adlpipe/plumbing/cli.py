"""What every stage's command line shares: a parser whose errors are one line, and number types that check their
range at the parser, so a bad option never reaches the code as ZeroDivisionError or an endless loop."""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from .atomic import refuse_special_outputs
from .errors import AdlError

C = TypeVar("C")


class Parser(argparse.ArgumentParser):
    """argparse with the stage's docstring as help and a single-line error (no usage block) on bad options; with
    io(), the parsed outputs are checked against the inputs, so that no output ever overwrites an input."""

    def __init__(self, prog: str, description: str | None = None) -> None:
        super().__init__(prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
        self._io: tuple[Sequence[str], Sequence[str], Callable | None, bool] | None = None

    def io(self, inputs: Sequence[str], outputs: Sequence[str],
           implied: Callable[[argparse.Namespace], Iterable[Path]] | None = None,
           writes_datasets: bool = False) -> None:
        """Declare which options (by dest) name the stage's inputs and its outputs; `implied`: inputs the arguments
        imply (e.g. the split.json beside a dataset when --split is not given); writes_datasets: its output is a
        dataset (ingest appends to one), so an existing dataset is a valid output."""
        self._io = (inputs, outputs, implied, writes_datasets)

    def parse_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                   namespace: argparse.Namespace | None = None) -> argparse.Namespace:
        parsed = super().parse_args(args, namespace)
        if self._io is not None:
            inputs, outputs, implied, writes_datasets = self._io
            ins = [p for d in inputs for p in _paths(getattr(parsed, d, None))]
            outs = [p for d in outputs for p in _paths(getattr(parsed, d, None))]
            refuse_special_outputs(*outs)  # first: reading a FIFO to check it would block
            refuse_overwriting_inputs(outs, ins + list(implied(parsed) if implied else []))
            if not writes_datasets:
                refuse_overwriting_datasets(outs)
        if os.environ.get("ADLPIPE_PARSE_ONLY"):  # the documentation's test: the command parses, nothing runs
            raise SystemExit(0)
        return parsed

    def add_force(self) -> None:
        """--force: replace outputs a DVC pipeline owns (adlpipe.plumbing.dvc_outputs refuses them otherwise)."""
        self.add_argument("--force", action="store_true",
                          help="replace outputs that a DVC pipeline (dvc.lock) owns; refused without it outside dvc "
                          "repro")

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {' '.join(message.split())} (see --help)", file=sys.stderr)
        sys.exit(2)


def _paths(value: object) -> list[Path]:
    if value is None:
        return []
    if isinstance(value, (list, tuple)):
        return [Path(str(v)) for v in value if v is not None]
    return [Path(str(value))]


def refuse_overwriting_inputs(outputs: Iterable[Path], inputs: Iterable[Path]) -> None:
    """One line before any work when an output is an input (or resolves to it, through links), or lies among a
    dataset's episode files (the x.shards folder its index x.h5 links to)."""
    ins = [(Path(p), Path(p).resolve()) for p in inputs]
    shards = [(p, p.with_name(p.stem + ".shards").resolve()) for p, _ in ins if p.suffix == ".h5"]
    for out in outputs:
        o = Path(out).resolve()
        for given, i in ins:
            if o == i:
                raise AdlError(f"{out}: is an input of this command ({given}); writing it would destroy that input, "
                               "give another output path")
        for given, folder in shards:
            if o == folder or folder in o.parents:
                raise AdlError(f"{out}: lies among the episode files of the dataset {given}; give another output path")


HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def refuse_overwriting_datasets(outputs: Iterable[Path]) -> None:
    """One line when an output of a stage that writes no dataset is an existing HDF5 file or lies in a dataset's
    folder of episode files (x.shards): a dataset is never an output by mistake."""
    for out in map(Path, outputs):
        if any(p.name.endswith(".shards") for p in [out, *out.parents]):
            raise AdlError(f"{out}: lies in a dataset's folder of episode files; give another output path")
        try:
            with open(out, "rb") as f:
                head = f.read(8)
        except OSError:
            continue  # no such file (or a folder): nothing to destroy
        if head == HDF5_SIGNATURE:
            raise AdlError(f"{out}: is an HDF5 file (a dataset?); this command would overwrite it, give another "
                           "output path")


def _number(kind: type, lo: float | None, hi: float | None, lo_open: bool = False) -> Callable[[str], float]:
    lo_txt = "" if lo is None else (f"> {lo}" if lo_open else f">= {lo}")
    hi_txt = "" if hi is None else f"<= {hi}"
    allowed = " and ".join(t for t in (lo_txt, hi_txt) if t)

    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if isinstance(value, float) and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
        if (lo is not None and (value <= lo if lo_open else value < lo)) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"{text} is out of range: must be {allowed}")
        return value

    parse.__name__ = f"{kind.__name__} {allowed}".strip()
    return parse


def int_range(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    return _number(int, lo, hi)  # type: ignore[return-value]


def float_range(lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> Callable[[str], float]:
    return _number(float, lo, hi, lo_open)


POSITIVE = int_range(1)
NON_NEGATIVE = int_range(0)
SEED = int_range(0, 2**32 - 1)  # what every generator it reaches accepts (numpy, torch, the gym environments)


def read_token_file(path: Path) -> str:
    """A --token-file's shared token (its first 4 KiB, stripped), or one line saying why it cannot be one."""
    try:
        token = path.read_text()[:4096].strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise AdlError(f"--token-file {path}: cannot read it ({exc})") from None
    if not token:
        raise AdlError(f"--token-file {path}: empty")
    return token


def config_from(args: argparse.Namespace, config: type[C], **given: Any) -> C:
    """The stage's typed configuration (a dataclass) from its parsed options: each field from the option of the same
    name, or from `given` (a field the stage derives: a default path, the device placement). Built once, in the
    stage; nothing below it sees the namespace."""
    names = [f.name for f in fields(config)]  # type: ignore[arg-type]
    return config(**{n: given[n] if n in given else getattr(args, n) for n in names})
