"""Closed-form registration against known transforms built with scipy's Rotation."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

from posecorr.geometry import homogeneous, nearest_rotation
from posecorr.registration import robot_world_hand_eye, umeyama


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
