"""Registries: a representation, an activation and a trainer added by registering them alone
work end to end."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr import rotations
from posecorr._xp import namespace


def _matrix_to_mrp(R):
    """Modified Rodrigues parameters q_xyz / (1 + q_w) (q_w >= 0 from matrix_to_quat)."""
    q = rotations.matrix_to_quat(R)
    return q[..., 1:4] / (1.0 + q[..., 0:1])


def _mrp_to_matrix(p):
    xp = namespace(p)
    n2 = xp.sum(p * p, axis=-1, keepdims=True)
    q = xp.concat([1.0 - n2, 2.0 * p], axis=-1) / (1.0 + n2)
    return rotations.quat_to_matrix(q)


@pytest.fixture
def mrp():
    rotations.register_representation("mrp", rotations.Representation(3, _matrix_to_mrp, _mrp_to_matrix))
    yield "mrp"
    del rotations.REPRESENTATIONS["mrp"]


def test_registered_representation_round_trips_against_scipy(mrp: str) -> None:
    R = Rotation.random(1000, random_state=0)
    params = rotations.encode(R.as_matrix(), mrp)
    assert np.allclose(params, R.as_mrp(), atol=1e-12)       # scipy's shortest MRP: q_w >= 0 too
    assert np.allclose(rotations.decode(params, mrp), R.as_matrix(), atol=1e-12)


def test_registered_representation_fits_and_exports(mrp: str, tmp_path) -> None:
    """PMC on the new representation fits a simulated experiment and exports a graph that
    onnxruntime runs like predict: nothing but the registration was added."""
    from posecorr.export.parity import quat_angle, run_onnx
    from posecorr.simulate import simulate
    from posecorr.train import PMC

    table = simulate(3, seed=0).table.subset(np.arange(600))
    model = PMC(representation=mrp).fit(table.measured, table.reference)
    predicted = model.predict(table.measured)
    raw_rot = rotations.geodesic_angle(rotations.quat_to_matrix(table.measured[:, 3:7]),
                                       rotations.quat_to_matrix(table.reference[:, 3:7]))
    fit_rot = rotations.geodesic_angle(rotations.quat_to_matrix(predicted[:, 3:7]),
                                       rotations.quat_to_matrix(table.reference[:, 3:7]))
    assert np.sqrt(np.mean(fit_rot ** 2)) < 0.1 * np.sqrt(np.mean(raw_rot ** 2))
    model.to_onnx(tmp_path / "mrp.onnx", measured=table.measured, reference=table.reference)
    onnx_out = run_onnx(str(tmp_path / "mrp.onnx"), table.measured)
    assert np.allclose(onnx_out[:, :3], predicted[:, :3], atol=1e-5)
    # float32 graph: measured 7.8e-7 rad at most; 1e-5 as test_export's assert_parity
    assert np.max(quat_angle(onnx_out[:, 3:], predicted[:, 3:])) < 1e-5


def test_unknown_representation_is_refused_not_decoded_as_another() -> None:
    with pytest.raises(ValueError, match="unknown representation 'zhuo'"):
        rotations.decode(np.zeros((1, 6)), "zhuo")


# --- activations ---------------------------------------------------------------------------

def _elliotsig(n):
    """MATLAB's elliotsig, n / (1 + |n|): not one of the paper's eight."""
    return n / (1.0 + namespace(n).abs(n))


@pytest.fixture
def elliotsig():
    from posecorr.train.activations import ACTIVATIONS, Activation, register_activation

    register_activation(Activation("elliotsig", _elliotsig, lambda z, a: 1.0 / (1.0 + z.abs()) ** 2, None,
                                   (-1.0, 1.0)))
    yield "elliotsig"
    del ACTIVATIONS["elliotsig"]


def test_registered_activation_is_a_cli_choice_and_no_paper_preset(elliotsig: str) -> None:
    from posecorr.cli import build_parser
    from posecorr.train.protocol import GRID_PRESETS

    assert main_choices(build_parser(), "fit", "--activation") >= {"tansig", elliotsig}
    assert elliotsig not in GRID_PRESETS["paper-exp1"]["activations"]


def main_choices(parser, verb: str, option: str) -> set[str]:
    sub = next(a for a in parser._actions if a.dest == "verb").choices[verb]
    return set(next(a for a in sub._actions if option in a.option_strings).choices)


def test_registered_activation_gauss_newton_matches_autograd(elliotsig: str) -> None:
    """The registered derivative feeds the Levenberg-Marquardt J^T J and J^T r: they equal the
    products of torch's autograd Jacobian through the registered forward."""
    import torch

    from posecorr.train.lm import Network

    rng = np.random.default_rng(0)
    net = Network([4, 6, 5, 3], elliotsig, np.array([1.0, 2.0, 0.5]))
    theta = torch.as_tensor(rng.normal(size=net.n_params))
    X, T = torch.as_tensor(rng.normal(size=(20, 4))), torch.as_tensor(rng.normal(size=(20, 3)))
    JJ, g, r = net.gauss_newton(theta, X, T)
    J = net.jacobian(theta, X, T)
    assert torch.allclose(JJ, J.T @ J, atol=1e-10)
    assert torch.allclose(g, J.T @ r.reshape(-1), atol=1e-10)


