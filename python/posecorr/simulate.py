"""Simulated paired-pose tables of the paper's three experiments (section 2.2).

Reference poses come from `geometry` (lattice x orientations, eq. 19); the measured poses are
the reference poses with the catalogue's effects applied in order (`effects.apply_effects`).
Poses are measured in a random order (seeded), one every `dwell` seconds, so `drift` acts
along the session time `t`, which the table carries.

Effect mix rule: `base="default"` starts from the experiment's DEFAULT_MIX; every effect named
in `effects` replaces that effect's whole parameter vector (or adds it), `NAME=off` (None)
removes it; effects from `effect_files` join at their default magnitude unless named.
`base="none"` starts from nothing: only the named effects (and the file effects) act, so no
noise unless `noise` is named.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Iterable, Mapping

import numpy as np

from . import geometry
from .data import PoseTable
from .effects import (EffectContext, Noise, apply_effects, checked_theta, get_effect, load_effect_file,
                      parse_effects_arg, sorted_effects)
from .kinematics import UR_ARMS
from .metrics import pose_metrics
from .rotations import matrix_to_quat

# The default mix per experiment (theta in each effect's parameter order; SI units), tuned
# so that the raw errors match the raw rows of the paper's tables 2-4 within a few percent.
# Story, common to all three: one Lighthouse station (its sweep calibration, range scale and
# incidence bias are properties of the hardware, identical in every session), one tracker on
# a 3D-printed adapter, and a station registration from a single measurement (eq. 23) per
# session. That registration dominates Experiments I and III: the SteamVR universe it was
# taken in is offset by centimetres (I: 4.2 cm, III: 1.9 cm) and a few mrad from the one the
# experiment ran in (re-initialisation after a line-of-sight loss; the universe's heading is
# the least constrained, hence III's 15 mrad about the vertical). Experiment II was registered
# well (3 mm), so there the hardware effects and the adapter show. Each experiment remounted
# the tracker on its 1/4" screw, so the adapter error differs per session; its clocking about
# the screw axis (d_z, tracker z = vertical when upright) is the largest rotation: Experiment
# II's yaw-only poses cannot tell it from a constant, III's roll/pitch poses expose it (2.1 deg
# there, the only way to reach the paper's 0.0508 rad). Drift: 1-2 mm with a 1.5 h time constant.
_HARDWARE = {
    "sweep": [1.5e-3, -1.0e-3, 0.03, -0.02],   # phase_x, phase_y (rad), curve_x, curve_y (1/rad)
    "range_scale": [0.005],                    # 0.5 %
    "incidence": [1.5e-3, 1.0e-3],             # b1, b2 (m)
    "noise": [3e-4, 5e-4, 2e-4],               # docs/design.md default: sigma_p, sigma_r, k2
}
DEFAULT_MIX: dict[int, dict[str, list[float]]] = {
    1: {
        "mount": [3e-3, -2e-3, 8e-3, 2.0e-3, -1.5e-3, 3.0e-3],
        **_HARDWARE,
        "drift": [1.0e-3, -0.8e-3, 1.5e-3, 5400.0],
        "station": [2.0e-3, -1.5e-3, 3.0e-3, -0.0295, 0.0243, 0.0165],
    },
    2: {
        "mount": [5e-3, -4e-3, 7.3e-3, 2.0e-3, -1.5e-3, 2.5e-3],
        **_HARDWARE,
        "drift": [0.8e-3, -0.6e-3, 1.0e-3, 5400.0],
        "station": [2.5e-3, 1.5e-3, 2.0e-3, -1.5e-3, -1.9e-3, 1.1e-3],
    },
    3: {
        "mount": [6e-3, -5e-3, 36.8e-3, 3.0e-3, -2.0e-3, 4.0e-3],
        **_HARDWARE,
        "drift": [1.0e-3, -0.8e-3, 1.5e-3, 5400.0],
        "station": [4.0e-3, -3.0e-3, 15e-3, -0.013, 0.011, 0.0087],
    },
}


@dataclass
class SimulationResult:
    """A simulated experiment.

    table: the paired-pose table, rows in measurement order, with `t` (s) and `id` (lattice index).
    raw: pose_metrics(reference, measured). noise_floor: pose_metrics of the reference against the
    reference perturbed by the noise effect alone with the same draws (what a perfect correction
    leaves). effects: {name: theta} actually applied, in application order.
    """

    table: PoseTable
    raw: dict[str, float | None]
    noise_floor: dict[str, float | None]
    effects: dict[str, np.ndarray]
    experiment: int
    seed: int
    context: EffectContext = field(repr=False)
    spec: "SessionSpec | None" = None      # realistic sessions only (experiment 0)

    def effects_json(self) -> dict[str, dict[str, list[float]]]:
        """{effect: {param: values}}, JSON-ready."""
        return {name: get_effect(name).describe(theta) for name, theta in self.effects.items()}

    def station_in_tracker_frame(self) -> str:
        """Where the base station stands in the measurements' own frame, as `--station-pose`
        takes it ("tracker:x,y,z,qw,qx,qy,qz"): what SteamVR would report of it. The frame is
        the reference's moved by the `station` effect, the registration error."""
        R_S, t_S = self.context.R_S, self.context.t_S
        p, R = (t_S[None], R_S[None]) if "station" not in self.effects else \
            get_effect("station").forward(t_S[None], R_S[None], self.effects["station"], self.context)
        values = np.concatenate([np.asarray(p)[0], matrix_to_quat(np.asarray(R))[0]])
        return geometry.TRACKER_FRAME_PREFIX + ",".join(f"{v:.6f}" for v in values)


