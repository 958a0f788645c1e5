"""Simulated recordings of the paper's cell: what `posecorr ingest` reads, made from a simulated table.

The UR5e visits the first targets of a simulated experiment (`simulate.simulate`, measurement
order) through their inverse kinematics (eq. 21), from a home posture, on one posture branch
(elbow up, as in the paper). Between stops the joints follow synchronised trapezoidal
velocity profiles (UR `movej` with a move time); stop k is `stand` s long and centred on the
table's t = (k + 1) dwell, so the table and the recording share their clock. Joint states are
published at `joint_hz`, the tracker at `tracker_hz` on its own clock (robot time + offset).

The tracker reports, in the station frame (eq. 20 undone with the nominal base_T_station):
- standing at target k: the table's measured pose k (its effects and its per-pose noise);
- moving: the experiment's effects (all but `noise`) applied to the moving reference pose;
- on top: per-sample jitter (the catalogue's `noise` effect with the jitter magnitudes), a
  decaying ring after each arrival (what the settle time drops), bursts of large jitter (what
  the RMS gate drops), dropped samples and gaps, and stamp jitter.
So ingesting the recording must give back the table: the same references, the measured poses
within the jitter, and the offset.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from . import geometry
from .data import PoseTable
from .effects import EffectContext, apply_effects, get_effect
from .ingest.csvlog import write_csv_log
from .ingest.rosformats import write_mcap, write_ros1_bag, write_ros2_bag
from .ingest.streams import IngestError, JointStream, PoseStream
from .kinematics import DEFAULT_ARM, UR_ARMS, UR_JOINT_NAMES, inverse, reference_poses
from .metrics import pose_metrics
from .rotations import matrix_to_quat, matrix_to_rotvec, quat_to_matrix, rotvec_to_matrix
from .simulate import SimulationResult

# Elbow up, wrist down, flange up: the posture the paper keeps over the whole cube (section 2.2).
HOME = np.array([np.pi / 2, -1.2, 1.75, -2.1, np.pi / 2, 0.0])
EPOCH_S = 1_700_000_000.0      # recordings carry wall-clock stamps


@dataclass(frozen=True)
class RecordingOptions:
    joint_hz: float = 500.0
    tracker_hz: float = 250.0
    stand: float = 6.0                 # s still at each target (of the dwell)
    ramp: float = 0.25                 # fraction of a move spent accelerating (and decelerating)
    clock_offset: float = 0.137        # s, tracker clock - robot clock
    stamp_jitter: float = 2e-4         # s, standard deviation of the tracker's stamps
    jitter_p: float = 1.5e-4           # m per axis, per sample (literature: 0.15 mm static jitter)
    jitter_r: float = 3e-4             # rad per axis, per sample
    joint_noise: float = 1e-6          # rad, encoder noise
    ring: float = 4e-4                 # m, amplitude of the ring after arrival
    ring_tau: float = 0.08             # s, its decay time
    ring_hz: float = 7.0
    loss: float = 0.01                 # probability of a lost tracker sample
    gap_rate: float = 1 / 40           # gaps per s (line-of-sight losses)
    gap_length: tuple[float, float] = (0.05, 0.4)   # s
    burst_rate: float = 1 / 60         # bursts per s
    burst_length: float = 0.3          # s
    burst_sigma: float = 3e-3          # m per axis


@dataclass
class Recording:
    """The two streams (robot clock for joints, tracker clock for poses) and the truth behind them."""

    joints: JointStream
    tracker: PoseStream
    table: PoseTable
    offset: float
    stands: np.ndarray                 # (K, 2) s, robot clock, of each stop
    options: RecordingOptions = field(repr=False, default_factory=RecordingOptions)


def trapezoid(tau: np.ndarray, ramp: float) -> np.ndarray:
    """Normalised position 0..1 of a trapezoidal velocity profile at normalised time tau in [0, 1]."""
    tau = np.clip(tau, 0.0, 1.0)
    v = 1.0 / (1.0 - ramp)                 # cruise speed
    a = v / ramp
    rising = 0.5 * a * tau ** 2
    cruise = 0.5 * a * ramp ** 2 + v * (tau - ramp)
    falling = 1.0 - 0.5 * a * (1.0 - tau) ** 2
    return np.where(tau < ramp, rising, np.where(tau <= 1.0 - ramp, cruise, falling))


def joint_targets(reference: np.ndarray, arm_name: str = DEFAULT_ARM,
                  end_T_tracker: np.ndarray = geometry.END_T_TRACKER) -> np.ndarray:
    """(K, 6) joint angles reaching tracker poses (K, 4, 4) (eq. 21), each seeded by the previous one."""
    arm = UR_ARMS[arm_name]
    q, out = HOME, []
    for T in reference @ np.linalg.inv(end_T_tracker):
        q = inverse(arm, T, q)
        q = np.remainder(q + np.pi, 2 * np.pi) - np.pi
        out.append(q)
    return np.array(out)


class _Trajectory:
    """Home -> stops -> home; q(t) on the robot clock (s since the recording started)."""

    def __init__(self, q_stops: np.ndarray, centres: np.ndarray, stand: float, move: float, ramp: float) -> None:
        waypoints = np.vstack([HOME, np.repeat(q_stops, 2, axis=0), HOME])
        # Segment j runs from waypoint j to j + 1 over [times[j], times[j + 1]]: odd ones are stops.
        times = [0.0]
        for c in centres:
            times += [c - stand / 2, c + stand / 2]
        times.append(times[-1] + move)
        self.waypoints, self.times, self.ramp = waypoints, np.array(times), ramp

    @property
    def end(self) -> float:
        return float(self.times[-1])

    def progress(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(segment j, fraction 0..1 of the way from waypoint j to j + 1) at times t."""
        j = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2)
        tau = (t - self.times[j]) / (self.times[j + 1] - self.times[j])
        return j, trapezoid(tau, self.ramp)

    def __call__(self, t: np.ndarray) -> np.ndarray:
        j, s = self.progress(t)
        return self.waypoints[j] + s[:, None] * (self.waypoints[j + 1] - self.waypoints[j])


