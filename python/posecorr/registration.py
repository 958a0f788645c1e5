"""Closed-form frame registration: the initial guesses for the `station` and `mount` effects.

Model (docs/design.md, effects `mount` then `station`): a measured pose is the reference pose
seen through an unknown world transform W (base frame -> tracker's reporting frame) and an
unknown mount error X (true tracker frame -> nominal one):

    M_i = W  T_i  X          (4x4 homogeneous; T_i reference, M_i measured)

which is the robot-world-hand-eye problem A_i X = Y B_i with A_i = T_i, B_i = M_i and
Y = W^-1. Both solvers below work for ANY rotation between the frames (data recorded in
the tracker's own frame), which is what makes them good starting points for the joint
nonlinear least-squares refinement. The same relation read on the orientations alone
(`turn_mismatch`) tells a table whose two quaternion series are written in two component
orders (`quaternion_order_note`).
"""
from __future__ import annotations

import numpy as np

from .geometry import homogeneous, nearest_rotation

__all__ = ["umeyama", "rotation_of_covariance", "robot_world_hand_eye"]


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """R, t, s minimising sum |target - (s R source + t)|^2 over (N, 3) point sets.

    Kabsch when `with_scale` is False (s = 1). Umeyama (1991), with the reflection fix.
    """
    source, target = np.asarray(source, float), np.asarray(target, float)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(f"expected two (N, 3) point sets, got {source.shape} and {target.shape}")
    if len(source) < 3:
        raise ValueError(f"a rigid registration needs at least 3 points, got {len(source)}")
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    xs, xt = source - mu_s, target - mu_t
    R, aligned = rotation_of_covariance(xt.T @ xs / len(source))
    s = float(aligned / np.mean(np.sum(xs * xs, axis=1))) if with_scale else 1.0
    t = mu_t - s * R @ mu_s
    return R, t, s


def rotation_of_covariance(cov: np.ndarray) -> tuple[np.ndarray, float]:
    """(R, trace(R^T cov)): the rotation maximising trace(R^T cov) for the (3, 3) covariance
    cov = mean(target_c source_c^T) of centred point sets (Kabsch, with the reflection fix),
    and that maximum, which is all a streamed fit needs (`controller.apply`'s Kabsch fit keeps
    the sums, not the points)."""
    U, sigma, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    return U @ np.diag([1.0, 1.0, d]) @ Vt, float(sigma[0] + sigma[1] + d * sigma[2])


