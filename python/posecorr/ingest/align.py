"""The clock offset between the robot and the tracker streams.

The tracker's point moves with the flange, so its speed, computed from the tracker's own
positions, is the speed of the forward-kinematics tracker point on the robot clock, shifted
by the offset (speeds do not depend on the frame, so this needs no registration). The offset
is the lag that maximises the correlation of the two speed signals: coarse by FFT on a
`COARSE_HZ` grid within +-max_offset, then refined by least squares on the positions
(`_refine`). Convention: tracker stamp = robot time + offset.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..data import PLAUSIBLE_SESSION_S
from ..registration import umeyama
from .segments import moving_average
from .streams import IngestError

COARSE_HZ = 100.0
SMOOTH_S = 0.04            # s, position smoothing before differentiation (tracker jitter)
GAP_FACTOR = 3.0           # tracker gaps longer than this many median periods carry no speed
MIN_MOTION_M_S = 0.005     # the robot must move faster than this somewhere to align on its motion
MIN_CORRELATION = 0.5
# Below this correlation a lag beyond --max-offset is looked for, up to WIDER times it, and one
# that correlates CLEARLY_BETTER is named (right offsets correlate at 0.95-0.98 in simulated
# recordings, a stop early or late at 0.73-0.82).
WELL_ALIGNED = 0.9
WIDER = 4.0
CLEARLY_BETTER = 0.1
OUTLIER_FACTOR = 4.0       # residuals beyond this many medians leave the offset fit
# s: the shortest stream (joints, tracker) the offset is estimated from. Its speeds are smoothed over SMOOTH_S
# on the COARSE_HZ grid: a stream of less than a few smoothing windows leaves next to no speed
# sample that smoothing has not flattened, nothing to correlate (under one grid step, no grid).
MIN_SPAN_S = 0.1
# The most steps of the COARSE_HZ grid (the joint stream's span) the offset is estimated on: a
# session's. Each step takes some hundred bytes; a stray stamp decades off, or stamps in
# nanoseconds, would ask for terabytes.
MAX_GRID_STEPS = PLAUSIBLE_SESSION_S * COARSE_HZ


@dataclass(frozen=True)
class Alignment:
    offset: float          # s, tracker clock - robot clock
    correlation: float | None   # at the offset, Pearson over the overlap; None when given
    source: str            # "estimated" or "given"


def speed_on_grid(t: np.ndarray, p: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(speed, valid) of the point p(t) resampled on `grid` (uniform); invalid outside t and in gaps."""
    period = float(np.median(np.diff(t)))
    step = grid[1] - grid[0]
    n = max(1, int(round(SMOOTH_S / step)))
    resampled = np.stack([np.interp(grid, t, p[:, k]) for k in range(3)], axis=1)
    v = np.gradient(moving_average(resampled, n), step, axis=0)
    valid = (grid >= t[0]) & (grid <= t[-1])
    gap_starts = np.flatnonzero(np.diff(t) > GAP_FACTOR * period)
    for i in gap_starts:
        valid &= ~((grid > t[i] - SMOOTH_S) & (grid < t[i + 1] + SMOOTH_S))
    return np.linalg.norm(v, axis=1), valid


def check_overlap(t_robot: np.ndarray, t_tracker: np.ndarray, max_offset: float, what: str,
                  given: float | None = None) -> None:
    """IngestError when the streams cannot overlap for any offset within +-max_offset, or,
    with the offset `given` (--offset, already taken off t_tracker), at all."""
    if t_tracker[0] - max_offset <= t_robot[-1] and t_tracker[-1] + max_offset >= t_robot[0]:
        return
    why = (f"with --offset {given:.15g} s; the offset is the tracker clock minus the robot's" if given is not None
           else f"more than --max-offset {max_offset:g} s apart; a bag stamped on two clocks (a tracker's boot "
                "time) reads on the recorder's with --stamps receive, else give --offset, the tracker clock minus "
                "the robot's")
    raise IngestError(f"{what}: the streams do not overlap: joint states {t_robot[0]:.3f}..{t_robot[-1]:.3f} s, "
                      f"tracker {t_tracker[0]:.3f}..{t_tracker[-1]:.3f} s ({why})")


def _correlation(a: np.ndarray, a_ok: np.ndarray, b: np.ndarray, b_ok: np.ndarray) -> float:
    ok = a_ok & b_ok
    if ok.sum() < 3:
        return 0.0
    x, y = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    denominator = np.sqrt(np.sum(x * x) * np.sum(y * y))
    return float(np.sum(x * y) / denominator) if denominator > 0 else 0.0


