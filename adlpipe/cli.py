"""What every stage's command line shares: a parser whose errors are one line, and number types that check their
range at the parser, so a bad option never reaches the code as ZeroDivisionError or an endless loop."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from typing import NoReturn


class Parser(argparse.ArgumentParser):
    """argparse with the stage's docstring as help and a single-line error (no usage block) on bad options."""

    def __init__(self, prog: str, description: str | None = None) -> None:
        super().__init__(prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)

    def add_force(self) -> None:
        """--force: replace outputs a DVC pipeline owns (adlpipe.dvc_outputs refuses them otherwise)."""
        self.add_argument("--force", action="store_true",
                          help="replace outputs that a DVC pipeline (dvc.lock) owns; refused without it outside dvc "
                          "repro")

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {' '.join(message.split())} (see --help)", file=sys.stderr)
        sys.exit(2)


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
