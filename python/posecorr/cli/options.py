"""Numeric option types: each checks range and finiteness where argparse reads the option,
so a bad value ends as `argument --NAME: ...` (exit 2) before any work, and no option can
ask for unbounded work (`--targets 1000000`, `--batch 1e9`, `--hidden 100000`)."""
from __future__ import annotations

import argparse
import math
import os
from typing import Callable


def integer(lo: int, hi: int | None = None, *, what: str = "") -> Callable[[str], int]:
    """An int in [lo, hi] (hi None: no upper bound)."""
    def parse(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < lo or (hi is not None and value > hi):
            span = f">= {lo}" if hi is None else f"in {lo}..{hi}"
            raise argparse.ArgumentTypeError(f"expected an integer {span}{what}, got {value}")
        return value

    parse.__name__ = "integer"  # argparse names the type in its messages
    return parse


def real(lo: float | None = None, hi: float | None = None, *, open_lo: bool = False,
         what: str = "") -> Callable[[str], float]:
    """A finite float in [lo, hi] ((lo, hi] when open_lo)."""
    def parse(text: str) -> float:
        try:
            value = float(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        below = lo is not None and (value <= lo if open_lo else value < lo)
        if below or (hi is not None and value > hi):
            left = "" if lo is None else (f"> {lo:g}" if open_lo else f">= {lo:g}")
            right = "" if hi is None else f"<= {hi:g}"
            raise argparse.ArgumentTypeError(f"expected a number {' and '.join(p for p in (left, right) if p)}"
                                             f"{what}, got {text}")
        return value

    parse.__name__ = "number"
    return parse


def cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


SEED = integer(0, 2**32 - 1)
THREADS = integer(1, 1024)
# The paper's largest network is 4 x 20; layers of a few hundred already train for hours.
LAYER_WIDTH_MAX = 1024


def layer_sizes(text: str, option: str, separator: str) -> tuple[int, ...]:
    """'20,20' -> (20, 20): hidden layer widths in 1..LAYER_WIDTH_MAX."""
    from .common import CliError

    sizes = []
    for part in text.split(separator):
        if not part.strip():
            continue
        try:
            size = int(part)
        except ValueError:
            size = 0
        if not 1 <= size <= LAYER_WIDTH_MAX:
            raise CliError(f"{option}: layer sizes are integers in 1..{LAYER_WIDTH_MAX}, got {part.strip()!r}")
        sizes.append(size)
    if not sizes:
        raise CliError(f"{option}: give at least one layer size, got {text!r}")
    return tuple(sizes)
