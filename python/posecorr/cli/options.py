"""Numeric option types: each checks range and finiteness where argparse reads the option,
so a bad value ends as `argument --NAME: ...` (exit 2) before any work, and no option can
ask for unbounded work (`--targets 1000000`, `--batch 1e9`, `--hidden 100000`)."""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Callable


def integer(lo: int, hi: int | None = None, *, what: str = "") -> Callable[[str], int]:
    """An int in [lo, hi] (hi None: no upper bound)."""
    def parse(text: str) -> int:
        try:
            # int() and float() take the blanks around a number themselves; str.strip() would
            # also take control characters (U+001C..U+001F) they refuse: "1\x1f" is no number.
            value = int(text)
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
            value = float(text)
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


def file_name(text: str) -> Path:
    """A file to write. A trailing separator names a folder, and Path would drop it
    (`-o newdir/` would write a file named newdir); "-", standard output to most tools, would
    be a file named "-" (every output here is a file, written whole or not at all)."""
    if text == "-":
        raise argparse.ArgumentTypeError("'-' would be a file named '-' (posecorr writes its outputs to files, "
                                         "never to standard output); expected a file name to write")
    if not text:   # Path("") is ".", the working folder
        raise argparse.ArgumentTypeError("an empty name; expected a file name to write")
    if text.endswith(("/", os.sep)):
        raise argparse.ArgumentTypeError(f"{text!r} ends with a separator (a folder); expected a file name to write")
    return Path(text)


file_name.__name__ = "file name"


def cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


SEED = integer(0, 2**32 - 1)
THREADS = integer(1, 1024)
WORKERS = integer(1, 1024)
# Trainers that keep P x P matrices of the P weights (the Gauss-Newton matrix of LM and BR,
# BFGS' inverse Hessian): 5,000 weights is 200 MB per matrix, 1024,1024 would be 8 TB.
SECOND_ORDER_TRAINERS = ("lm", "br", "bfg")
SECOND_ORDER_WEIGHTS_MAX = 5000


def layer_sizes(text: str, option: str) -> tuple[int, ...]:
    """'20-20', '20x20' or '20,20' -> (20, 20): `train.spec.parse_hidden`'s grammar and
    bounds, refused in one line naming the option; at least one layer."""
    from ..train.spec import parse_hidden
    from .common import CliError

    try:
        sizes = parse_hidden(text)
    except ValueError as exc:
        raise CliError(f"{option}: {exc}") from None
    if not sizes:
        raise CliError(f"{option}: give at least one layer size, got {text!r}")
    return sizes


def check_network_size(hidden: tuple[int, ...], trainer: str, option: str) -> None:
    """A network whose trainer would need P x P matrices larger than memory is refused
    before any work; the hidden-to-hidden weights alone are a lower bound of P."""
    from .common import CliError

    weights = sum(a * b for a, b in zip(hidden, hidden[1:])) + sum(hidden)
    if trainer in SECOND_ORDER_TRAINERS and weights > SECOND_ORDER_WEIGHTS_MAX:
        raise CliError(f"{option}: a network of more than {weights:,} weights; trainer {trainer} keeps "
                       f"matrices of weights x weights, so it takes at most {SECOND_ORDER_WEIGHTS_MAX:,} "
                       "(choose smaller layers or a first-order --trainer such as adam or rp)")


def station_pose(text: str) -> str | None:
    """`--station-pose`, checked where argparse reads it (`geometry.parse_station_pose`): the
    text as written, None for the paper's station."""
    from ..geometry import parse_station_pose

    try:
        return parse_station_pose(text, argparse.ArgumentTypeError).text
    except argparse.ArgumentTypeError as exc:   # argparse names the option itself
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--station-pose ")) from None