@pytest.mark.parametrize("trainer", ["lm", "adam"])
def test_registered_activation_trains_and_exports(elliotsig: str, trainer: str, tmp_path) -> None:
    """An MLP with the new activation trains (the error falls), predicts what an independent
    numpy network with its weights computes, and exports a graph onnxruntime runs like predict."""
    from posecorr.export.parity import run_onnx
    from posecorr.simulate import simulate
    from posecorr.train import MLP

    table = simulate(1, seed=0).table.subset(np.arange(400))
    M, R = table.measured, table.reference
    model = MLP("pos", hidden=(6,), activation=elliotsig, trainer=trainer, epochs=60, lr=0.01,
                validation_fraction=0.0).fit(M, R)
    assert model.history_["mse"][-1] < 0.5 * model.history_["mse"][0]
    # independent forward: mapminmax, W x + b, n / (1 + |n|), linear, reverse mapminmax
    h = M[:, :3] * model.x_gain_ + model.x_offset_
    h = h @ model.coefs_[0] + model.intercepts_[0]
    h = h / (1.0 + np.abs(h))
    y = (h @ model.coefs_[1] + model.intercepts_[1] - model.y_offset_) / model.y_gain_
    predicted = model.predict(M)
    assert np.allclose(predicted[:, :3], y, atol=1e-12)
    model.to_onnx(tmp_path / "elliot.onnx", measured=M, reference=R)
    assert np.allclose(run_onnx(str(tmp_path / "elliot.onnx"), M)[:, :3], predicted[:, :3], atol=1e-5)


@pytest.fixture
def signed_gd():
    """A trainer registered here alone: x -= lr sign(g) ("signed gradient descent", not one
    of table 1's twelve)."""
    from posecorr.train.trainers import TRAINERS, Step, register

    @register("signgd", "(none)", None, "Signed gradient descent (this test)")
    class SignGD(Step):
        def __call__(self, epoch, theta, mse, g):
            return self.moved(theta - self.lr * g.sign())

    yield "signgd"
    del TRAINERS["signgd"]


def test_registered_trainer_trains_and_is_a_cli_choice(signed_gd: str) -> None:
    """The registered step runs in the shared loop: every epoch moves each weight by exactly
    lr (an independent check of the step it ran), the error falls, and the CLI offers it;
    registering the name twice is refused."""
    import argparse

    from posecorr.cli import build_parser
    from posecorr.simulate import simulate
    from posecorr.train import MLP
    from posecorr.train.trainers import register

    table = simulate(1, seed=0).table.subset(np.arange(300))
    M, R = table.measured, table.reference
    kwargs = dict(hidden=(5,), activation="tansig", epochs=1, lr=1e-3, validation_fraction=0.0,
                  random_state=3)
    start = MLP("pos", trainer=signed_gd, **{**kwargs, "epochs": 0}).fit(M, R)
    one = MLP("pos", trainer=signed_gd, **kwargs).fit(M, R)
    moved = np.concatenate([(a - b).ravel() for a, b in zip(one.coefs_ + one.intercepts_,
                                                            start.coefs_ + start.intercepts_)])
    assert np.allclose(np.abs(moved), 1e-3, rtol=1e-9)
    longer = MLP("pos", trainer=signed_gd, **{**kwargs, "epochs": 40}).fit(M, R)
    assert longer.history_["mse"][-1] < longer.history_["mse"][0]
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    trainer_options = [a for p in sub.choices.values() for a in p._actions if a.dest == "trainer"]
    assert trainer_options and all(signed_gd in a.choices for a in trainer_options)
    with pytest.raises(ValueError, match="trainer 'signgd' is already registered"):
        register("signgd", "(none)", None, "again")(lambda *a: None)


def test_cli_preset_choices_are_the_grid_presets():
    """The sweep's --preset choices are written out in cli/sweep.py (reading GRID_PRESETS there
    would load scikit-learn for every verb); this keeps the two from drifting apart."""
    import argparse

    from posecorr.cli import build_parser
    from posecorr.train.protocol import GRID_PRESETS

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    preset = next(a for a in sub.choices["sweep"]._actions if a.dest == "preset")
    assert set(preset.choices) == set(GRID_PRESETS)
