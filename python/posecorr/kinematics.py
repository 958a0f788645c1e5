"""Forward and inverse kinematics of the reference robot (paper eqs. 19 and 21).

Universal Robots arms come from their published Denavit-Hartenberg parameters (standard DH:
T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)), in the frames the robot's controller reports:
`base` at the foot, the flange (tool0) at the end, the paper's UR5e by default. Any other
serial arm comes from its URDF, parsed by pytransform3d (a maintained transformation library
whose URDF parser needs nothing beyond numpy, scipy, matplotlib and lxml); the chain between
a base and a tip link is multiplied out here, vectorised over samples.

Every arm maps joint angles (N, n_joints) to flange poses (N, 4, 4); `reference_poses`
appends end_T_tracker (eq. 22 by default) to give base_T_tracker (eq. 19).
"""
from __future__ import annotations

import re

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .geometry import END_T_TRACKER
from .rotations import matrix_to_rotvec, rotvec_to_matrix

UR_JOINT_NAMES = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                  "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
_UR_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)


class KinematicsError(ValueError):
    """A robot model that cannot be built or a pose it cannot reach."""


class _SerialArm:
    """A serial chain: its pose is the product of one transform per link, base to tip."""

    joint_names: tuple[str, ...]

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def forward(self, q: np.ndarray) -> np.ndarray:
        """(N, 4, 4) base_T_tip for joint values (N, n_joints) in `joint_names` order (or one vector)."""
        q = _joint_array(q, self.n_joints)
        T = _identities(len(q))
        for link in self._links(q):
            T = T @ link
        return T

    def _links(self, q: np.ndarray) -> Iterator[np.ndarray]:
        """Each link's (N, 4, 4) or (4, 4) transform for joint values q (N, n_joints)."""
        raise NotImplementedError


def _identities(n: int) -> np.ndarray:
    return np.broadcast_to(np.eye(4), (n, 4, 4)).copy()


@dataclass(frozen=True)
class DHArm(_SerialArm):
    """A serial arm in standard DH parameters (metres, radians), one joint per (a, d, alpha)."""

    name: str
    a: tuple[float, ...]
    d: tuple[float, ...]
    alpha: tuple[float, ...]
    joint_names: tuple[str, ...] = UR_JOINT_NAMES

    def __post_init__(self) -> None:
        if not len(self.a) == len(self.d) == len(self.alpha) == len(self.joint_names):
            raise KinematicsError(f"{self.name}: a, d, alpha and joint_names differ in length")

    def _links(self, q: np.ndarray) -> Iterator[np.ndarray]:
        for i in range(self.n_joints):
            ct, st = np.cos(q[:, i]), np.sin(q[:, i])
            ca, sa = np.cos(self.alpha[i]), np.sin(self.alpha[i])
            A = np.zeros((len(q), 4, 4))
            A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 0, 3] = ct, -st * ca, st * sa, self.a[i] * ct
            A[:, 1, 0], A[:, 1, 1], A[:, 1, 2], A[:, 1, 3] = st, ct * ca, -ct * sa, self.a[i] * st
            A[:, 2, 1], A[:, 2, 2], A[:, 2, 3] = sa, ca, self.d[i]
            A[:, 3, 3] = 1.0
            yield A


def _ur(name: str, d1: float, a2: float, a3: float, d4: float, d5: float, d6: float) -> DHArm:
    return DHArm(name, a=(0.0, a2, a3, 0.0, 0.0, 0.0), d=(d1, 0.0, 0.0, d4, d5, d6), alpha=_UR_ALPHA)