def _quadratic_features(p: np.ndarray) -> np.ndarray:
    """(N, 10) 1, x, y, z and their products, of positions centred and scaled to unit spread."""
    x = (p - p.mean(axis=0)) / max(float(p.std()), 1e-9)
    i, j = np.triu_indices(3)
    return np.concatenate([np.ones((len(x), 1)), x, x[:, i] * x[:, j]], axis=1)


def _velocity_coefficient(v: np.ndarray, y: np.ndarray, F: np.ndarray) -> tuple[float, np.ndarray]:
    """(d, residual norms (N,)) of the least-squares fit y_k = -d v_k + F c_k (every axis k its own c_k).

    The c_k are eliminated in closed form (Schur complement); sums by einsum keep the
    hundreds of thousands of rows out of multi-threaded BLAS, which stalls on a busy machine.
    """
    G_inv = np.linalg.pinv(np.einsum("ni,nj->ij", F, F))   # pinv: constant orientations make R columns collinear
    Fv, Fy = np.einsum("ni,nk->ik", F, v), np.einsum("ni,nk->ik", F, y)
    numerator = -np.einsum("nk,nk->", v, y) + np.einsum("ik,ij,jk->", Fv, G_inv, Fy)
    denominator = np.einsum("nk,nk->", v, v) - np.einsum("ik,ij,jk->", Fv, G_inv, Fv)
    d = float(numerator / denominator)
    c = G_inv @ (Fy + Fv * d)
    return d, np.linalg.norm(y + d * v - F @ c, axis=1)


def _refine(t_robot: np.ndarray, T_robot: np.ndarray, t_tracker: np.ndarray, p_tracker: np.ndarray,
            coarse: float, iterations: int = 4) -> float:
    """The offset near `coarse`, by least squares on positions.

    With the tracker positions mapped rigidly onto the forward-kinematics point,
    p_tracker(t) - p_robot(t - lag) = -(offset - lag) v_robot(t - lag) + f(p, R) + noise, where f is
    what the tracker gets wrong at rest: a distortion of space (a quadratic in position absorbs
    most of it) and the error of the lever arm end_T_tracker, R e, linear in the entries of the
    orientation R, which joint-space moves change along the way. One linear solve gives
    offset - lag; a few rounds converge. Unlike the speed correlation this uses the exact
    positions at every sample, without smoothing.
    """
    p_robot = T_robot[:, :3, 3]
    R_robot = T_robot[:, :3, :3].reshape(-1, 9)
    velocity = np.gradient(p_robot, t_robot, axis=0)
    lag = coarse
    inlier = np.ones(len(t_tracker), dtype=bool)
    for _ in range(iterations):
        inside = (t_tracker - lag > t_robot[0]) & (t_tracker - lag < t_robot[-1]) & inlier
        t, p = t_tracker[inside] - lag, p_tracker[inside]
        target = np.stack([np.interp(t, t_robot, p_robot[:, k]) for k in range(3)], axis=1)
        v = np.stack([np.interp(t, t_robot, velocity[:, k]) for k in range(3)], axis=1)
        rotation, shift, _ = umeyama(p, target)
        mapped = p @ rotation.T + shift
        R = np.stack([np.interp(t, t_robot, R_robot[:, k]) for k in range(9)], axis=1)
        d, residual = _velocity_coefficient(v, mapped - target, np.concatenate([_quadratic_features(target), R], axis=1))
        lag += d
        # Bursts of jitter would pull the fit: later rounds leave out samples far off the model.
        inlier[np.flatnonzero(inside)[residual > OUTLIER_FACTOR * np.median(residual)]] = False
    return lag


def _coarse(grid: np.ndarray, r: np.ndarray, r_ok: np.ndarray, t_tracker: np.ndarray, p_tracker: np.ndarray,
            max_offset: float) -> tuple[float, float]:
    """(the lag within +-max_offset that best matches the tracker's speed to the robot's `r` on
    `grid`, their correlation there): every lag at once, by one FFT correlation."""
    step = grid[1] - grid[0]
    lags = np.arange(-int(round(max_offset / step)), int(round(max_offset / step)) + 1)
    tgrid = np.arange(grid[0] - max_offset - step, grid[-1] + max_offset + 2 * step, step)
    s, s_ok = speed_on_grid(t_tracker, p_tracker, tgrid)
    rz = np.where(r_ok, r - r[r_ok].mean(), 0.0)
    sz = np.where(s_ok, s - (s[s_ok].mean() if s_ok.any() else 0.0), 0.0)
    size = 1 << int(np.ceil(np.log2(len(tgrid) + len(grid))))
    full = np.fft.irfft(np.fft.rfft(sz, size) * np.conj(np.fft.rfft(rz, size)), size)
    base = int(round((grid[0] - tgrid[0]) / step))   # tgrid index of grid[0] at zero lag
    coarse = lags[int(np.argmax(full[(base + lags) % size]))] * step
    return coarse, _correlation(r, r_ok, *speed_on_grid(t_tracker, p_tracker, grid + coarse))


