"""Rotations against scipy's Rotation; numpy against torch; decode of raw vectors."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from posecorr import rotations as rot

N = 10_000


def _canonical(q: np.ndarray) -> np.ndarray:
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


@pytest.fixture(scope="module")
def rotations() -> Rotation:
    """10^4 random rotations plus angles near 0 and near pi about random axes."""
    rng = np.random.default_rng(7)
    axes = rng.normal(size=(2000, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    tiny = 10.0 ** rng.uniform(-13, -3, size=(1000, 1))
    small = axes[:1000] * tiny
    near_pi = axes[1000:] * (np.pi - tiny)
    random = Rotation.random(N - 2000, random_state=3).as_rotvec()
    return Rotation.from_rotvec(np.concatenate([random, small, near_pi]))


def test_quaternion_matrix_against_scipy(rotations: Rotation) -> None:
    R = rotations.as_matrix()
    q_scipy = _canonical(rotations.as_quat(scalar_first=True))
    np.testing.assert_allclose(rot.matrix_to_quat(R), q_scipy, atol=1e-12)
    np.testing.assert_allclose(rot.quat_to_matrix(q_scipy), R, atol=1e-12)


def test_rotvec_against_scipy(rotations: Rotation) -> None:
    v = rotations.as_rotvec()
    np.testing.assert_allclose(rot.rotvec_to_matrix(v), rotations.as_matrix(), atol=1e-12)
    # Near pi the axis sign is ambiguous only at exactly pi; these are pi - 1e-13 at most.
    np.testing.assert_allclose(rot.matrix_to_rotvec(rotations.as_matrix()), v, atol=1e-9)


@pytest.mark.parametrize("rep", rot.orientations())
def test_round_trip(rotations: Rotation, rep: str) -> None:
    R = rotations.as_matrix()
    params = rot.encode(R, rep)
    assert params.shape == (N, rot.REPRESENTATIONS[rep].size)
    np.testing.assert_allclose(rot.decode(params, rep), R, atol=1e-12)


def test_zhou_is_first_two_columns(rotations: Rotation) -> None:
    R = rotations.as_matrix()
    z = rot.encode(R, "zhou")
    np.testing.assert_array_equal(z[:, :3], R[:, :, 0])
    np.testing.assert_array_equal(z[:, 3:], R[:, :, 1])


@pytest.mark.parametrize("rep", rot.orientations())
def test_numpy_and_torch_agree(rotations: Rotation, rep: str) -> None:
    R = rotations.as_matrix()
    params_np = rot.encode(R, rep)
    params_t = rot.encode(torch.from_numpy(R), rep)
    np.testing.assert_allclose(params_t.numpy(), params_np, atol=1e-12, rtol=0)
    raw = params_np + np.random.default_rng(1).normal(scale=0.3, size=params_np.shape)
    np.testing.assert_allclose(rot.decode(torch.from_numpy(raw), rep).numpy(), rot.decode(raw, rep),
                               atol=1e-12, rtol=0)


@pytest.mark.parametrize("rep", rot.orientations())
def test_decode_of_any_raw_vector_is_proper(rep: str) -> None:
    rng = np.random.default_rng(2)
    raw = rng.normal(scale=3.0, size=(5000, rot.REPRESENTATIONS[rep].size))
    R = rot.decode(raw, rep)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


@pytest.mark.parametrize("rep", rot.orientations())
def test_decode_is_differentiable_everywhere_used(rep: str) -> None:
    """Gradients are finite at the identity, where Rodrigues and the quaternion log are 0/0,
    and match finite differences there, near it, in general and near pi, for decode both of
    encoded and of raw (off-manifold) parameters and for encode."""
    params = torch.tensor(rot.encode(np.eye(3)[None], rep), requires_grad=True)
    R = rot.decode(params, rep)
    back = rot.encode(R, rep)
    (R.sum() + back.sum()).backward()
    assert torch.isfinite(params.grad).all()
    matrices = Rotation.from_rotvec([[0, 0, 0], [1e-8, -2e-8, 3e-8], [1e-4, 2e-4, -1e-4], [0.3, -1.2, 0.8],
                                     [0, 0, np.pi - 1e-3]]).as_matrix()
    encoded = rot.encode(matrices, rep)
    raw = encoded + np.random.default_rng(3).normal(scale=0.05, size=encoded.shape)
    for x in np.concatenate([encoded, raw]):
        assert torch.autograd.gradcheck(lambda p: rot.decode(p, rep), (torch.tensor(x[None], requires_grad=True),))
    for M in matrices:
        assert torch.autograd.gradcheck(lambda m: rot.encode(m, rep), (torch.tensor(M[None], requires_grad=True),))


def test_rotvec_gradient_matches_finite_differences() -> None:
    v = torch.tensor([[1e-9, -2e-9, 3e-9], [0.3, -1.2, 0.8]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rot.rotvec_to_matrix, (v,))


def test_geodesic_angle_against_scipy(rotations: Rotation) -> None:
    other = Rotation.random(N, random_state=11)
    expected = (rotations * other.inv()).magnitude()
    got = rot.geodesic_angle(rotations.as_matrix(), other.as_matrix())
    np.testing.assert_allclose(got, expected, atol=1e-12)
    # Small angles keep their digits (arccos((tr - 1) / 2) would return 0 below ~1e-8).
    tiny = Rotation.from_rotvec([[1e-10, 0, 0]]).as_matrix()
    assert rot.geodesic_angle(tiny, np.eye(3)[None])[0] == pytest.approx(1e-10, rel=1e-6)


def test_unknown_representation_is_named() -> None:
    with pytest.raises(ValueError, match="expected one of eaa, quat, R, zhou"):
        rot.encode(np.eye(3), "euler")