def simulate_recording(result: SimulationResult, n_targets: int | None = None,
                       options: RecordingOptions = RecordingOptions(), seed: int = 0,
                       dwell: float = geometry.DWELL_S) -> Recording:
    """The recording behind the first `n_targets` rows of `result.table` (all by default)."""
    table = result.table if n_targets is None else result.table.subset(np.arange(min(n_targets, result.table.n)))
    if not 0.0 < options.stand < dwell:
        raise ValueError(f"stand {options.stand:g} s must be shorter than the dwell {dwell:g} s")
    rng = np.random.default_rng([seed, 15])
    exp = geometry.experiment(result.experiment)
    ids = np.array([int(i) for i in table.extras["id"]])
    p_ref, R_ref = exp.reference_poses()
    T_ref = geometry.homogeneous(R_ref[ids], p_ref[ids])
    q_stops = joint_targets(T_ref)
    centres = np.asarray(table.extras["t"], float)
    traj = _Trajectory(q_stops, centres, options.stand, dwell - options.stand, options.ramp)
    stands = np.stack([centres - options.stand / 2, centres + options.stand / 2], axis=1)

    t_joint = np.arange(0.0, traj.end, 1.0 / options.joint_hz)
    q_joint = traj(t_joint) + options.joint_noise * rng.standard_normal((len(t_joint), 6))

    # Tracker samples: their true (robot-clock) times, then the ones that survive.
    t_true = np.arange(rng.uniform(0, 1 / options.tracker_hz), traj.end, 1.0 / options.tracker_hz)
    keep = rng.random(len(t_true)) >= options.loss
    for start in _events(rng, options.gap_rate, traj.end):
        keep &= ~((t_true >= start) & (t_true < start + rng.uniform(*options.gap_length)))
    t_true = t_true[keep]
    p, R = _tracker_poses(result, table, traj, stands, t_true, options, rng)

    burst = np.zeros(len(t_true), dtype=bool)
    for start in _events(rng, options.burst_rate, traj.end):
        burst |= (t_true >= start) & (t_true < start + options.burst_length)
    p[burst] += options.burst_sigma * rng.standard_normal((int(burst.sum()), 3))

    station = np.linalg.inv(geometry.base_T_station()) @ geometry.homogeneous(R, p)
    t_stamp = t_true + options.clock_offset + options.stamp_jitter * rng.standard_normal(len(t_true))
    joints = JointStream(EPOCH_S + t_joint, q_joint, UR_JOINT_NAMES)
    tracker = PoseStream(EPOCH_S + t_stamp, station[:, :3, 3], matrix_to_quat(station[:, :3, :3]), frame="lighthouse")
    return Recording(joints, tracker, table, options.clock_offset, stands, options)


def _events(rng: np.random.Generator, rate: float, duration: float) -> np.ndarray:
    """Start times of a Poisson process of `rate` per s over [0, duration]."""
    return np.sort(rng.uniform(0.0, duration, rng.poisson(rate * duration))) if rate > 0 else np.zeros(0)