def _refuse_better_outside(grid: np.ndarray, r: np.ndarray, r_ok: np.ndarray, t_tracker: np.ndarray,
                           p_tracker: np.ndarray, max_offset: float, correlation: float, what: str) -> None:
    """IngestError when the speeds match clearly better at a lag beyond --max-offset. A robot
    that stops at targets a few seconds apart matches the tracker fairly well one stop early or
    late too: a true offset just outside the range would align every pose with the previous
    stop's tracker pose, and the table would look like any other."""
    wider, wider_correlation = _coarse(grid, r, r_ok, t_tracker, p_tracker, WIDER * max_offset)
    if abs(wider) > max_offset and wider_correlation > correlation + CLEARLY_BETTER:
        raise IngestError(f"{what}: the robot's and the tracker's speeds match best at a clock offset of "
                          f"{wider:+.2f} s (correlation {wider_correlation:.2f}), beyond --max-offset {max_offset:g} s "
                          f"(at most {correlation:.2f} within it); raise --max-offset to "
                          f"{math.ceil(abs(wider) + 1):g} or give --offset")


def estimate_offset(t_robot: np.ndarray, T_robot: np.ndarray, t_tracker: np.ndarray, p_tracker: np.ndarray,
                    max_offset: float, what: str) -> Alignment:
    """The offset (module docstring) from the FK tracker poses T_robot (N, 4, 4) at t_robot and the
    tracker's positions p_tracker at t_tracker."""
    p_robot = T_robot[:, :3, 3]
    check_overlap(t_robot, t_tracker, max_offset, what)
    for stream, t, sample in (("joint", t_robot, "joint state"), ("tracker", t_tracker, "tracker pose")):
        span = float(t[-1] - t[0])
        if span < MIN_SPAN_S:
            samples = f"{len(t)} {sample}" + ("s" if len(t) != 1 else "")
            raise IngestError(f"{what}: the {stream} stream is too short to find the clock offset: it spans "
                              f"{span:.3g} s ({samples}), and the estimate takes at least {MIN_SPAN_S:g} s of "
                              "motion; give --offset, the tracker clock minus the robot's")
    step = 1.0 / COARSE_HZ
    span = float(t_robot[-1] - t_robot[0])
    if span / step > MAX_GRID_STEPS:
        raise IngestError(f"{what}: the joint states span {span:.6g} s ({span / 86_400:.3g} days), "
                          f"{span / step:.3g} steps of the {COARSE_HZ:g} Hz grid the clock offset is estimated on, "
                          f"more than a {PLAUSIBLE_SESSION_S / 86_400:g}-day session's {MAX_GRID_STEPS:.3g}; check the "
                          "stamps (one far off the others?), or give --offset")
    grid = np.arange(t_robot[0], t_robot[-1], step)
    r, r_ok = speed_on_grid(t_robot, p_robot, grid)
    if not np.any(r[r_ok] > MIN_MOTION_M_S):
        raise IngestError(f"{what}: the robot does not move, so the clocks cannot be aligned on its motion; "
                          "give --offset")
    coarse, correlation = _coarse(grid, r, r_ok, t_tracker, p_tracker, max_offset)
    if correlation < MIN_CORRELATION:
        raise IngestError(f"{what}: the robot's and the tracker's speeds correlate at most {correlation:.2f} "
                          f"(expected >= {MIN_CORRELATION}): wrong topics, or clocks more than --max-offset "
                          f"{max_offset:g} s apart; give --offset")
    if correlation < WELL_ALIGNED:
        _refuse_better_outside(grid, r, r_ok, t_tracker, p_tracker, max_offset, correlation, what)
    offset = _refine(t_robot, T_robot, t_tracker, p_tracker, coarse)
    if abs(offset) > max_offset - 2 * step:
        raise IngestError(f"{what}: the best clock offset {offset:+.3f} s lies at the edge of --max-offset "
                          f"{max_offset:g} s; raise --max-offset or give --offset")
    return Alignment(offset, correlation, "estimated")