def simulated_station(station_pose: str | None) -> geometry.StationPose:
    """The station a simulation places (`geometry.parse_station_pose`): in the reference frame
    only, for the tracker's frame is what the simulation makes (`station_in_tracker_frame`)."""
    stated = geometry.parse_station_pose(station_pose)
    if stated.in_tracker_frame:
        raise ValueError(f"--station-pose {station_pose}: simulate places the station in the reference frame "
                         "(x,y,z[,qw,qx,qy,qz]); the tracker's frame is what it makes, and it prints where the station "
                         "stands there")
    return stated


def _placed(ctx: EffectContext, station_pose: str | None, **changes: Any) -> EffectContext:
    """`ctx` with the base station where `station_pose` puts it (`simulated_station`), and `changes`."""
    stated = simulated_station(station_pose)
    return replace(ctx, R_S=stated.R, t_S=stated.t, **changes)


def resolve_mix(experiment: int | str, effects: str | Mapping[str, Any] | None = None,
                base: str = "default", file_effects: Iterable[str] = ()) -> dict[str, np.ndarray]:
    """The {name: theta} to simulate, by the module's mix rule, in application order."""
    if base not in ("default", "none"):
        raise ValueError(f"base must be 'default' or 'none', got {base!r}")
    number = geometry.experiment(experiment).number
    mix: dict[str, Any] = dict(DEFAULT_MIX[number]) if base == "default" else {}
    for name in file_effects:
        mix.setdefault(name, get_effect(name).default_theta())
    overrides = parse_effects_arg(effects) if isinstance(effects, str) else dict(effects or {})
    for name, theta in overrides.items():
        get_effect(name)  # an unknown name fails here, one given to remove too
        if theta is None:
            mix.pop(name, None)
        else:
            mix[name] = theta
    return {e.name: checked_theta(e, mix[e.name]) for e in sorted_effects(mix)}


