"""The generic forms (posecorr.forms) against direct per-pose evaluations of their formulas,
their inverses, torch, and the exported graph on onnxruntime and the C runtime.

The references below are written from the table in the module's docstring (per-pose loops,
scipy's Rotation for Exp), not from posecorr's helpers."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from posecorr import effects as fx
from posecorr.effects import EffectContext, get_effect
from posecorr.forms import TIME_SCALE_S

N = 40   # the poses of conftest.workspace_poses
FORMS = ("strain", "quadratic", "orientation_field", "orientation_bias", "time_trend", "sweep_harmonics")
THETA = {
    "strain": np.array([0.012, -0.008, 0.004, 0.006, -0.005, 0.003]),
    "quadratic": np.linspace(-0.03, 0.03, 18),
    "orientation_field": np.array([0.02, -0.01, 0.005, 0.0, 0.015, -0.02, 0.01, 0.0, -0.01]),
    "orientation_bias": np.array([3e-3, -1e-3, 0.0, 2e-3, 1e-3, -2e-3, 0.0, 1e-3, 2e-3]),
    "time_trend": np.array([2e-3, -1e-3, 5e-4, -5e-4, 1e-3, 2e-4]),
    "sweep_harmonics": np.array([2e-3, -1e-3, 1e-3, 5e-4, -1e-3, 2e-3, -5e-4, 1e-3]),
}


@pytest.fixture(scope="module")
def ctx() -> EffectContext:
    rng = np.random.default_rng(11)
    return EffectContext.default(t=rng.uniform(0.0, 3000.0, N))


def ref_strain(p, R, th, ctx):
    xx, yy, zz, xy, xz, yz = th
    S = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    return np.array([pi + S @ (pi - ctx.c) for pi in p]), R


def ref_quadratic(p, R, th, ctx):
    Q = th.reshape(3, 6)
    out = []
    for pi in p:
        x, y, z = pi - ctx.c
        out.append(pi + Q @ np.array([x * x, y * y, z * z, x * y, x * z, y * z]))
    return np.array(out), R


def ref_orientation_field(p, R, th, ctx):
    G = th.reshape(3, 3)
    return p, np.array([Rotation.from_rotvec(G @ (pi - ctx.c)).as_matrix() @ Ri for pi, Ri in zip(p, R)])


def ref_orientation_bias(p, R, th, ctx):
    K = th.reshape(3, 3)
    return np.array([pi + K @ Ri[:, 2] for pi, Ri in zip(p, R)]), R


def ref_time_trend(p, R, th, ctx):
    s = ctx.t / TIME_SCALE_S
    return p + np.outer(s, th[:3]) + np.outer(s * s, th[3:]), R


def ref_sweep_harmonics(p, R, th, ctx):
    def h(angle, c):
        return c[0] * np.cos(angle) + c[1] * np.sin(angle) + c[2] * np.cos(2 * angle) + c[3] * np.sin(2 * angle)

    out = []
    for pi in p:
        s = ctx.R_S.T @ (pi - ctx.t_S)
        alpha, beta, r = np.arctan2(s[0], -s[2]), np.arctan2(s[1], -s[2]), np.linalg.norm(s)
        v = np.array([np.tan(alpha + h(alpha, th[:4])), np.tan(beta + h(beta, th[4:])), -1.0])
        out.append(ctx.t_S + ctx.R_S @ (r * v / np.linalg.norm(v)))
    return np.array(out), R


REFERENCES = {name: globals()[f"ref_{name}"] for name in FORMS}


def test_forms_are_registered_beside_the_catalogue():
    assert set(fx.FORM_NAMES) == set(FORMS)
    for name in FORMS:
        effect = get_effect(name)
        assert effect.generic and effect.causes and effect.size == THETA[name].size
        assert np.allclose(effect.forward(*_poses(), effect.identity_theta(), _ctx())[0], _poses()[0])
        with pytest.raises(ValueError, match="built in"):
            fx.unregister_effect(name)
    assert not any(get_effect(name).generic for name in fx.BUILTIN_NAMES)


def _ctx():
    return EffectContext.default(t=np.linspace(0, 100, N))


def _poses():
    rng = np.random.default_rng(1)
    return np.array([0.0, -0.6, 0.5]) + rng.uniform(-0.2, 0.2, (N, 3)), np.tile(np.eye(3), (N, 1, 1))


@pytest.mark.parametrize("name", FORMS)
def test_forward_matches_the_formula(name, workspace_poses, ctx):
    p, R = workspace_poses
    got_p, got_R = get_effect(name).forward(p, R, THETA[name], ctx)
    want_p, want_R = REFERENCES[name](p, R, THETA[name], ctx)
    assert np.abs(got_p - want_p).max() < 1e-12
    assert np.abs(got_R - want_R).max() < 1e-12


@pytest.mark.parametrize("name", FORMS)
def test_inverse_of_forward(name, workspace_poses, ctx):
    effect = get_effect(name)
    p, R = workspace_poses
    fp, fR = effect.forward(p, R, THETA[name], ctx)
    bp, bR = effect.inverse(fp, fR, THETA[name], ctx)
    assert np.abs(bp - p).max() < 1e-9
    assert np.abs(bR - R).max() < 1e-9


@pytest.mark.parametrize("name", FORMS)
def test_per_row_theta_and_torch_agree_with_numpy(name, workspace_poses, ctx):
    effect = get_effect(name)
    p, R = workspace_poses
    want_p, want_R = effect.forward(p, R, THETA[name], ctx)
    rows_p, rows_R = effect.forward(p, R, np.tile(THETA[name], (N, 1)), ctx)
    assert np.abs(rows_p - want_p).max() < 1e-15 and np.abs(rows_R - want_R).max() < 1e-15
    tp, tR = effect.forward(torch.tensor(p), torch.tensor(R), torch.tensor(THETA[name]), ctx)
    assert np.abs(tp.numpy() - want_p).max() < 1e-12 and np.abs(tR.numpy() - want_R).max() < 1e-12


@pytest.mark.parametrize("name", FORMS)
def test_a_fitted_form_exports_and_runs_alike_on_every_back_end(name, tmp_path):
    """Simulated with the form, fitted with station, mount and the form: the ONNX graph on
    onnxruntime and on the C runtime gives the numpy model's correction."""
    from posecorr.controller.runtime import Corrector
    from posecorr.export.onnx_export import to_onnx
    from posecorr.simulate import simulate_session
    from posecorr.train.physics import PhysicsModel

    session = simulate_session(3, n=40, robot="ur5e", extra={name: THETA[name] / 2})
    table = session.table
    t = np.linspace(0.0, 2000.0, table.n)
    model = PhysicsModel(("station", "mount", name)).fit(table.measured, table.reference, t=t)
    # parity "raise" (the default): the export refuses a graph that departs from the model.
    to_onnx(model, tmp_path / "m.onnx", measured=table.measured, reference=table.reference, t=t)
    want = model.predict(table.measured, t)
    for backend in ("c", "onnxruntime"):
        got = Corrector(tmp_path / "m.onnx", backend=backend).correct(table.measured, t=t)
        assert np.abs(got[:, :3] - want[:, :3]).max() < 2e-5, backend
        assert np.abs(np.abs(np.sum(got[:, 3:] * want[:, 3:], axis=1)) - 1).max() < 1e-6, backend