def robot_world_hand_eye(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """X, Y (4x4) solving A_i X = Y B_i in the least-squares sense, A and B (N, 4, 4).

    Rotations first, linearly: vec(R_Ai R_X) = vec(R_Y R_Bi) is a homogeneous linear
    system in the 18 entries of R_X and R_Y (Kronecker form); its null vector is found by
    SVD and each half is projected onto SO(3). Translations then solve the linear system
    R_Ai t_X - t_Y = R_Y t_Bi - t_Ai. Needs at least 3 poses with rotations about
    non-parallel axes for R_X to be determined.
    """
    A, B = np.asarray(A, float), np.asarray(B, float)
    if A.shape != B.shape or A.shape[1:] != (4, 4):
        raise ValueError(f"expected two (N, 4, 4) stacks, got {A.shape} and {B.shape}")
    n = len(A)
    if n < 3:
        raise ValueError(f"robot-world-hand-eye calibration needs at least 3 poses, got {n}")
    RA, tA, RB, tB = A[:, :3, :3], A[:, :3, 3], B[:, :3, :3], B[:, :3, 3]
    eye = np.eye(3)
    # Column-major vec: vec(P Q) = (I kron P) vec(Q) = (Q^T kron I) vec(P). The null vector
    # of the stacked 9N x 18 system is the smallest eigenvector of its 18 x 18 normal matrix.
    left = np.einsum("ij,nkl->nikjl", eye, RA).reshape(n, 9, 9)                       # I kron R_Ai
    right = np.einsum("nji,kl->nikjl", RB, eye).reshape(n, 9, 9)                      # R_Bi^T kron I
    K = np.concatenate([left, -right], axis=2)
    normal = np.einsum("nki,nkj->ij", K, K)
    _, vectors = np.linalg.eigh(normal)
    v = vectors[:, 0]
    RX_raw = v[:9].reshape(3, 3, order="F")
    RY_raw = v[9:].reshape(3, 3, order="F")
    # The null vector's scale and sign are free: make R_X's determinant positive.
    scale = np.cbrt(np.linalg.det(RX_raw))
    RX = nearest_rotation(RX_raw / scale)
    RY = nearest_rotation(RY_raw / scale)
    lhs = np.concatenate([RA, -np.broadcast_to(eye, (n, 3, 3))], axis=2).reshape(3 * n, 6)
    rhs = (tB @ RY.T - tA).reshape(-1)
    sol, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
    return homogeneous(RX, sol[:3]), homogeneous(RY, sol[3:])


# A relative turn shorter than this has no axis worth comparing (a tracker's orientation
# noise is about 0.5 mrad; 2 degrees is 35 mrad).
MIN_TURN = np.deg2rad(2.0)
# Of the turns' size, what only another relation leaves (a rigid one leaves noise: 12.6 % of
# the 13-degree turns of the real session 20201002_Exp1), and how much less another order
# must leave to be taken for the one the logger wrote (that session misread: 142 %).
UNRELATED_LEFT, ORDER_GAIN = 0.2, 4.0


def turn_mismatch(meas_q: np.ndarray, ref_q: np.ndarray, W: np.ndarray | None = None) -> float | None:
    """How far two orientation series (N, 4) are from a rigid relation, measured = W reference X
    (W a frame, X a mount). Under it every turn from pose 0 of the measurements, R_0^T R_k, is
    the reference's conjugated by X: the same angle, its axis turned by X. The RMS of what the
    best X leaves of those turns, over their RMS size: about 0 for a rigid relation, about 1
    for none. None where fewer than 3 reference turns exceed MIN_TURN.

    Given W (the frames' rotation, from the positions), the turns in the frames, R_k R_0^T,
    are compared instead: the measurements' are the reference's turned by W. Where every turn
    is about one axis (poses set down by hand, turned about the vertical) a series read in
    another component order still turns rigidly about some axis, only not about W's image."""
    from .rotations import matrix_to_rotvec, quat_to_matrix

    def turns(q: np.ndarray) -> np.ndarray:
        R = quat_to_matrix(np.asarray(q, float))
        first_inverse = np.swapaxes(R[:1], 1, 2)
        return matrix_to_rotvec(R @ first_inverse if W is not None else first_inverse @ R)

    a, b = turns(meas_q), turns(ref_q)
    keep = np.linalg.norm(b, axis=1) > MIN_TURN
    if keep.sum() < 3:
        return None
    a, b = a[keep], b[keep]
    X = nearest_rotation(b.T @ a) if W is None else np.asarray(W, float).T   # rows: a_k = b_k X
    size = np.mean(np.sum(a * a + b * b, axis=1)) / 2
    return float(np.sqrt(np.mean(np.sum((a - b @ X) ** 2, axis=1)) / size))


# The component orders a logger may have written, tried against the names: one series'
# components shifted round (x, y, z, w under qw, qx, qy, qz: scipy's as_quat order), or both.
_SHIFTS = tuple((which, shift) for which in ("measured", "reference", "both") for shift in (1, 2, 3))


def quaternion_order_note(meas_q: np.ndarray, ref_q: np.ndarray, meas_p: np.ndarray | None = None,
                          ref_p: np.ndarray | None = None) -> str | None:
    """A note where the quaternions look written in another component order than their
    names say: as written no frame and mount relate the two orientation series, and with a
    series' components shifted round one does; None otherwise. First on the turns alone
    (which series is shifted they cannot say: turning both alike keeps the relation rigid),
    then, with the positions, on the turns in the frames, with the positions' frame rotation
    (`turn_mismatch`): a session turned about one axis shows it only so."""
    checks = [(None, "no frame and mount relate the two orientation series")]
    if meas_p is not None and ref_p is not None and len(ref_p) >= 3:
        W = umeyama(np.asarray(ref_p, float), np.asarray(meas_p, float))[0]
        checks.append((W, "the orientations turn about other axes than the positions' frame rotation allows"))
    for W, unrelated in checks:
        as_written = turn_mismatch(meas_q, ref_q, W)
        if as_written is None or as_written < UNRELATED_LEFT:
            continue
        shifted = {}
        # on the turns alone a shift of both series keeps the relation: only one is tried
        for which, shift in (s for s in _SHIFTS if W is not None or s[0] == "measured"):
            m = np.roll(meas_q, shift, axis=1) if which != "reference" else meas_q
            r = np.roll(ref_q, shift, axis=1) if which != "measured" else ref_q
            left = turn_mismatch(m, r, W)
            if left is not None:
                shifted[(which, shift)] = left
        if not shifted:
            continue
        (which, _), left = min(shifted.items(), key=lambda item: item[1])
        if left > min(UNRELATED_LEFT, as_written / ORDER_GAIN):
            continue
        series = ("one series'" if W is None else
                  "both series'" if which == "both" else f"the {which} series'")
        return (f"the quaternions look written in another order than their names: as written, {unrelated} "
                f"({'the best mount leaves' if W is None else 'leaving'} {as_written:.0%} of their turns), while "
                f"with {series} components shifted round "
                f"they agree ({left:.1%} left). posecorr reads qw, qx, qy, qz by their names: check which component "
                "each logger writes under each (scipy's as_quat() writes x, y, z, w)")
    return None


def orientation_notes(meas_q: np.ndarray, ref_q: np.ndarray | None, meas_p: np.ndarray | None = None,
                      ref_p: np.ndarray | None = None) -> list[str]:
    """What a fit or a diagnosis says of a table's orientations before its figures: the
    `quaternion_order_note`, where there is one (none without reference orientations)."""
    note = None if ref_q is None else quaternion_order_note(meas_q, ref_q, meas_p, ref_p)
    return [note] if note else []