def simulate(experiment: int | str, effects: str | Mapping[str, Any] | None = None, seed: int = 0,
             effect_files: Iterable[str] = (), order: str = "random", base: str = "default",
             dwell: float = geometry.DWELL_S, station_pose: str | None = None) -> SimulationResult:
    """Simulate Experiment 1/2/3 (I/II/III): reference lattice -> effects -> paired table.

    effects: None, a CLI string 'NAME=V1,...;NAME' or {name: theta or None}; see the module
    docstring for how it combines with `base` and `effect_files`. order: "random" (seeded
    measurement order) or "lattice". dwell: seconds per pose (t of pose k is (k + 1) dwell).
    station_pose: where the base station stands, in the reference frame
    (`geometry.parse_station_pose`; None: the paper's).
    """
    file_effects: list[str] = []
    for path in effect_files:
        file_effects += load_effect_file(path)
    exp = geometry.experiment(experiment)
    mix = resolve_mix(exp.number, effects, base, file_effects)
    if order not in ("random", "lattice"):
        raise ValueError(f"order must be 'random' or 'lattice', got {order!r}")

    rng = np.random.default_rng(seed)
    p_ref, R_ref = exp.reference_poses()
    n = len(p_ref)
    index = rng.permutation(n) if order == "random" else np.arange(n)
    p_ref, R_ref = p_ref[index], R_ref[index]
    t = (np.arange(n) + 1.0) * dwell
    ctx = _placed(EffectContext.default(t=t, noise_draws=Noise.draw(rng, n)), station_pose)

    p_meas, R_meas = apply_effects(p_ref, R_ref, mix, ctx)
    if "noise" in mix:
        p_floor, R_floor = get_effect("noise").forward(p_ref, R_ref, mix["noise"], ctx)
    else:
        p_floor, R_floor = p_ref, R_ref

    q_ref, q_meas = matrix_to_quat(R_ref), matrix_to_quat(R_meas)
    table = PoseTable(meas_p=np.asarray(p_meas), meas_q=np.asarray(q_meas), ref_p=p_ref,
                      ref_q=None if exp.position_only else q_ref,
                      extras={"id": np.array([str(i) for i in index], dtype=object), "t": t})
    with_rotation = not exp.position_only
    reference = np.concatenate([p_ref, q_ref], axis=1)
    raw = pose_metrics(reference, table.measured, with_rotation)
    floor = pose_metrics(reference, np.concatenate([p_floor, matrix_to_quat(R_floor)], axis=1), with_rotation)
    return SimulationResult(table, raw, floor, mix, exp.number, seed, ctx)


# --- realistic sessions (docs/design.md, "Real sessions") ---------------------------------

SPREADS = ("none", "yaw", "full")


@dataclass(frozen=True)
class SessionSpec:
    """What a real robot-cell session looks like; `draw_session_spec` draws one.

    n: poses (6-40). spread: orientations "none" (all alike), "yaw" (about the vertical) or
    "full" (about every axis, up to `max_angle` rad). planar: the positions lie in a plane (a
    tracker set down on a table). position_only: the reference has no orientation.
    unremovable: RMS (m) of a per-pose error no model removes (0: none; bad real sessions
    show 60-110 mm). The tracker reports in its own frame (any rotation, `offset` m away), from a
    lever arm of `lever` m on a mount turned by any rotation. robot: a robot arm of
    `kinematics.UR_ARMS` (a drawn one: "ur5e", or the KUKA-sized "ur10e") carries the tracker
    on its flange through random joint angles (30-60 poses, full orientation): the reference
    is the flange pose, the mount the unknown flange-to-tracker offset of a hand-eye
    calibration; "" for a tracker set down by hand. duration: the session's length in s, pose k measured at
    (k + 1) duration / n, as the table's time column t; 0 for a table without times (as the
    real sessions come), where a time-dependent effect is the identity.
    """

    n: int
    spread: str
    planar: bool
    position_only: bool
    unremovable: float
    offset: float
    lever: float
    box: float
    max_angle: float
    robot: str = ""
    duration: float = 0.0


# The arms a session draws; any arm of `kinematics.UR_ARMS` may be asked for.
DRAWN_ROBOTS = ("ur5e", "ur10e")


