"""The line-search and conjugate-gradient trainers (trainscg, trainbfg, traincgb, traincgf,
traincgp) on problems whose minimiser is known: a quadratic (numpy's solve), Rosenbrock's
function (1, 1), and a linear network, whose least-squares weights numpy's lstsq gives."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from posecorr.train import MLP  # noqa: E402
from posecorr.train.trainers import TRAINERS  # noqa: E402

from test_trainers import linear_problem, lstsq_prediction  # noqa: E402

NEW = ("scg", "bfg", "cgb", "cgf", "cgp")


class Function:
    """A Problem (mse, mse_grad, loss) over a plain function of the parameter vector."""

    def __init__(self, f):
        self.f = f

    def loss(self, theta):
        return self.f(theta)

    def mse(self, theta):
        return float(self.f(theta))

    def mse_grad(self, theta):
        th = theta.detach().requires_grad_(True)
        value = self.f(th)
        (grad,) = torch.autograd.grad(value, th)
        return float(value.detach()), grad


def minimise(name, problem, x0, epochs):
    """The trainer's Step driven as the training loop drives it (stop on its stop_reason)."""
    x = torch.as_tensor(np.asarray(x0, float))
    step = TRAINERS[name].step(problem, x, SimpleNamespace(lr=0.01))
    value, g = problem.mse_grad(x)
    for epoch in range(epochs):
        if step.stop_reason or float(g.norm()) < 1e-13:
            break
        x, value, g = step(epoch, x, value, g)
    return x.numpy(), value, step


def quadratic(n=8, cond=50.0, seed=0):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    A = Q @ np.diag(np.geomspace(1.0, cond, n)) @ Q.T
    b = rng.normal(size=n)
    At, bt = torch.as_tensor(A), torch.as_tensor(b)
    return Function(lambda x: 0.5 * x @ At @ x - bt @ x), np.linalg.solve(A, b)


def test_registry_holds_table_1():
    numbered = sorted((t.number, t.matlab) for t in TRAINERS.values() if t.number is not None)
    assert numbered == [(1, "trainlm"), (2, "trainbr"), (3, "trainrp"), (4, "trainscg"), (5, "trainbfg"),
                        (6, "traingd"), (7, "traingda"), (8, "traingdm"), (9, "traingdx"), (10, "traincgb"),
                        (11, "traincgf"), (12, "traincgp")]
    assert all(TRAINERS[name].step is not None for name in NEW)


@pytest.mark.parametrize("name", NEW)
def test_quadratic_minimiser(name):
    problem, x_star = quadratic()
    x, value, step = minimise(name, problem, np.zeros(len(x_star)), 400)
    np.testing.assert_allclose(x, x_star, atol=1e-6)
    assert value == pytest.approx(problem.mse(torch.as_tensor(x_star)), abs=1e-12)


def test_scg_is_conjugate_gradient_on_a_quadratic():
    # Moller's step is (up to the small scale lambda) the exact line minimum along
    # conjugate directions when the finite-difference curvature is exact (a quadratic):
    # about n steps reach the minimiser, where resilient backpropagation is still far off.
    problem, x_star = quadratic(n=6, cond=20.0, seed=3)
    x, _, _ = minimise("scg", problem, np.zeros(6), 6 + 2)
    np.testing.assert_allclose(x, x_star, atol=1e-7)
    x_rp, _, _ = minimise("rp", problem, np.zeros(6), 6 + 2)
    assert np.max(np.abs(x_rp - x_star)) > 1e-2


def rosenbrock():
    return Function(lambda x: (1.0 - x[0]) ** 2 + 100.0 * (x[1] - x[0] ** 2) ** 2)


@pytest.mark.parametrize("name", ["scg", "bfg"])
def test_rosenbrock_minimum(name):
    x, value, step = minimise(name, rosenbrock(), [-1.2, 1.0], 1000)
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-6)
    assert value < 1e-12 and step.stop_reason is None


@pytest.mark.parametrize("name,atol", [("cgb", 1e-4), ("cgp", 3e-3), ("cgf", 3e-2)])
def test_rosenbrock_conjugate_gradients_stop_where_srchcha_cannot_resolve_the_step(name, atol):
    # srchcha's interval tolerance (delta 0.01 / scale_tol 20 along a unit direction) ends
    # the search without a lower point once the line minimum is closer than that: MATLAB's
    # "Minimum step size reached", near the valley floor's minimum (from f = 24.2).
    x, value, step = minimise(name, rosenbrock(), [-1.2, 1.0], 10000)
    assert step.stop_reason == "Minimum step size reached"
    np.testing.assert_allclose(x, [1.0, 1.0], atol=atol)
    assert value < 1e-3


@pytest.mark.parametrize("name", NEW)
def test_linear_network_reaches_least_squares(name):
    meas, ref = linear_problem()
    model = MLP("pos", (), "purelin", name, epochs=400, validation_fraction=0.0, min_grad=0).fit(meas, ref)
    want = lstsq_prediction(meas, ref, meas)
    got = model.predict(meas)[:, :3]
    best_mse = np.mean((want - ref[:, :3]) ** 2)
    assert np.mean((got - ref[:, :3]) ** 2) <= best_mse * (1 + 1e-3)
    # within 10 % of the noise sigma (1e-4 m) of the exact least-squares prediction
    assert np.max(np.abs(got - want)) < 1e-5
    assert np.all(np.diff(model.history_["mse"]) <= 1e-15)  # every epoch descends
