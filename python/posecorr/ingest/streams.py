"""The two time series a robot cell records, as read from any recording format.

Times are seconds on the recording's clock(s) (float64: nanosecond stamps of a 10-minute
recording keep sub-microsecond resolution); each stream is sorted by time on construction.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..textui import counted


def median_period(t: np.ndarray) -> float:
    """A stream's sampling period (s): the median step of its times (dropped samples do not
    lengthen it), 0 with fewer than two."""
    return float(np.median(np.diff(t))) if len(t) > 1 else 0.0


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

    def subset(self, keep: np.ndarray) -> "JointStream":
        return replace(self, t=self.t[keep], q=self.q[keep], notes=list(self.notes))


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

    def subset(self, keep: np.ndarray) -> "PoseStream":
        return replace(self, t=self.t[keep], p=self.p[keep], q=self.q[keep], notes=list(self.notes))


def keep_usable(stream: JointStream | PoseStream, values: np.ndarray) -> JointStream | PoseStream:
    """The stream without the samples a bag may carry and no later step can use, each kind
    counted in a note: samples whose `values` (N, k) (the columns used) are not finite (a
    tracker publishes NaN when it loses track, a driver for a joint it cannot read), and
    samples that repeat the stamp of the one before (a driver publishing a state twice, a
    bridge stamping two poses alike: the first of each stamp is kept, as the recorder got it).
    Rates, speeds and the clock alignment divide by time steps, so they must be > 0. A CSV log
    is refused for either, naming the row (csvlog). IngestError when nothing is left."""
    finite = np.isfinite(values).all(axis=1) & np.isfinite(stream.t)
    if not finite.any():
        raise IngestError(f"{stream.source}: every one of the {len(finite)} samples has NaN or infinite values")
    # The stream is sorted stably by time: a repeated stamp follows its first sample.
    kept = np.flatnonzero(finite)
    repeated = np.zeros(len(finite), dtype=bool)
    repeated[kept[1:]] = np.diff(stream.t[kept]) <= 0
    if finite.all() and not repeated.any():
        return stream
    usable = stream.subset(finite & ~repeated)
    if not finite.all():
        usable.notes.append(f"{stream.source}: left out {int(np.sum(~finite))} of {len(finite)} samples "
                            "with NaN or infinite values")
    if repeated.any():
        n = int(np.sum(repeated))
        usable.notes.append(f"{stream.source}: left out {counted(n, 'sample')} that {'repeats' if n == 1 else 'repeat'} "
                            "the stamp of the one before (the first of each stamp kept)")
    return usable


def _sorted(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(t, kind="stable")
    return t[order], values[order]