def _tracker_poses(result: SimulationResult, table: PoseTable, traj: _Trajectory, stands: np.ndarray,
                   t: np.ndarray, options: RecordingOptions, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Measured tracker poses (base frame) at robot-clock times t, before bursts (module docstring).

    The table's per-pose noise is a property of where the tracker stood; while it moves, that
    error blends from the last stop's to the next one's, so the error field stays continuous
    (a jump at every arrival would not be a real tracker's, and would bias the clock fit).
    """
    arm = UR_ARMS[DEFAULT_ARM]
    ref = reference_poses(arm, traj(t))
    systematic = {name: theta for name, theta in result.effects.items() if name != "noise"}
    p, R = (np.asarray(a, float) for a in apply_effects(ref[:, :3, 3], ref[:, :3, :3], systematic,
                                                         EffectContext.default(t=t)))
    # The per-stop error: the table's measured pose against the systematic effects alone.
    stop_ref = reference_poses(arm, traj.waypoints[1:-1:2])
    p_stop, R_stop = (np.asarray(a, float) for a in apply_effects(
        stop_ref[:, :3, 3], stop_ref[:, :3, :3], systematic, EffectContext.default(t=table.extras["t"])))
    zero = np.zeros((1, 3))
    dp = np.vstack([zero, table.meas_p - p_stop, zero])
    dr = np.vstack([zero, matrix_to_rotvec(quat_to_matrix(table.meas_q) @ np.swapaxes(R_stop, 1, 2)), zero])
    j, s = traj.progress(t)
    # Segment j runs from waypoint j to j + 1; waypoints are home, stop 0 twice, stop 1 twice, ..., home.
    before, after = (j + 1) // 2, (j + 2) // 2
    weight = s[:, None]
    p = p + (1 - weight) * dp[before] + weight * dp[after]
    R = rotvec_to_matrix((1 - weight) * dr[before] + weight * dr[after]) @ R

    # The ring after each arrival, along the last move's direction.
    k = np.searchsorted(stands[:, 0], t, side="right") - 1
    standing = (k >= 0) & (t <= stands[np.clip(k, 0, None), 1])
    since = t - stands[np.clip(k, 0, None), 0]
    approach = reference_poses(arm, traj(np.stack([stands[:, 0] - 0.05, stands[:, 0]], axis=1).reshape(-1)))
    moves = approach[1::2, :3, 3] - approach[0::2, :3, 3]
    directions = moves / np.maximum(np.linalg.norm(moves, axis=1, keepdims=True), 1e-12)
    ring = options.ring * np.exp(-since / options.ring_tau) * np.sin(2 * np.pi * options.ring_hz * since)
    p = p + np.where(standing, ring, 0.0)[:, None] * directions[np.clip(k, 0, None)]

    jitter = get_effect("noise")
    ctx = EffectContext.default(t=t, rng=rng)
    p, R = jitter.forward(p, R, np.array([options.jitter_p, options.jitter_r, 0.0]), ctx)
    return np.asarray(p, float), np.asarray(R, float)


def table_metrics(result: SimulationResult, n: int) -> tuple[dict, dict]:
    """(raw, noise floor) metrics of the first n rows of a simulated table (as `simulate` reports them)."""
    table = result.table.subset(np.arange(n))
    reference = table.reference
    raw = pose_metrics(reference, table.measured, table.has_orientation)
    floor = raw
    if "noise" in result.effects:
        R_ref = quat_to_matrix(reference[:, 3:7])
        p, R = get_effect("noise").forward(reference[:, :3], R_ref, result.effects["noise"],
                                           result.context.subset(np.arange(n)))
        floor = pose_metrics(reference, np.concatenate([np.asarray(p), matrix_to_quat(np.asarray(R))], axis=1),
                             table.has_orientation)
    return raw, floor


# Output formats of `posecorr simulate --recording`, by suffix ("" = a ROS 2 bag directory).
WRITERS: dict[str, Callable[[Path, JointStream, PoseStream, str], None]] = {
    ".bag": write_ros1_bag,
    ".mcap": write_mcap,
    ".csv": lambda path, joints, tracker, frame: write_csv_log(path, joints, tracker),
    "": write_ros2_bag,
}


def write_recording(recording: Recording, path: str | Path) -> Path:
    """Write in the format named by the suffix (WRITERS); an existing recording is replaced
    whole once the new one is complete (`safeio.replaced`)."""
    path = Path(path)
    writer = WRITERS.get(path.suffix.lower())
    if writer is None:
        raise IngestError(f"{path}: unknown recording format {path.suffix!r}; expected .bag (ROS 1), .mcap, .csv "
                          "or a directory name without suffix (ROS 2 bag)")
    from .safeio import replaced

    check_recording_output(path)
    with replaced(path) as fresh:
        if path.suffix:
            writer(fresh, recording.joints, recording.tracker, recording.tracker.frame)
        else:   # a ROS 2 bag names its database after its folder: written under the final name, moved up
            named = fresh / path.name
            fresh.mkdir()
            writer(named, recording.joints, recording.tracker, recording.tracker.frame)
            for part in named.iterdir():
                part.rename(fresh / part.name)
            named.rmdir()
    return path


def check_recording_output(path: str | Path) -> Path:
    """A recording path `write_recording` may replace: a new name, a file, or a ROS 2 bag
    folder (holding metadata.yaml); any other folder is refused."""
    from .safeio import check_folder_output, check_output

    path = Path(path)
    if path.suffix:
        return check_output(path)
    return check_folder_output(path, "metadata.yaml", "a ROS 2 bag")
