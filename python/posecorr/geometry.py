"""Frames and reference poses of the paper's experimental setup (section 2.2).

Frames (all in metres and radians):

- base: the UR5e base frame; z points up (gravity along -z).
- station: the Lighthouse base station, nominal pose `base_T_station` of eq. 23. A base
  point p has station coordinates s = R_S^T (p - t_S); the station looks along its -z axis.
- end: the robot flange; tracker: the VIVE tracker, `end_T_tracker` of eq. 22 (42 mm along the
  flange z axis, no rotation), so the tracker's z axis is the flange's z axis.

Reference poses are tracker poses in the base frame, base_T_ref = base_T_end(q) end_T_tracker
(eq. 19), where the flange pose is what the robot is commanded to (eq. 21).

"Upright" (our choice, the paper does not define it): the tracker's z axis (the normal of the
face opposite its mounting screw, i.e. the flange z axis) points up, base +z, and its x axis
points horizontally towards the base station, so the station sees the tracker's side at a
near-constant incidence. Orientation variations are applied in the tracker frame:
Experiment II rotates about the tracker z axis (= the vertical), Experiment III uses
R = R_upright Rz(yaw) Ry(pitch) Rx(roll) (intrinsic Z-Y-X, roll about the tracker x axis).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np

# Eq. 23 as printed: 4 decimals, so its rotation is orthonormal to ~1e-4 only.
PRINTED_BASE_T_STATION = np.array([
    [0.9981, 0.0125, 0.0601, 0.0764],
    [0.0599, 0.0160, -0.9981, -1.5668],
    [-0.0134, 0.9998, 0.0152, 0.6615],
    [0.0, 0.0, 0.0, 1.0],
])

# Eq. 22: the adapter puts the tracker 42 mm along the flange z axis.
END_T_TRACKER = np.array([
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.042],
    [0.0, 0.0, 0.0, 1.0],
])

WORKSPACE_CENTRE = np.array([0.0, -0.6, 0.5])  # m, base frame (section 2.2)
DWELL_S = 10.0  # s per pose: the paper holds each pose 10 s before recording

EXPERIMENT_NAMES = {1: "I", 2: "II", 3: "III"}


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to M in the Frobenius norm: U diag(1, 1, det(U V^T)) V^T from M's SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def station_pose() -> tuple[np.ndarray, np.ndarray]:
    """Nominal (R_S (3, 3), t_S (3,) m) of base_T_station, eq. 23 with R_S orthonormalised by SVD."""
    return nearest_rotation(PRINTED_BASE_T_STATION[:3, :3]), PRINTED_BASE_T_STATION[:3, 3].copy()


def base_T_station() -> np.ndarray:
    """4x4 homogeneous base_T_station (eq. 23, orthonormalised rotation)."""
    R, t = station_pose()
    return homogeneous(R, t)


def homogeneous(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(..., 4, 4) transforms from (..., 3, 3) rotations and (..., 3) translations."""
    R, t = np.asarray(R, float), np.asarray(t, float)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


# Named transforms of --tool (end_T_tracker) and --registration (base_T_<tracker frame>), the
# options of `ingest` and, for the registration, of the `ros2` node.
NAMED_TRANSFORMS = {
    "tool": {"paper": END_T_TRACKER.copy, "none": lambda: np.eye(4)},
    "registration": {"paper": base_T_station, "none": lambda: np.eye(4)},
    "station_pose": {},   # its "paper" is parse_station_pose's: a reference-frame pose, never "tracker:paper"
}


def parse_transform(text: str, kind: str, error: type[Exception] = ValueError) -> np.ndarray:
    """A 4x4 transform from a name in NAMED_TRANSFORMS[kind] or 'x,y,z[,qw,qx,qy,qz]' (m, unit
    quaternion); `error` (the caller's kind of refusal) naming the option otherwise."""
    from .rotations import quat_to_matrix

    named = NAMED_TRANSFORMS[kind]
    if text.strip().lower() in named:
        return named[text.strip().lower()]()
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (3, 7) or not np.all(np.isfinite(values)):
        raise error(f"--{kind} {text!r}: expected {', '.join(named)} or x,y,z[,qw,qx,qy,qz]")
    quat = np.array(values[3:] or [1.0, 0.0, 0.0, 0.0])
    if abs(np.linalg.norm(quat) - 1.0) > 1e-3:
        raise error(f"--{kind} {text!r}: quaternion norm {np.linalg.norm(quat):.6g}, expected 1")
    return homogeneous(quat_to_matrix(quat), np.array(values[:3]))


# Where a session's base station stood (`--station-pose`): its pose in the reference frame, or
# with this prefix in the tracker's own frame (where SteamVR reports its base stations).
TRACKER_FRAME_PREFIX = "tracker:"


