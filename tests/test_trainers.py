"""Trainers: LM / BR against closed forms, BR's evidence updates, the first-order family."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from posecorr import rotations  # noqa: E402
from posecorr.train import MLP, TRAINERS  # noqa: E402
from posecorr.train.base import encode_pose  # noqa: E402


def linear_problem(n=300, noise=1e-4, seed=0):
    """Poses whose reference vector is an exact affine map of the measured vector + noise."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.1, 0.1, (n, 3)) + np.array([0.0, -0.6, 0.5])
    meas = np.concatenate([p, np.tile([1.0, 0, 0, 0], (n, 1))], axis=1)
    ref = meas.copy()
    A = np.eye(3) + rng.normal(0, 0.05, (3, 3))
    ref[:, :3] = p @ A.T + np.array([0.003, -0.002, 0.001]) + rng.normal(0, noise, (n, 3))
    return meas, ref


def lstsq_prediction(meas, ref, test):
    X = np.concatenate([meas[:, :3], np.ones((len(meas), 1))], axis=1)
    coef, *_ = np.linalg.lstsq(X, ref[:, :3], rcond=None)
    return np.concatenate([test[:, :3], np.ones((len(test), 1))], axis=1) @ coef


@pytest.mark.parametrize("hidden", [(), (4,)])
@pytest.mark.parametrize("trainer", ["lm", "br"])
def test_lm_and_br_match_closed_form_least_squares_on_linear_net(hidden, trainer):
    meas, ref = linear_problem()
    model = MLP("pos", hidden, "purelin", trainer, epochs=200, validation_fraction=0.0).fit(meas, ref)
    want = lstsq_prediction(meas, ref, meas)
    got = model.predict(meas)[:, :3]
    # BR is a ridge fit with a tiny alpha / beta on a well-determined problem
    tol = 1e-9 if trainer == "lm" else 1e-7
    assert np.max(np.abs(got - want)) < tol


def test_br_weights_are_the_ridge_solution_of_their_own_alpha_beta():
    meas, ref = linear_problem(noise=2e-3)
    model = MLP("pos", (), "purelin", "br", epochs=300).fit(meas, ref)
    # The final network minimises beta * Ed + alpha * Ew in the scaled parameters:
    # (beta Xn'DXn + alpha I) w = beta Xn' D tn per output, D the error scale^2.
    X = encode_pose(meas, "pos") * model.x_gain_ + model.x_offset_
    T = encode_pose(ref, "pos") * model.y_gain_ + model.y_offset_
    Xa = np.concatenate([X, np.ones((len(X), 1))], axis=1)
    a, b = model.extra_["alpha"], model.extra_["beta"]
    for k in range(3):
        d2 = (1.0 / model.y_gain_[k]) ** 2
        w = np.linalg.solve(b * d2 * Xa.T @ Xa + a * np.eye(4), b * d2 * Xa.T @ T[:, k])
        got = np.concatenate([model.coefs_[0][:, k], model.intercepts_[0][k:k + 1]])
        np.testing.assert_allclose(got, w, rtol=1e-4, atol=1e-6)


def test_br_gamma_is_parameter_count_when_well_determined_and_falls_with_noise():
    meas, ref = linear_problem(n=400, noise=1e-5)
    clean = MLP("pos", (), "purelin", "br", epochs=200).fit(meas, ref)
    n_params = clean.n_parameters_
    assert n_params == 12
    assert clean.extra_["gamma"] == pytest.approx(n_params, abs=0.05)
    # an over-parameterised net on targets that are pure noise: the evidence switches most
    # parameters off
    rng = np.random.default_rng(1)
    meas, _ = linear_problem(n=60, seed=2)
    noisy_ref = meas.copy()
    noisy_ref[:, :3] = meas[:, :3].mean(0) + rng.normal(0, 0.01, (60, 3))
    noisy = MLP("pos", (10,), "tansig", "br", epochs=200).fit(meas, noisy_ref)
    assert noisy.n_parameters_ == 73
    assert noisy.extra_["gamma"] < 0.25 * noisy.n_parameters_


def test_lm_returns_the_best_validation_network():
    rng = np.random.default_rng(2)
    meas, ref = linear_problem(n=60, noise=5e-3, seed=3)
    Xv, Rv = linear_problem(n=40, noise=5e-3, seed=4)
    model = MLP("pos", (15, 15), "tansig", "lm", epochs=200).fit(meas, ref, validation=(Xv, Rv))
    vals = np.asarray(model.history_["val_mse"])
    assert model.best_val_loss_ == pytest.approx(np.nanmin(vals))
    # the returned network has exactly that validation error (in the scaled-target units)
    pred = encode_pose(model.predict(Xv), "pos")
    want = encode_pose(Rv, "pos")
    mse_units = np.mean(((pred - want)) ** 2)
    assert mse_units == pytest.approx(model.best_val_loss_, rel=1e-9)
    if model.stop_reason_ == "Validation stop":
        assert int(np.nanargmin(vals)) == len(vals) - 1 - 6
    del rng


@pytest.mark.parametrize("trainer", [t for t in TRAINERS if t not in ("lm", "br")])
def test_first_order_trainers_reduce_the_error(trainer):
    rng = np.random.default_rng(5)
    p = rng.uniform(-0.1, 0.1, (200, 3)) + np.array([0.0, -0.6, 0.5])
    q = rotations.matrix_to_quat(rotations.rotvec_to_matrix(rng.normal(0, 0.3, (200, 3))))
    meas = np.concatenate([p, q], axis=1)
    ref = meas.copy()
    ref[:, :3] += 0.01 * np.tanh(20 * (p - p.mean(0)))
    model = MLP("pos", (8,), "tansig", trainer, epochs=60, max_fail=1000, lr=0.01).fit(meas, ref)
    mse = np.asarray(model.history_["mse"])
    assert np.all(np.isfinite(mse))
    if trainer in ("gd", "gdm"):
        # plain gradient descent at lr 0.01 is slow (as in MATLAB) but must descend
        assert mse[-1] < mse[0] and np.all(np.diff(mse[5:]) <= 1e-15)
    else:
        assert mse.min() < 0.9 * mse[0]


def test_lbfgs_reaches_least_squares_on_linear_net():
    meas, ref = linear_problem()
    model = MLP("pos", (), "purelin", "lbfgs", epochs=100, validation_fraction=0.0, min_grad=0).fit(meas, ref)
    # within 5 % of the noise sigma (1e-4 m) of the exact least-squares prediction
    assert np.max(np.abs(model.predict(meas)[:, :3] - lstsq_prediction(meas, ref, meas))) < 5e-6
