"""MLP (paper 2.4): MATLAB transfer functions, mapminmax, init, all activations, parity."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from posecorr import rotations  # noqa: E402
from posecorr.train import ACTIVATIONS, ARCHITECTURES, MLP  # noqa: E402
from posecorr.train.lm import Network  # noqa: E402
from posecorr.train.mlp import activation_xp, init_weights, mapminmax_settings  # noqa: E402
from posecorr.train.spec import parse_hidden  # noqa: E402


def random_poses(n, rng, spread=0.4):
    p = rng.uniform(-0.1, 0.1, (n, 3)) + np.array([0.0, -0.6, 0.5])
    q = rotations.matrix_to_quat(rotations.rotvec_to_matrix(rng.normal(0, spread, (n, 3))))
    return np.concatenate([p, q], axis=1)


def distorted(meas):
    ref = meas.copy()
    ref[:, :3] = meas[:, :3] + 0.02 * np.sin(8 * meas[:, [1, 2, 0]]) + 0.003
    R = rotations.quat_to_matrix(meas[:, 3:]) @ rotations.rotvec_to_matrix(np.array([0.02, -0.01, 0.03]))
    ref[:, 3:] = rotations.matrix_to_quat(R)
    return ref


def test_table1_architectures():
    assert len(ARCHITECTURES) == 16
    assert ARCHITECTURES[0] == (5,) and ARCHITECTURES[15] == (20, 20, 20, 20) and ARCHITECTURES[6] == (15, 15)
    assert parse_hidden("20-20") == (20, 20) and parse_hidden("#16") == (20, 20, 20, 20)
    assert parse_hidden("10,5") == (10, 5) and parse_hidden(7) == (7,)


def test_transfer_functions_match_matlab_definitions():
    n = np.array([[-3.0, -0.5, 0.0, 0.5, 2.0, 2.0]])
    np.testing.assert_allclose(activation_xp("tansig", n), 2 / (1 + np.exp(-2 * n)) - 1, atol=1e-15)
    np.testing.assert_allclose(activation_xp("logsig", n), 1 / (1 + np.exp(-n)), atol=1e-15)
    np.testing.assert_allclose(activation_xp("radbas", n), np.exp(-n ** 2), atol=1e-15)
    np.testing.assert_array_equal(activation_xp("purelin", n), n)
    np.testing.assert_array_equal(activation_xp("satlin", n), [[0, 0, 0, 0.5, 1, 1]])
    np.testing.assert_array_equal(activation_xp("hardlim", n), [[0, 0, 1, 1, 1, 1]])
    np.testing.assert_array_equal(activation_xp("compet", n), [[0, 0, 0, 0, 1, 0]])  # first maximum
    np.testing.assert_allclose(activation_xp("softmax", n), np.exp(n) / np.exp(n).sum(), atol=1e-15)
    # torch namespace gives the same numbers
    for name in ACTIVATIONS:
        t = activation_xp(name, torch.tensor(n)).numpy()
        np.testing.assert_allclose(t, activation_xp(name, n), atol=1e-15)


def test_mapminmax_like_matlab():
    X = np.array([[0.0, 5.0, 1.0], [2.0, 5.0, 3.0], [1.0, 5.0, 2.0]])
    gain, offset = mapminmax_settings(X)
    Xn = X * gain + offset
    np.testing.assert_allclose(Xn[:, 0], [-1, 1, 0])
    np.testing.assert_allclose(Xn[:, 1], [-1, -1, -1])  # constant row -> ymin, gain 1
    np.testing.assert_allclose(Xn[:, 2], [-1, 1, 0])


def test_nguyen_widrow_init_spreads_tansig_units_over_active_range():
    rng = np.random.default_rng(0)
    coefs, biases = init_weights([9, 20, 20, 9], "tansig", rng)
    assert [w.shape for w in coefs] == [(9, 20), (20, 20), (20, 9)]
    w = coefs[0]
    np.testing.assert_allclose(np.linalg.norm(w, axis=0), 2 * 0.7 * 20 ** (1 / 9), rtol=1e-12)
    # biases evenly spread (magnitudes are |linspace| * the same factor)
    np.testing.assert_allclose(np.sort(np.abs(biases[0])), np.sort(np.abs(2 * 0.7 * 20 ** (1 / 9)
                                                                          * np.linspace(-1, 1, 20))))
    assert np.all(np.abs(coefs[-1]) <= 1) and np.all(np.abs(biases[-1]) <= 1)  # output layer: rands


@pytest.mark.parametrize("act", ACTIVATIONS)
def test_factored_gauss_newton_equals_autograd_jacobian(act):
    rng = np.random.default_rng(7)
    net = Network([6, 5, 4, 3], act, np.array([0.5, 2.0, 1.5]))
    theta = torch.tensor(rng.standard_normal(net.n_params))
    X = torch.tensor(rng.uniform(-1, 1, (17, 6)))
    T = torch.tensor(rng.uniform(-1, 1, (17, 3)))
    JJ, g, r = net.gauss_newton(theta, X, T)
    J = net.jacobian(theta, X, T)
    np.testing.assert_allclose(JJ.numpy(), (J.T @ J).numpy(), atol=1e-11)
    np.testing.assert_allclose(g.numpy(), (J.T @ r.reshape(-1)).numpy(), atol=1e-11)
    np.testing.assert_allclose(r.numpy(), net.residual(theta, X, T).numpy(), atol=0)


@pytest.mark.parametrize("act", ACTIVATIONS)
def test_every_activation_constructs_trains_and_runs(act):
    rng = np.random.default_rng(8)
    meas = random_poses(120, rng)
    ref = distorted(meas)
    init = MLP("zhou", (6,), act, "lm", epochs=0).fit(meas, ref)
    for bad in ({"epochs": -5}, {"epochs": 2.5}, {"validation_fraction": 1.0}, {"validation_fraction": -0.5}):
        with pytest.raises(ValueError, match=f"{next(iter(bad))} must be"):
            MLP("zhou", (6,), act, "lm", **bad).fit(meas, ref)
    model = MLP("zhou", (6,), act, "lm", epochs=5, max_fail=100).fit(meas, ref)
    out = model.predict(meas)
    assert out.shape == (120, 7) and np.all(np.isfinite(out))
    np.testing.assert_allclose(np.linalg.norm(out[:, 3:], axis=1), 1.0, atol=1e-12)
    assert np.all(out[:, 3:][:, 0] >= 0)
    # measured 0.0014x (purelin) to 0.15x (compet) in 5 epochs
    assert model.history_["mse"][-1] < 0.3 * model.history_["mse"][0]
    if act in ("hardlim", "compet"):
        # zero derivative (as MATLAB): hidden weights stay at their initial values,
        # only the linear output layer learns
        np.testing.assert_array_equal(model.coefs_[0], init.coefs_[0])
        np.testing.assert_array_equal(model.intercepts_[0], init.intercepts_[0])
        assert not np.allclose(model.coefs_[1], init.coefs_[1])
    else:
        assert not np.allclose(model.coefs_[0], init.coefs_[0])


@pytest.mark.parametrize("rep", ["pos", "eaa", "quat", "R", "zhou"])
def test_forward_torch_equals_predict_numpy(rep):
    rng = np.random.default_rng(9)
    meas = random_poses(80, rng)
    ref = distorted(meas)
    model = MLP(rep, (8, 8), "tansig", "lm", epochs=3).fit(meas, ref)
    test = random_poses(30, rng)
    out = model.forward(torch.tensor(test, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(out, model.predict(test), atol=1e-12, rtol=0)
    if rep == "pos":
        np.testing.assert_allclose(out[:, 3:], rotations.canonical_quat(test[:, 3:]), atol=1e-15)


def test_export_info_and_params():
    rng = np.random.default_rng(10)
    meas = random_poses(60, rng)
    model = MLP("zhou", (5, 5), "logsig", "br", epochs=3).fit(meas, distorted(meas))
    info = model.export_info()
    assert info["method"] == "mlp" and info["architecture"] == "5-5" and info["trainer"] == "br"
    assert info["activation"] == "logsig" and int(info["n_parameters"]) == (9 + 1) * 5 + 6 * 5 + 6 * 9
    assert all(isinstance(v, str) for v in info.values())
    with pytest.raises(ValueError):
        MLP("zhou", (5,), "relu").fit(meas, distorted(meas))
    with pytest.raises(ValueError):
        MLP("zhou", (5,), "tansig", "trainscg").fit(meas, distorted(meas))


@pytest.mark.slow
def test_exp3_zhou_tansig_20x4_br_reaches_paper_improvement():
    simulate = pytest.importorskip("posecorr.simulate")
    from posecorr.train.protocol import fit_one
    from posecorr.train.spec import ModelSpec, parse_network

    sim = simulate.simulate(3, seed=0)
    hidden, trainer = parse_network("16/2")
    res = fit_one(sim.table, ModelSpec("mlp", "zhou", hidden, "tansig", trainer, epochs=100), seed=0)
    assert res.test["improvement_total"] >= 17.1
    assert res.test["rmse_total"] <= 1.5 * sim.noise_floor["rmse_total"]
