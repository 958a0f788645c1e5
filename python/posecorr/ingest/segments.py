"""Still segments: where the robot stood, which tracker samples to trust there, and their mean.

A still segment is a stretch of the joint stream where every joint turns slower than
`speed` rad/s (finite differences, smoothed over `SMOOTH_S`) for at least `min_duration` s,
without a gap in the joint stream. `settle` s are dropped at both ends (the arm rings after
it stops and the planner leaves before the speed rises). Tracker samples in what is left are
gated by RMS: a sample is kept when the RMS of the position deviations from the segment's
median over the `GATE_WINDOW_S` around it is at most `gate` metres, which drops bursts of
jitter (reflections, partial occlusion) and isolated jumps with their neighbours. The kept
samples are averaged: positions arithmetically, orientations by the quaternion mean.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SMOOTH_S = 0.05        # s, moving average of the joint speed (encoder noise differentiates badly)
GATE_WINDOW_S = 0.1    # s, the RMS window of the gate
GAP_FACTOR = 5.0       # a joint-stream gap longer than this many median periods breaks a segment


@dataclass
class Segment:
    """One still segment; times on the robot clock, s. status 'ok' or 'rejected' (with `reason`)."""

    index: int
    start: float
    end: float
    window: tuple[float, float]
    q: np.ndarray
    n_joint: int
    n_tracker: int = 0
    n_kept: int = 0
    p: np.ndarray | None = None
    quat: np.ndarray | None = None
    jitter_mm: float | None = None
    status: str = "ok"
    reason: str = ""
    row: int | None = field(default=None)

    def describe(self, t0: float) -> dict:
        return {"segment": self.index, "row": self.row, "status": self.status, "reason": self.reason or None,
                "start_s": self.start - t0, "end_s": self.end - t0, "duration_s": self.end - self.start,
                "window_s": [self.window[0] - t0, self.window[1] - t0], "joint_samples": self.n_joint,
                "tracker_samples": self.n_tracker, "kept_samples": self.n_kept, "jitter_mm": self.jitter_mm}


def moving_average(x: np.ndarray, n: int) -> np.ndarray:
    """Centred moving average over n samples along axis 0 (shorter windows at the ends)."""
    if n <= 1:
        return x
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    half = n // 2
    i = np.arange(len(x))
    lo, hi = np.clip(i - half, 0, len(x)), np.clip(i + half + 1, 0, len(x))
    shape = (-1,) + (1,) * (x.ndim - 1)
    return (c[hi] - c[lo]) / (hi - lo).reshape(shape)


def joint_speed(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(N,) the fastest joint's speed in rad/s, smoothed over SMOOTH_S."""
    if len(t) < 3:
        return np.zeros(len(t))
    dq = np.gradient(q, t, axis=0)
    period = float(np.median(np.diff(t)))
    return moving_average(np.abs(dq).max(axis=1), max(1, int(round(SMOOTH_S / period))))


def still_intervals(t: np.ndarray, speed: np.ndarray, threshold: float, min_duration: float) -> list[tuple[int, int]]:
    """[(first, last)] sample indices of stretches below `threshold` lasting >= min_duration, split at gaps."""
    still = speed < threshold
    if len(t) > 1:
        gaps = np.diff(t) > GAP_FACTOR * np.median(np.diff(t))
        breaks = np.flatnonzero(gaps)             # a segment may not span sample i -> i + 1
    else:
        breaks = np.array([], dtype=int)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    out = []
    for first, stop in zip(edges[::2], edges[1::2]):
        cuts = breaks[(breaks >= first) & (breaks < stop - 1)]
        bounds = np.concatenate([[first], cuts + 1, [stop]])
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b - 1 > a and t[b - 1] - t[a] >= min_duration:
                out.append((int(a), int(b - 1)))
    return out


def quaternion_mean(q: np.ndarray) -> np.ndarray:
    """The mean orientation of unit quaternions (N, 4) (w first): the eigenvector of sum q q^T with
    the largest eigenvalue (Markley et al. 2007), blind to each quaternion's sign; w >= 0."""
    q = np.asarray(q, float)
    M = q.T @ q
    _, vectors = np.linalg.eigh(M)
    mean = vectors[:, -1]
    return mean if mean[0] >= 0 else -mean


def gate(t: np.ndarray, p: np.ndarray, threshold_m: float) -> np.ndarray:
    """(M,) bool, the samples kept by the RMS gate (module docstring)."""
    if len(p) == 0:
        return np.zeros(0, dtype=bool)
    d2 = np.sum((p - np.median(p, axis=0)) ** 2, axis=1)
    period = float(np.median(np.diff(t))) if len(t) > 1 else GATE_WINDOW_S
    n = max(1, int(round(GATE_WINDOW_S / max(period, 1e-9))))
    return np.sqrt(moving_average(d2, n)) <= threshold_m


@dataclass(frozen=True)
class StillOptions:
    speed: float = 0.01          # rad/s, the fastest joint
    min_duration: float = 2.0    # s
    settle: float = 0.5          # s dropped at each end
    gate_mm: float = 1.0         # mm, windowed RMS deviation
    max_jitter_mm: float = 0.5   # mm, RMS of the kept samples about their mean
    min_samples: int = 100       # kept tracker samples


def find_segments(t: np.ndarray, q: np.ndarray, options: StillOptions) -> list[Segment]:
    """The still segments of a joint stream, with their mean joint angles over the settled window."""
    segments = []
    for a, b in still_intervals(t, joint_speed(t, q), options.speed, options.min_duration):
        lo, hi = t[a] + options.settle, t[b] - options.settle
        inside = slice(np.searchsorted(t, lo), np.searchsorted(t, hi, side="right"))
        segments.append(Segment(len(segments), float(t[a]), float(t[b]), (float(lo), float(hi)),
                                q[inside].mean(axis=0), inside.stop - inside.start))
    return segments


def measure(segment: Segment, t: np.ndarray, p: np.ndarray, quat: np.ndarray, options: StillOptions) -> None:
    """Gate and average the tracker samples (aligned times t) of one segment's window, in place."""
    lo, hi = np.searchsorted(t, segment.window[0]), np.searchsorted(t, segment.window[1], side="right")
    segment.n_tracker = int(hi - lo)
    keep = gate(t[lo:hi], p[lo:hi], options.gate_mm * 1e-3)
    kept_p, kept_q = p[lo:hi][keep], quat[lo:hi][keep]
    segment.n_kept = int(len(kept_p))
    if segment.n_kept:
        segment.p = kept_p.mean(axis=0)
        segment.quat = quaternion_mean(kept_q)
        segment.jitter_mm = float(np.sqrt(np.mean(np.sum((kept_p - segment.p) ** 2, axis=1))) * 1e3)
    if segment.n_kept < options.min_samples:
        segment.status = "rejected"
        segment.reason = (f"too few samples: {segment.n_kept} kept of {segment.n_tracker} "
                          f"(--min-samples {options.min_samples})")
    elif segment.jitter_mm > options.max_jitter_mm:
        segment.status = "rejected"
        segment.reason = f"too much jitter: {segment.jitter_mm:.3f} mm (--max-jitter-mm {options.max_jitter_mm:g})"
