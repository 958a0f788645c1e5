"""MLP (paper 2.4): MATLAB transfer functions, mapminmax, init, all activations, parity."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from posecorr import rotations  # noqa: E402
from posecorr.train import ACTIVATIONS, ARCHITECTURES, MLP  # noqa: E402
from posecorr.train import lm  # noqa: E402
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
    assert parse_hidden("10,5") == (10, 5) and parse_hidden(7) == (7,) and parse_hidden("") == ()
    for text in ("5-", "-5", "5,,5"):        # "5-" was taken for one layer of 5
        with pytest.raises(ValueError, match=f"got an empty one in '{text}'"):
            parse_hidden(text)


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


def test_mapminmax_holds_a_row_float32_cannot_resolve_constant():
    """A row that varies by fewer than CONSTANT_STEPS float32 steps of its magnitude is
    constant (gain 1): the exported graph, in float32, would see its rounding, not its values."""
    from posecorr.train.mlp import CONSTANT_STEPS

    step = float(np.spacing(np.float32(1.0)))
    X = np.array([[1.0, 0.5, 3.0], [1.0 - 0.5 * CONSTANT_STEPS * step, 0.5 + 1e-3, 3.0 + 2 * CONSTANT_STEPS * 2.4e-7]])
    gain, offset = mapminmax_settings(X)
    assert gain[0] == 1.0 and offset[0] == pytest.approx(-1.0 - X[:, 0].min())
    np.testing.assert_allclose(gain[1:], 2.0 / (X.max(axis=0) - X.min(axis=0))[1:])


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


def test_error_space_system_solves_the_weight_space_one():
    """Fewer error terms than weights (a small session): the step and trainbr's trace come
    from J J' (N x N); they equal the weight-space solve of J'J (P x P) and the autograd J."""
    rng = np.random.default_rng(11)
    net = Network([6, 5, 4, 3], "tansig", np.array([0.5, 2.0, 1.5]))
    theta = torch.tensor(rng.standard_normal(net.n_params))
    X, T = torch.tensor(rng.uniform(-1, 1, (7, 6))), torch.tensor(rng.uniform(-1, 1, (7, 3)))
    J, r = net.jacobian_rows(theta, X, T)
    np.testing.assert_allclose(J.numpy(), net.jacobian(theta, X, T).numpy(), atol=1e-12)
    dual, normal = net.linearise(theta, X, T), lm.Normal(*net.gauss_newton(theta, X, T))
    assert isinstance(dual, lm.Dual) and J.shape == (21, net.n_params) == (21, 74)
    assert dual.ed == pytest.approx(normal.ed, rel=1e-14)
    np.testing.assert_allclose(dual.g.numpy(), normal.g.numpy(), atol=1e-12)
    for beta, c, alpha in ((1.0, 1e-3, 0.0), (3.0, 0.5, 0.2), (2.0, 5.0, 4.0), (0.05, 0.03, 0.02)):
        want = torch.linalg.solve(beta * J.T @ J + c * torch.eye(74, dtype=torch.float64),
                                  -(beta * J.T @ r.reshape(-1) + alpha * theta))
        for system in (dual, normal):
            np.testing.assert_allclose(system.step(beta, c, alpha, theta).numpy(), want.numpy(),
                                       rtol=0, atol=1e-9 * float(want.abs().max()))
        want_trace = float(torch.trace(torch.linalg.inv(beta * J.T @ J + alpha * torch.eye(74, dtype=torch.float64))))
        if alpha > 0:
            assert dual.trace_inverse(beta, alpha) == pytest.approx(want_trace, rel=1e-10)
            assert normal.trace_inverse(beta, alpha) == pytest.approx(want_trace, rel=1e-10)
    X, T = torch.tensor(rng.uniform(-1, 1, (30, 6))), torch.tensor(rng.uniform(-1, 1, (30, 3)))
    assert isinstance(net.linearise(theta, X, T), lm.Normal)      # 90 error terms, 74 weights


def test_training_in_error_space_reaches_the_weight_space_network(monkeypatch):
    """trainlm on 12 poses (108 error terms, 1,649 weights) steps through J J'; forced through
    J'J instead, it reaches the same network. (mu held at 0.1 and above keeps both solves well
    posed; trainbr's damping alpha does so by itself, but on 12 poses it drives every weight
    towards zero, which would make the comparison empty.)"""
    rng = np.random.default_rng(12)
    meas = random_poses(12, rng)
    ref = distorted(meas)

    def fit():
        return MLP("zhou", (20, 20, 20, 20), "tansig", "lm", epochs=15, mu=0.1, mu_dec=0.5,
                   random_state=0).fit(meas, ref)

    dual = fit()
    monkeypatch.setattr(Network, "linearise",
                        lambda self, theta, X, T: lm.Normal(*self.gauss_newton(theta, X, T)))
    normal = fit()
    assert dual.n_epochs_ == normal.n_epochs_ >= 10
    for a, b in zip(dual.coefs_ + dual.intercepts_, normal.coefs_ + normal.intercepts_):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert max(float(np.abs(w).max()) for w in dual.coefs_) > 0.5


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


def test_network_after_the_physics_stage_learns_what_the_stage_left(tmp_path):
    """A 200-pose session with a range scale (1.5 %) that the physics stage (station, mount)
    does not model: `fit`'s network core learns the residual and removes most of it held out;
    the paper's absolute network in its place is driven by trainbr to a constant pose, metres
    from the truth (it made every physics+mlp fit fall back to the rigid fit). The residual
    core's file runs as its estimator in onnxruntime and the C runtime."""
    import onnxruntime as ort

    from posecorr.controller.runtime import Corrector
    from posecorr.effects import get_effect
    from posecorr.export import to_onnx
    from posecorr.metrics import pose_metrics
    from posecorr.simulate import simulate_session
    from posecorr.train.pipeline import CorrectionPipeline
    from posecorr.train.spec import spec_from_options

    table = simulate_session(0, n=200, robot="ur5e",
                             extra={"range_scale": 3 * get_effect("range_scale").default_theta()}).table
    folds = np.array_split(np.random.default_rng(0).permutation(table.n), 5)

    def held_out_mm(make):
        predicted = np.empty_like(table.measured)
        for fold in folds:
            train = np.setdiff1d(np.arange(table.n), fold)
            predicted[fold] = make().fit(table.measured[train], table.reference[train]).predict(table.measured[fold])
        return 1e3 * pose_metrics(table.reference, predicted, True)["rmse_pos"]

    def network(residual):
        return MLP("zhou", (5,), "tansig", "br", epochs=200, residual=residual)

    assert spec_from_options("mlp", "zhou").make().residual is True
    physics = held_out_mm(lambda: CorrectionPipeline(("station", "mount")))
    residual = held_out_mm(lambda: CorrectionPipeline(("station", "mount"), network(True)))
    absolute = held_out_mm(lambda: CorrectionPipeline(("station", "mount"), network(False)))
    assert physics > 5.0 and residual < 0.4 * physics and absolute > 100.0, (physics, residual, absolute)
    model = CorrectionPipeline(("station", "mount"), network(True)).fit(table.measured, table.reference)
    # the file counts the stage's 12 fitted directions with the network's weights (it said 104)
    weights = sum(w.size + b.size for w, b in zip(model.core_.coefs_, model.core_.intercepts_))
    assert weights == 104 and model.export_info()["n_parameters"] == "116"
    assert model.export_info()["output"] == "input + network"
    to_onnx(model, tmp_path / "r.onnx", measured=table.measured)
    x = table.measured[:50]
    want = model.predict(x)
    got = ort.InferenceSession(str(tmp_path / "r.onnx"), providers=["CPUExecutionProvider"]).run(
        None, {"pose": x.astype(np.float32)})[0]
    np.testing.assert_allclose(got[:, :3], want[:, :3], rtol=0, atol=2e-5)
    np.testing.assert_allclose(Corrector(tmp_path / "r.onnx").correct(x)[:, :3], want[:, :3], rtol=0, atol=2e-5)


