"""Orientation representations and conversions (paper section 2.1).

Representations (the registry `REPRESENTATIONS`), with their parameter counts:

| name   | size | meaning |
|--------|------|---------|
| `pos`  | 0    | position only (Experiment I): no orientation parameters, the orientation passes through |
| `eaa`  | 3    | rotation vector: axis times angle (rad), paper eq. 3 |
| `quat` | 4    | unit quaternion (w, x, y, z), scalar first, w >= 0 on encode |
| `R`    | 9    | rotation matrix, row-major |
| `zhou` | 6    | first two COLUMNS of R, (r11, r21, r31, r12, r22, r32), paper eq. 12 |

`encode(R, rep)` maps rotation matrices (..., 3, 3) to parameters (..., size);
`decode(params, rep)` maps ANY raw parameter vector (a network's output, say) to a proper
rotation: quat is normalised, R is projected through its quaternion, eaa uses Rodrigues
with a small-angle branch, zhou uses Gram-Schmidt (paper eqs. 13-18).

Every function works on numpy arrays, torch tensors (differentiable, batched) and the
symbolic tensors of the ONNX exporter: see `posecorr._xp`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from ._xp import namespace
from .registry import Registry

# Below this squared angle (rad^2) Rodrigues' coefficients use their Taylor series:
# sin(t)/t and (1 - cos t)/t^2 are 0/0 at t = 0 and must stay differentiable there.
_SMALL_ANGLE_SQ = 1e-12
# Floor under square roots of quantities that are >= 0 for valid input but may be
# slightly negative (rounding) or arbitrary (raw network output) elsewhere.
_TINY = 1e-12


def _flat9(R: Any) -> Any:
    return namespace(R).reshape(R, tuple(R.shape[:-2]) + (9,))


def _unflat9(m: Any) -> Any:
    return namespace(m).reshape(m, tuple(m.shape[:-1]) + (3, 3))


def _norm(v: Any) -> Any:
    xp = namespace(v)
    return xp.sqrt(xp.maximum(xp.sum(v * v, axis=-1, keepdims=True), _TINY * _TINY))


def normalize(v: Any) -> Any:
    """v / |v| along the last axis (a zero vector stays finite)."""
    return v / _norm(v)


def cross(a: Any, b: Any) -> Any:
    """Cross product along the last axis of (..., 3) arrays."""
    xp = namespace(a, b)
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return xp.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


# --- quaternion <-> matrix -------------------------------------------------------------

def quat_to_matrix(q: Any) -> Any:
    """(..., 4) quaternion (w, x, y, z), normalised first, -> (..., 3, 3) rotation matrix."""
    xp = namespace(q)
    q = normalize(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    m = xp.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=-1)
    return _unflat9(m)


def matrix_to_quat(R: Any) -> Any:
    """(..., 3, 3) matrix -> (..., 4) unit quaternion with w >= 0.

    Shepperd's method: of the four algebraically equivalent formulas, use the one whose
    pivot (4w^2, 4x^2, 4y^2 or 4z^2) is largest, so no division by a small number. For a
    matrix that is not orthogonal (a raw network output) the result is still a unit
    quaternion: it is normalised at the end.
    """
    xp = namespace(R)
    m = _flat9(R)
    r00, r01, r02 = m[..., 0], m[..., 1], m[..., 2]
    r10, r11, r12 = m[..., 3], m[..., 4], m[..., 5]
    r20, r21, r22 = m[..., 6], m[..., 7], m[..., 8]
    pivots = (1 + r00 + r11 + r22, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22)
    sx, sy, sz = r21 - r12, r02 - r20, r10 - r01          # 4 w (x, y, z)
    pxy, pxz, pyz = r01 + r10, r02 + r20, r12 + r21       # 4 (xy, xz, yz)
    candidates = (
        (pivots[0], sx, sy, sz),
        (sx, pivots[1], pxy, pxz),
        (sy, pxy, pivots[2], pyz),
        (sz, pxz, pyz, pivots[3]),
    )
    # Each candidate is 4 * pivot-component * q; dividing by its norm gives +-q.
    scaled = []
    for pivot, cand in zip(pivots, candidates):
        scale = 1.0 / (2.0 * xp.sqrt(xp.maximum(pivot, _TINY)))
        scaled.append([c * scale for c in cand])
    first_wins = pivots[0] >= pivots[1]
    third_wins = pivots[2] >= pivots[3]
    best01 = [xp.where(first_wins, a, b) for a, b in zip(scaled[0], scaled[1])]
    best23 = [xp.where(third_wins, a, b) for a, b in zip(scaled[2], scaled[3])]
    low_wins = xp.maximum(pivots[0], pivots[1]) >= xp.maximum(pivots[2], pivots[3])
    q = xp.stack([xp.where(low_wins, a, b) for a, b in zip(best01, best23)], axis=-1)
    return unit_quat(q)


def canonical_quat(q: Any) -> Any:
    """Flip the sign of q where w < 0 (q and -q are the same rotation)."""
    xp = namespace(q)
    negative = xp.reshape(q[..., 0] < 0, tuple(q.shape[:-1]) + (1,))
    return xp.where(negative, -q, q)


def unit_quat(q: Any) -> Any:
    """q made unit with w >= 0: the contract's form of a rotation, which a pose passed
    through must take too (a table's quaternions are unit within 1e-3 only)."""
    return canonical_quat(normalize(q))


# --- rotation vector <-> matrix --------------------------------------------------------

def rotvec_to_matrix(v: Any) -> Any:
    """(..., 3) rotation vector (rad) -> (..., 3, 3), Rodrigues' formula; Exp(v) in docs/design.md."""
    xp = namespace(v)
    t2 = xp.sum(v * v, axis=-1)
    small = t2 < _SMALL_ANGLE_SQ
    t = xp.sqrt(xp.where(small, 1.0, t2))        # safe: never sqrt(0) in the taken branch
    half = 0.5 * t
    a = xp.where(small, 1.0 - t2 / 6.0, xp.sin(t) / t)                         # sin t / t
    s = xp.sin(half) / half
    b = xp.where(small, 0.5 - t2 / 24.0, 0.5 * s * s)                          # (1 - cos t) / t^2
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    m = xp.stack([
        1 - b * (y * y + z * z), b * x * y - a * z, b * x * z + a * y,
        b * x * y + a * z, 1 - b * (x * x + z * z), b * y * z - a * x,
        b * x * z - a * y, b * y * z + a * x, 1 - b * (x * x + y * y),
    ], axis=-1)
    return _unflat9(m)


def quat_to_rotvec(q: Any) -> Any:
    """(..., 4) unit quaternion -> (..., 3) rotation vector with angle in [0, pi]."""
    xp = namespace(q)
    q = unit_quat(q)
    w = q[..., 0]
    v = q[..., 1:4]
    s2 = xp.sum(v * v, axis=-1)
    small = s2 < _SMALL_ANGLE_SQ
    s = xp.sqrt(xp.where(small, 1.0, s2))
    # angle / sin(angle / 2) = 2 atan2(s, w) / s; its series near s = 0, where w ~ 1.
    w_safe = xp.where(small, w, 1.0)
    factor = xp.where(small, 2.0 / w_safe * (1.0 - s2 / (3.0 * w_safe * w_safe)), 2.0 * xp.atan2(s, w) / s)
    return v * xp.reshape(factor, tuple(factor.shape) + (1,))


def matrix_to_rotvec(R: Any) -> Any:
    return quat_to_rotvec(matrix_to_quat(R))


# --- Zhou 6D <-> matrix ----------------------------------------------------------------

def matrix_to_zhou(R: Any) -> Any:
    """(..., 3, 3) -> (..., 6): the first two columns, column by column (paper eq. 12)."""
    xp = namespace(R)
    m = _flat9(R)
    return xp.stack([m[..., 0], m[..., 3], m[..., 6], m[..., 1], m[..., 4], m[..., 7]], axis=-1)


def zhou_to_matrix(z: Any) -> Any:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt (paper eqs. 13-18)."""
    xp = namespace(z)
    a1, a2 = z[..., 0:3], z[..., 3:6]
    b1 = normalize(a1)
    b2 = normalize(a2 - xp.sum(b1 * a2, axis=-1, keepdims=True) * b1)
    b3 = cross(b1, b2)
    m = xp.stack([b1[..., 0], b2[..., 0], b3[..., 0],
                  b1[..., 1], b2[..., 1], b3[..., 1],
                  b1[..., 2], b2[..., 2], b3[..., 2]], axis=-1)
    return _unflat9(m)


# --- generic encode / decode -----------------------------------------------------------

@dataclass(frozen=True)
class Representation:
    """How a corrector sees a pose's orientation: its parameter count, R -> params, and raw
    params -> a proper R. Size 0 is position only: no parameters, the orientation passes
    through. ``paper``: one of the paper's (section 2.1), the representations of its grids."""

    size: int
    encode: Callable[[Any], Any] | None = None
    decode: Callable[[Any], Any] | None = None
    paper: bool = False

    @property
    def orientation(self) -> bool:
        """Whether the orientation is corrected (and counts in the error): False for position only."""
        return self.size > 0


def _decode_R(params: Any) -> Any:
    # A raw 3x3 is orthonormalised through the nearest unit quaternion (Shepperd's method).
    return quat_to_matrix(matrix_to_quat(_unflat9(params)))


# The registry: adding a representation is one entry here and its two functions.
REPRESENTATIONS: Registry = Registry("representation")
# The position-only representation's name: what a table without orientation is fitted in.
POSITION_ONLY = "pos"


def register_representation(name: str, representation: Representation) -> None:
    """Add a representation: encode, decode, the correctors and the CLI's choices see it."""
    REPRESENTATIONS.add(name, representation)


def check_representation(rep: str) -> Representation:
    """The registered representation `rep`; ValueError naming the valid ones otherwise."""
    return REPRESENTATIONS.lookup(rep)


def orientations() -> tuple[str, ...]:
    """The registered representations of an orientation (every one but position only)."""
    return tuple(name for name, rep in REPRESENTATIONS.items() if rep.orientation)


register_representation(POSITION_ONLY, Representation(0, paper=True))
register_representation("eaa", Representation(3, matrix_to_rotvec, rotvec_to_matrix, paper=True))
register_representation("quat", Representation(4, matrix_to_quat, quat_to_matrix, paper=True))
register_representation("R", Representation(9, _flat9, _decode_R, paper=True))
register_representation("zhou", Representation(6, matrix_to_zhou, zhou_to_matrix, paper=True))


def _codec(rep: str) -> Representation:
    """The representation `rep` of an orientation; ValueError naming those otherwise."""
    codec = REPRESENTATIONS.get(rep)
    if codec is None or not codec.orientation:
        what = f"unknown representation {rep!r}" if codec is None else f"representation {rep!r} is position only"
        raise ValueError(f"{what}; expected one of {', '.join(orientations())}")
    return codec


def encode(R: Any, rep: str) -> Any:
    """Rotation matrices (..., 3, 3) -> parameters (..., size) of representation `rep`."""
    return _codec(rep).encode(R)


def decode(params: Any, rep: str) -> Any:
    """Any raw parameters (..., size) -> proper rotation matrices (..., 3, 3)."""
    return _codec(rep).decode(params)


# --- distances -------------------------------------------------------------------------

def geodesic_angle(R1: Any, R2: Any) -> Any:
    """Angle (rad, in [0, pi]) of R1 R2^T (paper eqs. 40-41), accurate near 0 and pi.

    atan2 of the skew and symmetric parts instead of arccos((tr - 1) / 2), which loses
    all digits of small angles.
    """
    xp = namespace(R1, R2)
    d = _flat9(xp.matmul(R1, xp.swap_last(R2)))
    cos = 0.5 * (d[..., 0] + d[..., 4] + d[..., 8] - 1.0)
    vx, vy, vz = d[..., 7] - d[..., 5], d[..., 2] - d[..., 6], d[..., 3] - d[..., 1]
    sin = 0.5 * xp.sqrt(vx * vx + vy * vy + vz * vz)
    return xp.atan2(sin, cos)
