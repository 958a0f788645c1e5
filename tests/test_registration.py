"""Closed-form registration against known transforms built with scipy's Rotation."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

from posecorr.geometry import homogeneous, nearest_rotation
from posecorr.registration import quaternion_order_note, robot_world_hand_eye, turn_mismatch, umeyama

REALDATA = Path(__file__).parent / "data" / "realdata"


def test_umeyama_recovers_any_rigid_transform() -> None:
    rng = np.random.default_rng(0)
    for seed in range(5):
        R = Rotation.random(random_state=seed).as_matrix()
        t = rng.normal(size=3)
        src = rng.uniform(-0.2, 0.2, size=(50, 3))
        R_est, t_est, s = umeyama(src, src @ R.T + t)
        np.testing.assert_allclose(R_est, R, atol=1e-12)
        np.testing.assert_allclose(t_est, t, atol=1e-12)
        assert s == 1.0


def test_umeyama_scale_and_reflection_guard() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    R = Rotation.from_rotvec([0.1, -0.3, 2.5]).as_matrix()
    R_est, t_est, s = umeyama(src, 1.01 * src @ R.T + [1, 2, 3], with_scale=True)
    assert s == pytest.approx(1.01, rel=1e-12)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, [1, 2, 3], atol=1e-12)
    # A mirrored target still yields a proper rotation, never a reflection: the best one,
    # as scipy's Kabsch finds it (unique here: the cross-covariance's singular values are
    # 23.5, 17.0, 3.6).
    target = src * [1, 1, -1]
    R_m, t_m, _ = umeyama(src, target)
    assert np.linalg.det(R_m) == pytest.approx(1.0)
    best, _ = Rotation.align_vectors(target - target.mean(axis=0), src - src.mean(axis=0))
    np.testing.assert_allclose(R_m, best.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(t_m, target.mean(axis=0) - best.as_matrix() @ src.mean(axis=0), atol=1e-12)


def test_umeyama_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="at least 3 points"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        umeyama(np.zeros((5, 2)), np.zeros((5, 2)))


def test_nearest_rotation_is_nearest() -> None:
    R = Rotation.from_rotvec([0.4, 0.2, -0.1]).as_matrix()
    noisy = R + 1e-3 * np.random.default_rng(2).normal(size=(3, 3))
    P = nearest_rotation(noisy)
    np.testing.assert_allclose(P @ P.T, np.eye(3), atol=1e-12)
    assert np.linalg.norm(P - R) < 2e-3
    # with det > 0 the nearest rotation is the orthogonal polar factor
    assert np.linalg.det(noisy) > 0
    np.testing.assert_allclose(P, scipy.linalg.polar(noisy)[0], atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_robot_world_hand_eye_exact_and_noisy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    X = homogeneous(Rotation.from_rotvec(rng.normal(scale=0.05, size=3)).as_matrix(), rng.normal(scale=0.01, size=3))
    # W: an arbitrary frame (the tracker's own), far from the identity.
    W = homogeneous(Rotation.random(random_state=seed + 10).as_matrix(), rng.normal(size=3))
    T = homogeneous(Rotation.from_euler("xyz", rng.uniform(-0.5, 0.5, size=(40, 3))).as_matrix(),
                    rng.uniform(-0.2, 0.2, size=(40, 3)) + [0, -0.6, 0.5])
    M = W @ T @ X
    X_est, Y_est = robot_world_hand_eye(T, M)
    np.testing.assert_allclose(X_est, X, atol=1e-9)
    np.testing.assert_allclose(Y_est, np.linalg.inv(W), atol=1e-9)
    # With 0.3 mm / 0.5 mrad noise the estimate stays within a few times the noise.
    noise = homogeneous(Rotation.from_rotvec(rng.normal(scale=5e-4, size=(40, 3))).as_matrix(),
                        rng.normal(scale=3e-4, size=(40, 3)))
    X_n, Y_n = robot_world_hand_eye(T, M @ noise)
    angle = Rotation.from_matrix(X_n[:3, :3] @ X[:3, :3].T).magnitude()
    assert angle < 1e-3
    assert np.linalg.norm(X_n[:3, 3] - X[:3, 3]) < 2e-3


def test_robot_world_hand_eye_needs_three_poses() -> None:
    with pytest.raises(ValueError, match="at least 3 poses"):
        robot_world_hand_eye(np.tile(np.eye(4), (2, 1, 1)), np.tile(np.eye(4), (2, 1, 1)))


def _related_orientations(n: int, seed: int, axes: int = 3, noise: float = 5e-4) -> tuple[np.ndarray, np.ndarray]:
    """(measured, reference) scalar-first quaternions of n poses related by a frame W and a
    mount X, with `noise` rad of noise: the reference turned about `axes` axes."""
    rng = np.random.default_rng(seed)
    turns = rng.uniform(-0.6, 0.6, (n, 3))
    turns[:, axes:] = 0.0
    ref = Rotation.from_rotvec(turns) * Rotation.random(random_state=seed)
    W, X = Rotation.random(random_state=seed + 1), Rotation.random(random_state=seed + 2)
    meas = W * ref * X * Rotation.from_rotvec(rng.normal(scale=noise, size=(n, 3)))
    return meas.as_quat(scalar_first=True), ref.as_quat(scalar_first=True)


@pytest.mark.parametrize("seed", range(5))
def test_quaternions_written_in_two_orders_are_told(seed: int) -> None:
    """scipy's as_quat() is x, y, z, w: written under qw, qx, qy, qz for one series, the two
    orientation series no longer relate by a frame and a mount (their turns from pose 0 keep
    their angles but not a common axis map), and the note says so; as written, or written so
    for both (which keeps the relation: the orientations cannot tell it), nothing is said."""
    meas, ref = _related_orientations(40, seed, noise=5e-4 if seed else 0.0)   # seed 0: exact, no noise
    scalar_last = lambda q: Rotation.from_quat(q, scalar_first=True).as_quat()  # noqa: E731
    assert turn_mismatch(meas, ref) < 0.01
    assert quaternion_order_note(meas, ref) is None
    assert quaternion_order_note(scalar_last(meas), scalar_last(ref)) is None
    for pair in ((scalar_last(meas), ref), (meas, scalar_last(ref))):
        assert turn_mismatch(*pair) > 0.5
        note = quaternion_order_note(*pair)
        assert note is not None and "written in another order" in note and "x, y, z, w" in note


def test_turns_about_one_axis_tell_the_order_with_the_positions() -> None:
    """All turns about one axis: any axis maps to any other, so on the turns alone the mismatch
    is small whatever the order. The turns in the frames must follow the positions' frame
    rotation, which a misread series breaks: with the positions the note is made for the
    measured series, the reference or both, and not for the series as written (the real
    session Exp1 turns about its yaw axis only: `test_the_real_session_read_in_another_order`)."""
    meas, ref = _related_orientations(40, 0, axes=1)
    W = Rotation.random(random_state=1)          # the frame _related_orientations draws
    rng = np.random.default_rng(0)
    ref_p = rng.uniform(-0.5, 0.5, (40, 3))
    meas_p = W.apply(ref_p) + [0.3, -1.0, 2.0] + rng.normal(scale=1e-3, size=(40, 3))
    scalar_last = lambda q: Rotation.from_quat(q, scalar_first=True).as_quat()  # noqa: E731
    assert quaternion_order_note(scalar_last(meas), ref) is None
    assert quaternion_order_note(meas, ref, meas_p, ref_p) is None
    for m, r, which in ((scalar_last(meas), ref, "the measured series'"), (meas, scalar_last(ref), "the reference series'"),
                        (scalar_last(meas), scalar_last(ref), "both series'")):
        note = quaternion_order_note(m, r, meas_p, ref_p)
        assert note is not None and f"with {which} components shifted round" in note, note
    assert turn_mismatch(meas, ref[:1].repeat(40, axis=0)) is None   # no turn at all: nothing to compare


def test_the_real_session_read_in_another_order() -> None:
    """The real session 20201002_Exp1 (11 poses set down by hand, 13 degrees of yaw) with its
    measured quaternions rolled to x, y, z, w: the rigid fit's rmse_rot grows 20 times, and
    the note names the measured series; as the file has them, no note."""
    from posecorr.data import read_table

    table = read_table(REALDATA / "20201002_Exp1.csv")
    assert quaternion_order_note(table.meas_q, table.ref_q, table.meas_p, table.ref_p) is None
    rolled = np.roll(table.meas_q, -1, axis=1)
    note = quaternion_order_note(rolled, table.ref_q, table.meas_p, table.ref_p)
    assert note is not None and "with the measured series' components shifted round" in note, note