def draw_session_spec(rng: np.random.Generator, n: int | None = None, spread: str | None = None,
                      position_only: bool | None = None, unremovable: float | None = None,
                      robot: str | None = None, duration: float = 0.0) -> SessionSpec:
    """A random session of the kinds real cells produce; the arguments pin what they name.
    The duration is never drawn (a drawn session has no clock, as the real ones)."""
    pinned_spread = spread
    spread = spread if spread is not None else str(rng.choice(SPREADS))
    if spread not in SPREADS:
        raise ValueError(f"spread must be one of {', '.join(SPREADS)}, got {spread!r}")
    if n is not None and n < 6:
        raise ValueError(f"a session needs at least 6 poses, got {n}")
    if not duration >= 0.0:
        raise ValueError(f"a session's duration is 0 (no times) or more seconds, got {duration!r}")
    drawn = SessionSpec(
        n=int(rng.integers(6, 41)), spread=spread, planar=bool(rng.random() < 0.3),
        position_only=bool(rng.random() < 0.25),
        unremovable=float(rng.uniform(0.06, 0.11)) if rng.random() < 0.15 else 0.0,
        offset=float(rng.uniform(1.0, 4.0)), lever=float(rng.uniform(0.02, 0.08)),
        box=float(rng.uniform(0.3, 1.5)), max_angle=float(np.deg2rad(rng.uniform(10.0, 60.0))))
    carried = str(rng.choice(DRAWN_ROBOTS)) if rng.random() < 0.15 else ""
    # A robot turns the tracker every way: a narrower spread asked for is a tracker set down by
    # hand (drawn the same, so that every other session of a seed stays as it was).
    robot = (carried if pinned_spread in (None, "full") else "") if robot is None else robot
    if robot:
        if robot not in UR_ARMS:
            raise ValueError(f"robot must be one of {', '.join(UR_ARMS)}, got {robot!r}")
        if pinned_spread not in (None, "full"):
            raise ValueError(f"a robot turns the tracker every way: spread {pinned_spread!r} goes with a tracker set "
                             "down by hand, not with a robot (spread 'full', or no robot)")
        # A robot carries the tracker through 30-60 poses of every orientation, on a flange
        # adapter 5-15 cm long; the reference is exact, no per-pose error beyond the tracker's.
        drawn = replace(drawn, n=int(rng.integers(30, 61)), spread="full", position_only=False,
                        unremovable=0.0, lever=float(rng.uniform(0.05, 0.15)), robot=robot)
    return replace(drawn, n=drawn.n if n is None else int(n),
                   position_only=drawn.position_only if position_only is None else bool(position_only),
                   unremovable=drawn.unremovable if unremovable is None else float(unremovable),
                   duration=float(duration))