@dataclass(frozen=True)
class StationPose:
    """Where the base station stood, as stated: `text` as written (None: the paper's station,
    eq. 23), and its rotation and origin in the frame it names (the reference frame, or the
    tracker's own with `in_tracker_frame`). The station looks along its own -z axis."""

    text: str | None
    R: np.ndarray
    t: np.ndarray
    in_tracker_frame: bool = False

    def in_reference(self, tracker_to_reference: tuple[np.ndarray, np.ndarray] | None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """(R_S, t_S) in the reference frame. A pose stated in the tracker's frame is carried
        there by `tracker_to_reference`, (R, t) with p_ref = R p_tracker + t: a rigid fit of
        the session. Its error (millimetres of a metres-wide sweep) moves the station by as
        much, far below what the station's effects can tell."""
        if not self.in_tracker_frame:
            return self.R, self.t
        if tracker_to_reference is None:
            raise ValueError(f"--station-pose {self.text!r} is in the tracker's frame: it needs the session's "
                             "poses to place it in the reference frame")
        R, t = tracker_to_reference
        return R @ self.R, R @ self.t + t

    def words(self) -> str:
        """The pose in a sentence: the frame and the origin."""
        frame = "the tracker's frame" if self.in_tracker_frame else "the reference frame"
        where = ", ".join(f"{x:.2f}" for x in self.t)
        return f"({where}) m in {frame}"


def parse_station_pose(text: str | None, error: type[Exception] = ValueError) -> StationPose:
    """`--station-pose`: None or "paper" (eq. 23), 'x,y,z[,qw,qx,qy,qz]' in the reference
    frame, or the same after "tracker:" in the tracker's own frame; `error` the caller's kind
    of refusal."""
    if text is None or text.strip().lower() == "paper":
        R, t = station_pose()
        return StationPose(None, R, t)
    body = text.strip()
    in_tracker = body.lower().startswith(TRACKER_FRAME_PREFIX)
    if in_tracker:
        body = body[len(TRACKER_FRAME_PREFIX):]
    try:
        T = parse_transform(body, "station_pose", error)
    except error as exc:
        raise error(f"--station-pose {text!r}: expected paper, x,y,z[,qw,qx,qy,qz] (m, reference frame) or "
                    f"{TRACKER_FRAME_PREFIX}x,y,z[,qw,qx,qy,qz] (the tracker's own frame)"
                    + (f"; {str(exc).split(': ', 1)[1]}" if "norm" in str(exc) else "")) from None
    return StationPose(text.strip(), T[:3, :3], T[:3, 3], in_tracker)


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def upright_rotation() -> np.ndarray:
    """Tracker orientation 'upright': z = base up, x = horizontal direction from the cube centre to the station."""
    _, t_S = station_pose()
    to_station = t_S - WORKSPACE_CENTRE
    x = np.array([to_station[0], to_station[1], 0.0])
    x /= np.linalg.norm(x)
    z = np.array([0.0, 0.0, 1.0])
    return np.stack([x, np.cross(z, x), z], axis=1)


def lattice(side: float, n: int, centre: np.ndarray = WORKSPACE_CENTRE) -> np.ndarray:
    """(n^3, 3) points of an n x n x n lattice filling a cube of `side` m, x slowest, z fastest."""
    axis = np.linspace(-side / 2.0, side / 2.0, n)
    return np.array(list(product(axis, axis, axis))) + centre


@dataclass(frozen=True)
class Experiment:
    """One of the paper's three experiments: a lattice of positions times a set of orientations."""

    number: int
    side: float                  # m, cube side
    n_per_axis: int
    orientations: np.ndarray     # (K, 3, 3) tracker orientations (base frame)
    position_only: bool

    @property
    def name(self) -> str:
        return EXPERIMENT_NAMES[self.number]

    @property
    def n_poses(self) -> int:
        return self.n_per_axis ** 3 * len(self.orientations)

    def tracker_targets(self) -> tuple[np.ndarray, np.ndarray]:
        """Commanded tracker poses (p (N, 3), R (N, 3, 3)); positions slowest, orientations fastest."""
        points = lattice(self.side, self.n_per_axis)
        k = len(self.orientations)
        p = np.repeat(points, k, axis=0)
        R = np.tile(self.orientations, (len(points), 1, 1))
        return p, R

    def flange_poses(self) -> np.ndarray:
        """(N, 4, 4) base_T_end the robot is commanded to: target * end_T_tracker^-1 (eq. 21)."""
        p, R = self.tracker_targets()
        return homogeneous(R, p) @ np.linalg.inv(END_T_TRACKER)

    def reference_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Reference tracker poses (p (N, 3) m, R (N, 3, 3)) = flange pose * end_T_tracker (eq. 19)."""
        T = self.flange_poses() @ END_T_TRACKER
        return T[:, :3, 3].copy(), T[:, :3, :3].copy()


def experiment(number: int | str) -> Experiment:
    """Experiment I, II or III of the paper (1/2/3 or 'I'/'II'/'III')."""
    key = {"1": 1, "2": 2, "3": 3, "I": 1, "II": 2, "III": 3}.get(str(number).strip().upper())
    if key is None:
        raise ValueError(f"unknown experiment {number!r}; expected 1, 2 or 3 (I, II, III)")
    R0 = upright_rotation()
    if key == 1:
        return Experiment(1, 0.4, 11, R0[None], position_only=True)
    if key == 2:
        # The paper's 13 values of linspace(0, 2 pi, 13): 0 and 2 pi are the same pose, kept twice.
        yaws = np.linspace(0.0, 2.0 * np.pi, 13)
        return Experiment(2, 0.4, 5, np.stack([R0 @ rot_z(a) for a in yaws]), position_only=False)
    angles = np.deg2rad([-30.0, 0.0, 30.0])
    rpy = [R0 @ rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
           for roll, pitch, yaw in product(angles, angles, angles)]
    return Experiment(3, 0.2, 5, np.stack(rpy), position_only=False)
