"""The two time series a robot cell records, as read from any recording format.

Times are seconds on the recording's clock(s) (float64: nanosecond stamps of a 10-minute
recording keep sub-microsecond resolution); each stream is sorted by time on construction.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class IngestError(ValueError):
    """A recording that cannot be turned into a table: one line naming the file and what was expected."""


@dataclass
class JointStream:
    """Joint angles q (N, n) in rad at times t (N,), columns named by `names`.

    positional: the columns are the arm's joints in kinematic order by the format's layout
    (a CSV log's --joint-cols), whatever their names. notes: what the reader left out.
    """

    t: np.ndarray
    q: np.ndarray
    names: tuple[str, ...]
    source: str = ""
    positional: bool = False
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.t, self.q = _sorted(np.asarray(self.t, float), np.asarray(self.q, float))


@dataclass
class PoseStream:
    """Tracker poses: positions p (M, 3) in m, unit quaternions q (M, 4) (w, x, y, z), at times t (M,)."""

    t: np.ndarray
    p: np.ndarray
    q: np.ndarray
    frame: str = ""
    source: str = ""
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        t = np.asarray(self.t, float)
        order = np.argsort(t, kind="stable")
        self.t, self.p, self.q = t[order], np.asarray(self.p, float)[order], np.asarray(self.q, float)[order]


def _sorted(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(t, kind="stable")
    return t[order], values[order]