# Each form cut to a few of its terms: (the terms kept, the full theta they come from).
CUTS = {name: sorted({0, len(THETA[name]) - 1, len(THETA[name]) // 2}) for name in FORMS}


def _cut(name):
    whole = get_effect(name)
    terms = CUTS[name]
    return whole, type(whole).keeping(terms, f"cut_{name}", np.asarray(THETA[name])[terms])()


@pytest.mark.parametrize("name", FORMS)
def test_a_cut_form_is_the_whole_form_with_the_other_terms_at_zero(name, workspace_poses, ctx):
    """The formula (written per pose above) with every coefficient outside the cut zeroed,
    on numpy, per-row theta and torch."""
    p, R = workspace_poses
    whole, cut = _cut(name)
    theta = np.asarray(THETA[name])
    zeroed = np.zeros_like(theta)
    zeroed[CUTS[name]] = theta[CUTS[name]]
    want_p, want_R = REFERENCES[name](p, R, zeroed, ctx)
    got_p, got_R = cut.forward(p, R, cut.default_theta(), ctx)
    assert np.abs(got_p - want_p).max() < 1e-12 and np.abs(got_R - want_R).max() < 1e-12
    rows_p, _ = cut.forward(p, R, np.tile(cut.default_theta(), (N, 1)), ctx)
    assert np.abs(rows_p - want_p).max() < 1e-15
    tp, _ = cut.forward(torch.tensor(p), torch.tensor(R), torch.tensor(cut.default_theta()), ctx)
    assert np.abs(tp.numpy() - want_p).max() < 1e-12
    assert cut.term_labels() == [whole.labels[t] for t in CUTS[name]] and cut.size == len(CUTS[name])


def test_a_cut_names_its_terms_or_is_refused():
    from posecorr.forms import Quadratic

    with pytest.raises(ValueError, match="terms must be 2 distinct indices of its 18"):
        Quadratic.keeping([3, 3], "twice")()
    with pytest.raises(ValueError, match="terms must be 1 distinct indices of its 18"):
        Quadratic.keeping([18], "beyond")()


def test_a_fitted_cut_form_exports_and_runs_alike_on_every_back_end(tmp_path):
    """The proposal's effect (a form cut to its terms) is a user effect like any other."""
    from posecorr.controller.runtime import Corrector
    from posecorr.effects import register_effect, unregister_effect
    from posecorr.export.onnx_export import to_onnx
    from posecorr.simulate import simulate_session
    from posecorr.train.physics import PhysicsModel

    whole, cut = _cut("quadratic")
    register_effect(type(cut), source="test")
    try:
        table = simulate_session(3, n=40, robot="ur5e", extra={"quadratic": THETA["quadratic"] / 2}).table
        model = PhysicsModel(("station", "mount", cut.name)).fit(table.measured, table.reference)
        to_onnx(model, tmp_path / "m.onnx", measured=table.measured, reference=table.reference)
        want = model.predict(table.measured)
        for backend in ("c", "onnxruntime"):
            got = Corrector(tmp_path / "m.onnx", backend=backend).correct(table.measured)
            assert np.abs(got[:, :3] - want[:, :3]).max() < 2e-5, backend
    finally:
        unregister_effect(cut.name)