def test_trainbr_learns_where_the_weights_outnumber_the_errors():
    """trainbr on 40 poses (120 numbers) with a 183-weight network: a smooth 4.6 mm field under
    0.87 mm of noise. MATLAB's start (beta = 1 where P >= N, whatever the errors' scale) let
    the weights' penalty drown the data: 1.6 effective weights, 3.3 mm left held out. Started
    at gamma = N / 2, the evidence settles between the two (92 effective weights) and the
    field is learned: held out, under half of it remains (1.5 mm), and the noise is not
    interpolated (0.3 mm left on the training poses)."""
    rng = np.random.default_rng(1)

    def poses(n):
        return np.hstack([rng.uniform(-0.5, 0.5, (n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))])

    def truth(m):
        x, y, z = m[:, 0], m[:, 1], m[:, 2]
        out = m.copy()
        out[:, :3] += 0.004 * np.stack([np.sin(3 * x + y), np.cos(2 * y - z), 4 * x * z], axis=1)
        return out

    def rms_mm(a, b):
        return 1e3 * np.sqrt(np.mean(np.sum((a[:, :3] - b[:, :3]) ** 2, axis=1)))

    train, test = poses(40), poses(400)
    target = truth(train)
    target[:, :3] += rng.normal(0.0, 0.0005, (40, 3))
    net = MLP("pos", (10, 10), "tansig", "br", epochs=300, residual=True).fit(train, target)
    assert net.n_parameters_ == 183 > 40 * 3
    field = rms_mm(test, truth(test))
    gamma = net.history_["gamma"][-1]
    assert 10 < gamma < 40 * 3, gamma
    assert rms_mm(net.predict(test), truth(test)) < 0.5 * field, field
    assert rms_mm(net.predict(train), target) > 0.1    # not interpolated: the noise is 0.87 mm