# Universal Robots' published DH parameters ("DH parameters for calculations of kinematics
# and dynamics"), metres: d1, a2, a3, d4, d5, d6.
UR_ARMS: dict[str, DHArm] = {arm.name: arm for arm in (
    _ur("ur3", 0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819),
    _ur("ur5", 0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823),
    _ur("ur10", 0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922),
    _ur("ur3e", 0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
    _ur("ur5e", 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    _ur("ur10e", 0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
    _ur("ur16e", 0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
)}
DEFAULT_ARM = "ur5e"


@dataclass(frozen=True)
class _UrdfJoint:
    name: str
    kind: str                 # revolute, continuous, prismatic, fixed
    origin: np.ndarray        # (4, 4) parent_T_joint at zero
    axis: np.ndarray          # (3,) unit, joint frame


class UrdfArm(_SerialArm):
    """The serial chain from `base_link` to `tip_link` of a URDF; its moving joints in chain order."""

    def __init__(self, path: str | Path, base_link: str | None = None, tip_link: str | None = None) -> None:
        from pytransform3d.urdf import UrdfException, parse_urdf

        self.path = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise KinematicsError(f"{path}: cannot read URDF: {exc.strerror}") from None
        # A URDF needs no document type: one that declares entities could expand them
        # without bound ("billion laughs"), so it is refused before any parsing.
        if re.search(r"<!\s*(DOCTYPE|ENTITY)", text, re.IGNORECASE):
            raise KinematicsError(f"{path}: declares a DOCTYPE or ENTITY, which a URDF never needs; refused unparsed")
        try:
            self.name, links, joints = parse_urdf(text)
        except (UrdfException, ValueError, KeyError, SyntaxError, TypeError, AttributeError) as exc:
            raise KinematicsError(f"{path}: not a valid URDF: {exc}") from None
        by_child = {j.child: j for j in joints}
        parents = {j.parent for j in joints}
        link_names = [link.name for link in links]
        roots = [name for name in link_names if name not in by_child]
        base = base_link or (roots[0] if len(roots) == 1 else None)
        if base is None:
            raise KinematicsError(f"{path}: {len(roots)} root links ({', '.join(roots)}); name one with --base-link")
        if tip_link is None:
            leaves = [name for name in link_names if name not in parents]
            tip_link = "tool0" if "tool0" in link_names else (leaves[0] if len(leaves) == 1 else None)
            if tip_link is None:
                raise KinematicsError(f"{path}: several end links ({', '.join(leaves)}); name one with --tip-link")
        for label, link in (("base link", base), ("tip link", tip_link)):
            if link not in link_names:
                raise KinematicsError(f"{path}: no {label} {link!r} (links: {', '.join(link_names)})")
        chain = []
        link = tip_link
        while link != base:
            if link not in by_child:
                raise KinematicsError(f"{path}: tip link {tip_link!r} does not descend from base link {base!r}")
            j = by_child[link]
            axis = np.asarray(j.joint_axis, float)
            if j.joint_type != "fixed" and not np.linalg.norm(axis) > 1e-9:
                raise KinematicsError(f"{path}: joint {j.joint_name!r}: its axis {axis.tolist()} has no direction")
            chain.append(_UrdfJoint(j.joint_name, j.joint_type, np.asarray(j.child2parent, float),
                                    axis / max(np.linalg.norm(axis), 1e-300)))
            link = j.parent
        self.chain = tuple(reversed(chain))
        self.base_link, self.tip_link = base, tip_link
        self.joint_names = tuple(j.name for j in self.chain if j.kind != "fixed")
        if not self.joint_names:
            raise KinematicsError(f"{path}: the chain from {base!r} to {tip_link!r} has no moving joint (every "
                                  "joint is fixed): its tip cannot follow the recorded joint angles")
        bad = next((j.name for j in self.chain if not (np.isfinite(j.axis).all() and np.isfinite(j.origin).all())),
                   None)
        if bad is not None:
            raise KinematicsError(f"{path}: joint {bad!r}: its origin or axis is not a finite number")

    def _links(self, q: np.ndarray) -> Iterator[np.ndarray]:
        k = 0
        for joint in self.chain:
            yield joint.origin
            if joint.kind == "fixed":
                continue
            motion = _identities(len(q))
            if joint.kind == "prismatic":
                motion[:, :3, 3] = q[:, k, None] * joint.axis
            else:
                motion[:, :3, :3] = rotvec_to_matrix(q[:, k, None] * joint.axis)
            yield motion
            k += 1


Arm = DHArm | UrdfArm


def load_arm(spec: str | Path = DEFAULT_ARM, base_link: str | None = None, tip_link: str | None = None) -> Arm:
    """A UR model by name (ur3, ur5, ur10, ur3e, ur5e, ur10e, ur16e) or a URDF file."""
    key = str(spec).strip().lower()
    if key in UR_ARMS:
        return UR_ARMS[key]
    if key.endswith(".urdf") or Path(spec).is_file():
        return UrdfArm(spec, base_link, tip_link)
    raise KinematicsError(f"unknown robot {spec!r}; expected one of {', '.join(UR_ARMS)} or a .urdf file")


def _joint_array(q: np.ndarray, n: int) -> np.ndarray:
    q = np.atleast_2d(np.asarray(q, dtype=float))
    if q.shape[-1] != n:
        raise KinematicsError(f"{q.shape[-1]} joint values per sample, the arm has {n} joints")
    return q


def reference_poses(arm: Arm, q: np.ndarray, end_T_tracker: np.ndarray = END_T_TRACKER) -> np.ndarray:
    """(N, 4, 4) base_T_tracker = base_T_end(q) end_T_tracker (paper eq. 19)."""
    return arm.forward(q) @ end_T_tracker


def pose_error(T: np.ndarray, T_target: np.ndarray) -> np.ndarray:
    """(..., 6) position error (m) and rotation vector of R_target R^T (rad)."""
    dp = T_target[..., :3, 3] - T[..., :3, 3]
    dr = matrix_to_rotvec(T_target[..., :3, :3] @ np.swapaxes(T[..., :3, :3], -1, -2))
    return np.concatenate([dp, dr], axis=-1)


_MAX_STEP_RAD = 0.2


def inverse(arm: Arm, T_target: np.ndarray, q_seed: np.ndarray, tol: float = 1e-12,
            max_iter: int = 100) -> np.ndarray:
    """Joint angles reaching base_T_flange `T_target` (4, 4), by damped Newton steps from `q_seed`.

    A local solver: the branch (elbow up, wrist flip) is the seed's, which keeps a sequence of
    nearby targets on one posture, as the paper's cell does (section 2.2).
    """
    q = np.asarray(q_seed, dtype=float).copy()
    h = 1e-7
    for _ in range(max_iter):
        probes = np.vstack([q, q + h * np.eye(len(q))])
        T = arm.forward(probes)
        err = pose_error(T[0], T_target)
        if np.linalg.norm(err) < tol:
            return q
        J = pose_error(T[0], T[1:]).T / h   # column j: the pose change per unit of joint j
        step = np.linalg.solve(J.T @ J + 1e-9 * np.eye(len(q)), J.T @ err)
        # Short steps keep the solver on the seed's branch instead of jumping across a singularity.
        q = q + step * min(1.0, _MAX_STEP_RAD / max(np.abs(step).max(), 1e-300))
    if np.linalg.norm(pose_error(arm.forward(q)[0], T_target)) > 1e-9:
        raise KinematicsError(f"{getattr(arm, 'name', 'arm')}: target {T_target[:3, 3].round(4).tolist()} m "
                              "is out of reach from the seed posture")
    return q