def _random_rotvec(rng: np.random.Generator, size: int | None = None) -> np.ndarray:
    """Rotation vectors of rotations uniform on SO(3) (from uniform unit quaternions)."""
    from .rotations import quat_to_rotvec

    q = rng.normal(size=(1 if size is None else size, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w = quat_to_rotvec(q)
    return w[0] if size is None else w


def robot_flange_poses(robot: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) flange poses of a UR arm at random joint angles: shoulder and elbow in a
    working posture, the wrist anywhere; poses whose flange is below 10 cm above the base
    or nearer than 20 cm to its axis (the arm folded on itself) are drawn again."""
    arm, poses = UR_ARMS[robot], []
    while sum(len(p) for p in poses) < n:
        q = np.column_stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-2.2, -0.6, n), rng.uniform(0.5, 2.3, n),
                             rng.uniform(-np.pi, np.pi, (n, 3))])
        T = arm.forward(q)
        ok = (T[:, 2, 3] > 0.1) & (np.linalg.norm(T[:, :2, 3], axis=1) > 0.2)
        poses.append(T[ok])
    return np.concatenate(poses)[:n]


def simulate_session(seed: int = 0, spec: SessionSpec | None = None, extra: Mapping[str, Any] | None = None,
                     station_pose: str | None = None, **pin: Any) -> SimulationResult:
    """A realistic session (see `SessionSpec`): few poses, an unregistered tracker frame, a
    lever arm, the given orientation spread, noise at the DESIGN defaults, and optionally an
    error no model removes. `pin` fixes fields of the drawn spec (n, spread, position_only,
    unremovable, duration). `extra` {effect: theta} adds effects where the tracker is, in the cell (a
    user's effect or a form, say), applied with the mount in catalogue order. The reference frame is the robot base; the workspace centre of the effects
    is the mean reference position, as a fit takes it. `station_pose`: where the base station
    stands, as `simulate`'s."""
    from .rotations import rotvec_to_matrix

    rng = np.random.default_rng([int(seed), 20261122])
    spec = spec or draw_session_spec(rng, **pin)
    centre = geometry.WORKSPACE_CENTRE + rng.uniform(-0.3, 0.3, 3)
    p_ref = centre + rng.uniform(-0.5, 0.5, (spec.n, 3)) * spec.box
    if spec.planar:
        p_ref[:, 2] = centre[2]
    base = rotvec_to_matrix(_random_rotvec(rng))
    if spec.robot:
        flange = robot_flange_poses(spec.robot, spec.n, rng)
        p_ref, R_ref = flange[:, :3, 3], flange[:, :3, :3]
    else:
        if spec.spread == "none":
            turns = np.zeros((spec.n, 3))
        elif spec.spread == "yaw":
            turns = np.zeros((spec.n, 3))
            turns[:, 2] = rng.uniform(-spec.max_angle, spec.max_angle, spec.n)
        else:
            axis = rng.normal(size=(spec.n, 3))
            turns = axis / np.linalg.norm(axis, axis=1, keepdims=True) * rng.uniform(0, spec.max_angle, (spec.n, 1))
        R_ref = rotvec_to_matrix(turns) @ base
    direction = rng.normal(size=3)
    lever = rng.normal(size=3)
    mix = {"mount": np.concatenate([_random_rotvec(rng), spec.lever * lever / np.linalg.norm(lever)]),
           "station": np.concatenate([_random_rotvec(rng), spec.offset * direction / np.linalg.norm(direction)]),
           "noise": get_effect("noise").default_theta()}
    t = (np.arange(spec.n) + 1.0) * spec.duration / spec.n if spec.duration else None
    ctx = _placed(EffectContext.default(t=t, noise_draws=Noise.draw(rng, spec.n)), station_pose, c=p_ref.mean(axis=0))
    # The noise acts where the tracker is, in the cell, before the unknown frame turns it into
    # the tracker's own coordinates (its range term would otherwise see the frame's offset).
    mix.update({name: np.asarray(theta, float) for name, theta in (extra or {}).items()})
    cell = {name: theta for name, theta in mix.items() if name != "station"}
    p_meas, R_meas = apply_effects(p_ref, R_ref, cell, ctx)
    p_meas, R_meas = apply_effects(p_meas, R_meas, {"station": mix["station"]}, ctx)
    p_floor, R_floor = get_effect("noise").forward(p_ref, R_ref, mix["noise"], ctx)
    if spec.unremovable:
        # Per-pose errors the tracker makes and no smooth model follows (reflections, a
        # station seen at grazing angles): in the measurement and in what a perfect fit leaves.
        bad = rng.normal(scale=spec.unremovable / np.sqrt(3.0), size=(spec.n, 3))
        p_meas, p_floor = p_meas + bad, p_floor + bad
    q_ref = matrix_to_quat(R_ref)
    table = PoseTable(meas_p=np.asarray(p_meas), meas_q=np.asarray(matrix_to_quat(R_meas)), ref_p=p_ref,
                      ref_q=None if spec.position_only else q_ref,
                      extras={"id": np.array([str(i) for i in range(spec.n)], dtype=object),
                              **({} if t is None else {"t": t})})
    with_rotation = not spec.position_only
    reference = np.concatenate([p_ref, q_ref], axis=1)
    raw = pose_metrics(reference, table.measured, with_rotation)
    floor = pose_metrics(reference, np.concatenate([p_floor, matrix_to_quat(R_floor)], axis=1), with_rotation)
    return SimulationResult(table, raw, floor, mix, 0, seed, ctx, spec)
