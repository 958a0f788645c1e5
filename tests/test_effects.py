"""The effect catalogue against direct numpy evaluations of docs/design.md's formulas.

The reference implementations below are written from the docs/design.md table alone (per-pose
loops, scipy's Rotation for Exp), not from posecorr's helpers.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from posecorr import effects as fx
from posecorr.effects import EffectContext, get_effect, parse_effects_arg

DATA = Path(__file__).parent / "data"
N = 40   # the poses of conftest.workspace_poses
INVERTIBLE = ("mount", "sweep", "range_scale", "incidence", "drift", "station")


def Exp(w: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(w).as_matrix()


@pytest.fixture(scope="module")
def ctx() -> EffectContext:
    rng = np.random.default_rng(11)
    return EffectContext.default(t=rng.uniform(0.0, 30000.0, N))


# Realistic but clearly non-zero parameters, a few times the default magnitudes.
THETA = {
    "mount": np.array([4e-3, -6e-3, 30e-3, 3e-3, -2e-3, 5e-3]),
    "sweep": np.array([2e-3, -1.5e-3, 0.05, -0.04]),
    "range_scale": np.array([0.008]),
    "incidence": np.array([2e-3, -1.5e-3]),
    "drift": np.array([2e-3, -1e-3, 1.5e-3, 4000.0]),
    "station": np.array([5e-3, -4e-3, 20e-3, -0.03, 0.02, 0.015]),
    "noise": np.array([3e-4, 5e-4, 2e-4]),
}


# --- direct evaluations of the docs/design.md table ------------------------------------

def ref_mount(p, R, th, ctx):
    d, e = th[:3], th[3:]
    return np.array([pi + Ri @ e for pi, Ri in zip(p, R)]), np.array([Ri @ Exp(d) for Ri in R])


def ref_sweep(p, R, th, ctx):
    px, py, cx, cy = th
    out = []
    for pi in p:
        s = ctx.R_S.T @ (pi - ctx.t_S)
        alpha, beta, r = np.arctan2(s[0], -s[2]), np.arctan2(s[1], -s[2]), np.linalg.norm(s)
        a2, b2 = alpha + px + cx * beta ** 2, beta + py + cy * alpha ** 2
        v = np.array([np.tan(a2), np.tan(b2), -1.0])
        out.append(ctx.t_S + ctx.R_S @ (r * v / np.linalg.norm(v)))
    return np.array(out), R


def ref_range_scale(p, R, th, ctx):
    return ctx.t_S + (1 + th[0]) * (p - ctx.t_S), R


def ref_incidence(p, R, th, ctx):
    b1, b2 = th
    out = []
    for pi, Ri in zip(p, R):
        u = (pi - ctx.t_S) / np.linalg.norm(pi - ctx.t_S)
        a = Ri[:, 2]
        cos_th = -a @ u
        perp = a - (a @ u) * u
        e = perp / np.linalg.norm(perp) if np.linalg.norm(perp) > 1e-12 else np.zeros(3)
        sin_th = np.sqrt(max(0.0, 1 - cos_th ** 2))
        out.append(pi + b1 * (1 - cos_th) * u + b2 * sin_th * e)
    return np.array(out), R


def ref_drift(p, R, th, ctx):
    return p + np.outer(1 - np.exp(-ctx.t / th[3]), th[:3]), R


def ref_station(p, R, th, ctx):
    W = Exp(th[:3])
    return np.array([ctx.c + W @ (pi - ctx.c) + th[3:] for pi in p]), np.array([W @ Ri for Ri in R])


REFERENCES = {"mount": ref_mount, "sweep": ref_sweep, "range_scale": ref_range_scale,
              "incidence": ref_incidence, "drift": ref_drift, "station": ref_station}


# --- catalogue ----------------------------------------------------------------------------

def test_catalogue_names_order_and_sizes():
    assert fx.BUILTIN_NAMES == ("mount", "sweep", "range_scale", "incidence", "drift", "station", "noise")
    assert [n for n in fx.EFFECTS if n in fx.BUILTIN_NAMES] == list(fx.BUILTIN_NAMES)
    sizes = {name: get_effect(name).size for name in fx.BUILTIN_NAMES}
    assert sizes == {"mount": 6, "sweep": 4, "range_scale": 1, "incidence": 2, "drift": 4, "station": 6, "noise": 3}
    assert get_effect("mount").param_names == ["d", "e"]
    assert get_effect("sweep").param_names == ["phase_x", "phase_y", "curve_x", "curve_y"]
    assert get_effect("noise").random and not get_effect("station").random
    for name in fx.BUILTIN_NAMES:
        e = get_effect(name)
        assert e.default_theta().shape == e.scales().shape == (e.size,)
        assert np.all(e.scales() > 0)


@pytest.mark.parametrize("name", list(REFERENCES))
def test_forward_matches_design_formula(name, workspace_poses, ctx):
    p, R = workspace_poses
    got_p, got_R = get_effect(name).forward(p, R, THETA[name], ctx)
    want_p, want_R = REFERENCES[name](p, R, THETA[name], ctx)
    np.testing.assert_allclose(got_p, want_p, rtol=0, atol=1e-13)
    np.testing.assert_allclose(got_R, want_R, rtol=0, atol=1e-13)
    assert np.max(np.linalg.norm(got_p - p, axis=1)) > 1e-4  # the effect did something


def test_incidence_degenerate_and_head_on(ctx):
    """Tracker z axis facing the station: no bias; facing away (a = u): 2 b1 along u, no e term."""
    p = np.array([[0.1, -0.5, 0.4], [0.0, -0.7, 0.6]])
    u = (p - ctx.t_S) / np.linalg.norm(p - ctx.t_S, axis=1, keepdims=True)

    def frame(z):  # any rotation whose third column is z
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        return np.stack([x, np.cross(z, x), z], axis=1)

    b = np.array([2e-3, 3e-3])
    facing = np.stack([frame(-ui) for ui in u])
    away = np.stack([frame(ui) for ui in u])
    np.testing.assert_allclose(get_effect("incidence").forward(p, facing, b, ctx)[0], p, atol=1e-15)
    np.testing.assert_allclose(get_effect("incidence").forward(p, away, b, ctx)[0], p + 2 * b[0] * u, atol=1e-15)
    np.testing.assert_allclose(get_effect("incidence").forward(p, away, b, ctx)[0],
                               ref_incidence(p, away, b, ctx)[0], atol=1e-15)


def test_noise_with_given_draws(workspace_poses, ctx):
    p, R = workspace_poses
    rng = np.random.default_rng(3)
    draws = fx.Noise.draw(rng, N)
    c = EffectContext(ctx.R_S, ctx.t_S, ctx.c, noise_draws=draws)
    sp, sr, k2 = THETA["noise"]
    got_p, got_R = get_effect("noise").forward(p, R, THETA["noise"], c)
    d = p - ctx.t_S
    r = np.linalg.norm(d, axis=1, keepdims=True)
    want_p = p + sp * draws["p"] + k2 * r ** 2 * draws["r"] * d / r
    want_R = np.array([Ri @ Exp(sr * wi) for Ri, wi in zip(R, draws["w"])])
    np.testing.assert_allclose(got_p, want_p, atol=1e-15)
    np.testing.assert_allclose(got_R, want_R, atol=1e-14)
    with pytest.raises(TypeError, match="no inverse"):
        get_effect("noise").inverse(p, R, THETA["noise"], c)


def test_noise_statistics(ctx):
    """sigma_p per axis, sigma_r per axis of the rotation vector, k2 r^2 along the line of sight."""
    n = 20000
    p = np.tile([0.0, -0.6, 0.5], (n, 1))
    R = np.tile(np.eye(3), (n, 1, 1))
    c = EffectContext(ctx.R_S, ctx.t_S, ctx.c, rng=np.random.default_rng(0))
    sp, sr, k2 = 3e-4, 5e-4, 2e-3
    q, Q = get_effect("noise").forward(p, R, [sp, sr, 0.0], c)
    assert np.std(q - p, axis=0) == pytest.approx([sp] * 3, rel=0.03)
    assert np.std(Rotation.from_matrix(Q).as_rotvec(), axis=0) == pytest.approx([sr] * 3, rel=0.03)
    q, _ = get_effect("noise").forward(p, R, [0.0, 0.0, k2], c)
    u = (p[0] - ctx.t_S) / np.linalg.norm(p[0] - ctx.t_S)
    along = (q - p) @ u
    assert np.std(along) == pytest.approx(k2 * np.sum((p[0] - ctx.t_S) ** 2), rel=0.03)
    assert np.allclose(q - p, np.outer(along, u), atol=1e-15)


@pytest.mark.parametrize("name", fx.BUILTIN_NAMES)
def test_identity_parameters(name, workspace_poses, ctx):
    p, R = workspace_poses
    e = get_effect(name)
    c = EffectContext(ctx.R_S, ctx.t_S, ctx.c, t=ctx.t, rng=np.random.default_rng(0))
    q, Q = e.forward(p, R, e.identity_theta(), c)
    np.testing.assert_allclose(q, p, atol=1e-15)
    np.testing.assert_allclose(Q, R, atol=1e-15)


@pytest.mark.parametrize("name", INVERTIBLE)
def test_inverse_of_forward(name, workspace_poses, ctx):
    p, R = workspace_poses
    e = get_effect(name)
    q, Q = e.forward(p, R, THETA[name], ctx)
    p2, R2 = e.inverse(q, Q, THETA[name], ctx)
    np.testing.assert_allclose(p2, p, rtol=0, atol=1e-12)
    np.testing.assert_allclose(R2, R, rtol=0, atol=1e-12)


def test_chain_inverse_and_order(workspace_poses, ctx):
    p, R = workspace_poses
    mix = {name: THETA[name] for name in reversed(INVERTIBLE)}   # given in any order
    q, Q = fx.apply_effects(p, R, mix, ctx)
    # The chain applies mount first ... station last.
    want_p, want_R = p, R
    for name in INVERTIBLE:
        want_p, want_R = REFERENCES[name](want_p, want_R, THETA[name], ctx)
    np.testing.assert_allclose(q, want_p, atol=1e-13)
    np.testing.assert_allclose(Q, want_R, atol=1e-13)
    p2, R2 = fx.invert_effects(q, Q, mix, ctx)
    np.testing.assert_allclose(p2, p, atol=1e-12)
    np.testing.assert_allclose(R2, R, atol=1e-12)


def test_drift_without_time_is_identity_and_says_so(workspace_poses, ctx):
    p, R = workspace_poses
    c = EffectContext(ctx.R_S, ctx.t_S, ctx.c)
    assert get_effect("drift").notes(c) and not get_effect("drift").notes(ctx)
    with pytest.warns(UserWarning, match="no time column"):
        q, _ = get_effect("drift").forward(p, R, THETA["drift"], c)
    np.testing.assert_array_equal(q, p)


# --- torch: agreement and gradients ---------------------------------------------------------

@pytest.mark.parametrize("name", INVERTIBLE)
def test_torch_matches_numpy(name, workspace_poses, ctx):
    p, R = workspace_poses
    e = get_effect(name)
    tp, tR, tth = (torch.tensor(x, dtype=torch.float64) for x in (p, R, THETA[name]))
    for method in (e.forward, e.inverse):
        np_p, np_R = method(p, R, THETA[name], ctx)
        t_p, t_R = method(tp, tR, tth, ctx)
        assert isinstance(t_p, torch.Tensor) and isinstance(t_R, torch.Tensor)
        np.testing.assert_allclose(t_p.numpy(), np_p, rtol=0, atol=1e-12)
        np.testing.assert_allclose(t_R.numpy(), np_R, rtol=0, atol=1e-12)
    # torch theta with numpy poses (a fit's typical call) also works
    t_p, _ = e.forward(p, R, tth, ctx)
    np.testing.assert_allclose(t_p.numpy(), e.forward(p, R, THETA[name], ctx)[0], atol=1e-12)


@pytest.mark.parametrize("name", INVERTIBLE + ("noise",))
def test_torch_gradients_match_finite_differences(name, workspace_poses, ctx):
    p, R = workspace_poses
    e = get_effect(name)
    c = ctx.subset(np.arange(6))
    c.noise_draws = fx.Noise.draw(np.random.default_rng(1), 6)
    tp = torch.tensor(p[:6], dtype=torch.float64, requires_grad=True)
    tR = torch.tensor(R[:6], dtype=torch.float64)
    th = torch.tensor(THETA[name], dtype=torch.float64, requires_grad=True)

    def f(theta, pos):
        q, Q = e.forward(pos, tR, theta, c)
        return q, Q

    assert torch.autograd.gradcheck(f, (th, tp), eps=1e-7, atol=1e-6, rtol=1e-5)
    if not e.random:
        assert torch.autograd.gradcheck(lambda theta, pos: e.inverse(pos, tR, theta, c), (th, tp),
                                        eps=1e-7, atol=1e-6, rtol=1e-5)


# --- the CLI syntax -----------------------------------------------------------------------

def test_parse_effects_arg():
    out = parse_effects_arg(" mount=1e-3,2e-3,3e-3,0.001,0.002,0.003 ; range_scale=0.01;sweep; noise=off")
    assert list(out) == ["mount", "range_scale", "sweep", "noise"]
    np.testing.assert_array_equal(out["mount"], [1e-3, 2e-3, 3e-3, 1e-3, 2e-3, 3e-3])
    np.testing.assert_array_equal(out["range_scale"], [0.01])
    np.testing.assert_array_equal(out["sweep"], get_effect("sweep").default_theta())
    assert out["noise"] is None
    assert parse_effects_arg("") == {}


def test_bare_effect_names_may_be_separated_by_commas():
    """An item without '=' has no values, so its ',' can only separate names; with values the
    ';' is needed, and the error says why."""
    out = parse_effects_arg("sweep,range_scale;drift=0.002,-0.001,0.0015,1800")
    assert list(out) == ["sweep", "range_scale", "drift"]
    np.testing.assert_array_equal(out["drift"], [0.002, -0.001, 0.0015, 1800])


@pytest.mark.parametrize("text, pattern", [
    ("bogus=1", r"unknown effect 'bogus'.*mount.*station"),
    ("mout", r"^unknown effect 'mout' \(did you mean mount\?\); expected one of mount, "),
    ("sweep,range_scale=0.01", r"^unknown effect 'sweep,range_scale': separate effects with ';', as values take ','"),
    ("mount=1,2", r"'mount' takes 6 values \(d\[3\] rad, e\[3\] m\), got 2"),
    ("range_scale=0.1,0.2", r"'range_scale' takes 1 values \(k 1\), got 2"),
    ("sweep=a,b,c,d", r"'sweep': expected 4 numbers"),
    ("station=0,0,0,0,0,nan", r"'station': parameters must be finite"),
    ("drift=0,0,0,0", r"tau must be > 0"),
    ("noise=-1,0,0", r"must be >= 0"),
    ("range_scale=0.1;range_scale=0.2", r"given twice"),
    ("sweep;;range_scale", r"^an effect name is empty in 'sweep;;range_scale'"),
    ("sweep,", r"^an effect name is empty in 'sweep,'"),
])
def test_parse_effects_arg_errors(text, pattern):
    with pytest.raises(ValueError, match=pattern):
        parse_effects_arg(text)


# --- user effects -------------------------------------------------------------------------

@pytest.fixture()
def user_effect():
    yield fx.load_effect_file(DATA / "example_effect.py")
    fx.unregister_effect("z_scale")
    with pytest.raises(ValueError, match="built in"):
        fx.unregister_effect("mount")


def test_user_effect_file(user_effect, workspace_poses, ctx):
    names = user_effect
    assert names == ["z_scale"]
    assert fx.load_effect_file(DATA / "example_effect.py") == ["z_scale"]   # idempotent
    e = get_effect("z_scale")
    names = list(fx.EFFECTS)
    assert isinstance(e, fx.Effect) and names.index("drift") < names.index("z_scale") < names.index("station")
    assert [x.order for x in fx.EFFECTS.values()] == sorted(x.order for x in fx.EFFECTS.values())
    p, R = workspace_poses
    q, Q = e.forward(p, R, np.array([0.02]), ctx)
    np.testing.assert_allclose(q[:, 2], p[:, 2] + 0.02 * (p[:, 2] - ctx.c[2]), atol=1e-15)
    np.testing.assert_array_equal(q[:, :2], p[:, :2])
    p2, _ = e.inverse(q, Q, np.array([0.02]), ctx)          # generic fixed-point inverse
    np.testing.assert_allclose(p2, p, atol=1e-12)
    assert list(parse_effects_arg("z_scale=0.03;station")) == ["z_scale", "station"]
    with pytest.raises(ValueError, match="'z_scale' takes 1 values"):
        parse_effects_arg("z_scale=1,2")
    # through the chain with torch parameters and numpy poses
    th = torch.tensor([0.02], dtype=torch.float64, requires_grad=True)
    tq, _ = fx.apply_effects(p, R, {"z_scale": th}, ctx)
    tq[:, 2].sum().backward()
    assert th.grad.item() == pytest.approx(np.sum(p[:, 2] - ctx.c[2]), rel=1e-12)


TURN_WITH_X = """
from posecorr.effects import Effect, Param, to_namespace


class TurnWithX(Effect):
    name = "turn_with_x"
    changes_rotation = True
    params = (Param("a", 1, (0.05,), 1e-2, "rad/m"),)

    def forward(self, p, R, theta, ctx):
        xp, p, R, theta = to_namespace(p, R, theta)
        angle = (theta[..., 0:1] * (p[..., 0:1] - xp.const(ctx.c, p)[..., 0:1]))[..., 0]
        c, s = xp.cos(angle), xp.sin(angle)
        z = c * 0.0
        turn = xp.stack([xp.stack([c, -s, z], axis=-1), xp.stack([s, c, z], axis=-1),
                         xp.stack([z, z, z + 1.0], axis=-1)], axis=-2)
        return p, xp.matmul(turn, R)
"""


def test_generic_inverse_of_a_user_rotation_stays_a_rotation_in_float32(tmp_path, workspace_poses, ctx):
    """The fixed-point inverse's residual holds x^T x, which doubled x's departure from
    orthogonality at every step (6 float32 steps: 1.6e-5), and the export of a user rotation
    effect failed its parity check; in float32, as the graph runs, the inverse is a rotation
    and undoes the turn (scipy's angles) to float32's rounding."""
    path = tmp_path / "turn_with_x.py"
    path.write_text(TURN_WITH_X)
    fx.load_effect_file(path)
    try:
        e = get_effect("turn_with_x")
        p, R = workspace_poses
        theta = np.array([0.2])
        q, Q = e.forward(p, R, theta, ctx)
        back_p, back_R = e.inverse(*(torch.tensor(a, dtype=torch.float32) for a in (q, Q, theta)), ctx)
        back_R = back_R.double().numpy()
        assert np.abs(np.swapaxes(back_R, 1, 2) @ back_R - np.eye(3)).max() < 2e-6
        assert (Rotation.from_matrix(R).inv() * Rotation.from_matrix(back_R)).magnitude().max() < 2e-6
        np.testing.assert_allclose(back_p.double().numpy(), p, atol=1e-6)
    finally:
        fx.unregister_effect("turn_with_x")


def test_user_effect_file_errors(tmp_path):
    bad = tmp_path / "clash.py"
    bad.write_text("from posecorr.effects import Effect\nclass M(Effect):\n    name = 'mount'\n")
    with pytest.raises(ValueError, match="'mount' is already defined by the built-in catalogue"):
        fx.load_effect_file(bad)
    empty = tmp_path / "empty.py"
    empty.write_text("x = 1\n")
    with pytest.raises(ValueError, match="defines no subclass"):
        fx.load_effect_file(empty)
    with pytest.raises(ValueError, match="does not exist"):
        fx.load_effect_file(tmp_path / "missing.py")


_SHIFT = ("\n\nclass {cls}(Effect):\n    name = '{name}'\n    params = (Param('k', 1, (0.01,), 0.01, '1'),)\n\n"
          "    def forward(self, p, R, theta, ctx):\n        return p, R\n")


def test_an_effect_files_name_clash_names_the_file_and_what_it_clashes_with(tmp_path):
    """A file's effect named as a built-in blamed the verb's table ("six.csv: effect 'mount' is
    already defined"); two classes of one file named alike kept the second in silence; a name
    two files define named only the first file. Each names the file (both files, or both
    classes) and leaves none of the file's effects registered."""
    head = "from posecorr.effects import Effect, Param\n"
    clash = tmp_path / "clash.py"
    clash.write_text(head + _SHIFT.format(cls="Fine", name="fine") + _SHIFT.format(cls="M", name="mount"))
    with pytest.raises(ValueError) as info:
        fx.load_effect_file(clash)
    assert str(info.value) == f"effect file {clash}: effect 'mount' is already defined by the built-in catalogue"
    assert "fine" not in fx.EFFECTS
    twice = tmp_path / "twice.py"
    twice.write_text(head + _SHIFT.format(cls="ShiftA", name="shift") + _SHIFT.format(cls="ShiftB", name="shift"))
    with pytest.raises(ValueError) as info:
        fx.load_effect_file(twice)
    assert str(info.value) == (f"effect file {twice}: classes ShiftA and ShiftB are both named 'shift'; give each "
                               "effect its own name")
    assert "shift" not in fx.EFFECTS
    first, second = tmp_path / "first.py", tmp_path / "second.py"
    for path in (first, second):
        path.write_text(head + _SHIFT.format(cls="Shift", name="shift"))
    assert fx.load_effect_file(first) == ["shift"]
    try:
        with pytest.raises(ValueError) as info:
            fx.load_effect_file(second)
        assert str(info.value) == f"effect file {second}: effect 'shift' is already defined by {first}"
        assert fx.load_effect_file(first) == ["shift"]   # the same file again still replaces its own
    finally:
        fx.unregister_effect("shift")


@pytest.mark.parametrize("body,expected", [
    ("a, b = theta\n        return p, R", r"raised ValueError: not enough values to unpack \(expected 2, got 1\) "
                                           r"\(line 10: a, b = theta\)"),
    ("return p[:, :2], R", r"returned p of shape \(4, 2\), expected \(4, 3\)"),
    ("return p", r"returned ndarray, expected the pair \(p, R\)"),
    ("return p / 0.0, R", r"returned p with values that are not finite"),
    # what it says of itself: a turn it does not declare (R @ R turns by R's own angle, the trial's largest
    # 1.44 rad), times it does not ask for
    ("return p, R @ R", r"turns R \(by up to 1.44 rad\), but the effect says changes_rotation = False, .* set "
                        r"changes_rotation = True$"),
    ("return p + theta * ctx.t[:, None], R", r"reads ctx.t, the poses' times, but the effect does not say "
                                             r"needs_time = True .*: set needs_time = True$"),
])
def test_a_user_effect_whose_forward_fails_is_refused_when_its_file_loads(tmp_path, body, expected):
    """A mistake in forward was a fit's error naming the data file ("d.csv: too many values to
    unpack"): it is found when the file loads, named by the effect and the file's line, and
    the file's effects are not left registered."""
    path = tmp_path / "wrong.py"
    path.write_text("from posecorr.effects import Effect, Param\n\n\nclass Wrong(Effect):\n    name = 'wrong'\n"
                    "    changes_rotation = False\n    params = (Param('k', 1, (0.01,), 0.01, '1'),)\n\n"
                    f"    def forward(self, p, R, theta, ctx):\n        {body}\n")
    with pytest.raises(ValueError) as info:
        fx.load_effect_file(path)
    assert str(info.value).startswith(f"effect file {path}: effect 'wrong': forward(p, R, theta, ctx) on 4 poses at "
                                      "its default theta ")
    assert re.search(expected, str(info.value)), str(info.value)
    assert "wrong" not in fx.EFFECTS


@pytest.mark.parametrize("root,where", [
    ("theta[..., 0:1] - 0.001", "where the fit starts, theta = [0]: its forward must be defined there"),
    ("0.001 - theta[..., 0:1]", "a small step from its default values (in root.a, for the fit's derivatives): its "
                                "forward must be defined around them"),
])
def test_a_user_effect_undefined_where_the_fit_starts_is_named(tmp_path, root, where):
    """Defined at its default (so it loads) and not at its identity, where the fit starts, or
    not a step above its default, where the fit's derivatives look: the solver's "Residuals
    are not finite in the initial point" or numpy's "SVD did not converge" was the fit's
    error, prefixed with the table's name. The effect and its file are named."""
    from posecorr.simulate import simulate_session
    from posecorr.train.physics import PhysicsModel

    path = tmp_path / "root.py"
    path.write_text("from posecorr.effects import Effect, Param, to_namespace\n\n\nclass Root(Effect):\n"
                    "    name = 'root'\n    changes_rotation = False\n"
                    "    params = (Param('a', 1, (0.001,), 0.001, 'm'),)\n\n"
                    "    def forward(self, p, R, theta, ctx):\n        xp, p, R, theta = to_namespace(p, R, theta)\n"
                    f"        return p + xp.sqrt({root}), R\n")
    fx.load_effect_file(path)
    try:
        table = simulate_session(1, n=20, spread="full", position_only=False, unremovable=0.0).table
        with pytest.raises(ValueError) as info:
            PhysicsModel(["station", "mount", "root"]).fit(table.measured, table.reference)
        assert str(info.value) == f"effect 'root' ({path.resolve()}) gives poses that are not finite {where}"
    finally:
        fx.unregister_effect("root")


@pytest.mark.parametrize("change,expected", [
    ({"size": 0, "default": ()}, "size must be a whole number >= 1, got 0"),
    ({"scale": -1.0}, r"scale \(its typical magnitude\) must be finite and > 0, got -1.0"),
    ({"scale": float("nan")}, "scale .* must be finite and > 0, got nan"),
    ({"bounds": (1.0, -1.0)}, r"bounds must be \(lower, upper\) with lower < upper, got \(1.0, -1.0\)"),
    ({"plausible": (None, 1.0)}, r"plausible must be \(lower, upper\) with lower < upper"),
    ({"default": (5.0,), "bounds": (0.0, 1.0)}, r"default \(5.0,\) lies outside its bounds \(0.0, 1.0\)"),
    ({"default": (0.0,), "domain": "positive"}, r"default \(0.0,\) must be > 0 \(domain 'positive'\)"),
    ({"default": (float("inf"),)}, r"default \(inf,\) must be finite$"),
])
def test_a_param_that_contradicts_itself_is_refused_where_it_is_written(change, expected):
    """A size of 0, a negative scale, bounds upside down, a default outside its bounds or
    domain: each loaded, and the fit met it later as the data's fault or the solver's."""
    fields = {"name": "a", "size": 1, "default": (0.5,), "scale": 1.0, "unit": "m", **change}
    with pytest.raises(ValueError, match=f"^parameter a: {expected}"):
        fx.Param(**fields)
    assert fx.Param(name="a", size=1, default=(0.5,), scale=1.0, unit="m", bounds=(0.0, np.inf))


# --- export-readiness: only the array-namespace interface ----------------------------------

class _StrictNamespace:
    """Exactly the `posecorr._xp` interface over a wrapped numpy array, like the ONNX exporter's
    symbolic tensors: no numpy functions, no fancy indexing, no Python branching on values."""

    name = "strict"

    def __getattr__(self, fn):
        if fn not in ("sqrt", "sin", "cos", "tan", "exp", "tanh", "abs"):
            raise AttributeError(f"not in the namespace interface: {fn}")
        return lambda x: _Strict(getattr(np, fn)(x.a))

    atan2 = staticmethod(lambda y, x: _Strict(np.arctan2(_raw(y), _raw(x))))
    maximum = staticmethod(lambda a, b: _Strict(np.maximum(_raw(a), _raw(b))))
    minimum = staticmethod(lambda a, b: _Strict(np.minimum(_raw(a), _raw(b))))
    where = staticmethod(lambda c, a, b: _Strict(np.where(_raw(c), _raw(a), _raw(b))))
    stack = staticmethod(lambda xs, axis=-1: _Strict(np.stack(np.broadcast_arrays(*map(_raw, xs)), axis)))
    concat = staticmethod(lambda xs, axis=-1: _Strict(np.concatenate([_raw(x) for x in xs], axis)))
    sum = staticmethod(lambda x, axis=-1, keepdims=False: _Strict(np.sum(x.a, axis=axis, keepdims=keepdims)))
    reshape = staticmethod(lambda x, shape: _Strict(np.reshape(x.a, shape)))
    swap_last = staticmethod(lambda x: _Strict(np.swapaxes(x.a, -1, -2)))
    matmul = staticmethod(lambda a, b: _Strict(np.matmul(_raw(a), _raw(b))))

    @staticmethod
    def const(value, like):
        assert isinstance(value, (np.ndarray, float, int)), f"const of {type(value)}"
        return _Strict(np.asarray(value, float))


def _raw(x):
    return x.a if isinstance(x, _Strict) else x


class _Strict:
    pc_namespace = _StrictNamespace()
    __array_ufunc__ = None          # numpy must not operate on it

    def __init__(self, a):
        self.a = np.asarray(a)

    shape = property(lambda self: self.a.shape)

    def __array__(self, *args, **kwargs):
        raise TypeError("a symbolic tensor cannot become a numpy array")

    def __bool__(self):
        raise TypeError("Python control flow on a symbolic value")

    def __getitem__(self, key):
        ok = isinstance(key, tuple) and len(key) == 2 and key[0] is Ellipsis and (
            isinstance(key[1], int) or (isinstance(key[1], slice) and key[1].step is None))
        assert ok, f"indexing beyond x[..., i] / x[..., i:j]: {key!r}"
        return _Strict(self.a[key])

    def _op(f):
        return lambda self, other: _Strict(f(self.a, _raw(other)))

    def _rop(f):
        return lambda self, other: _Strict(f(_raw(other), self.a))

    import operator as _o
    __add__, __sub__, __mul__, __truediv__ = _op(_o.add), _op(_o.sub), _op(_o.mul), _op(_o.truediv)
    __radd__, __rsub__, __rmul__, __rtruediv__ = _rop(_o.add), _rop(_o.sub), _rop(_o.mul), _rop(_o.truediv)
    __lt__, __le__, __gt__, __ge__ = _op(_o.lt), _op(_o.le), _op(_o.gt), _op(_o.ge)
    __neg__ = lambda self: _Strict(-self.a)  # noqa: E731


@pytest.mark.parametrize("name", INVERTIBLE)
def test_maps_use_only_the_namespace_interface(name, workspace_poses, ctx):
    """What the ONNX exporter's tensors support is enough for every invertible map and its inverse."""
    p, R = workspace_poses
    e = get_effect(name)
    c = EffectContext(ctx.R_S, ctx.t_S, ctx.c, t=_Strict(ctx.t))
    for method in (e.forward, e.inverse):
        q, Q = method(_Strict(p), _Strict(R), THETA[name], c)
        want_q, want_Q = method(p, R, THETA[name], ctx)
        np.testing.assert_allclose(q.a, want_q, atol=1e-14)
        np.testing.assert_allclose(Q.a, want_Q, atol=1e-14)


def test_a_value_is_implausible_only_where_the_data_rejects_the_plausible_range():
    """incidence's plausible range is +-5 mm: 15.1 mm with a standard error of 1.7 mm lies 5.9
    standard errors beyond it; with 10 mm, or held (NaN), the data does not reject the range."""
    incidence = get_effect("incidence")
    lo, hi = incidence.params[0].plausible
    theta = np.array([0.0151, 0.003])
    assert lo == -0.005 and hi == 0.005
    assert incidence.implausible(theta) == [
        "incidence.b1 = 0.0151 m lies outside the plausible -0.005 to 0.005 m"]
    assert incidence.implausible(theta, [0.0017, 1e-4]) == [
        "incidence.b1 = 0.0151 m lies outside the plausible -0.005 to 0.005 m (5.9 standard errors beyond)"]
    assert incidence.implausible(theta, [0.01, 1e-4]) == []
    assert incidence.implausible(theta, [np.nan, 1e-4]) == incidence.implausible(theta)
    assert incidence.implausible([0.004, -0.0049], [1e-6, 1e-6]) == []
    drift = get_effect("drift")
    # d (3) beyond by 0.05 m with 0.02 m errors: 2.5 standard errors, the farthest entry named
    assert drift.implausible([0.07, 0.01, -0.03, 3600.0], [0.02, 0.02, 0.02, 100.0]) == [
        "drift.d = 0.07 m lies outside the plausible -0.02 to 0.02 m (2.5 standard errors beyond)"]


def test_a_dimensionless_value_is_implausible_without_the_unit_1():
    """range_scale's k has the unit "1": "k = -0.953 1 lies outside the plausible -0.02 to
    0.02 1" read as two numbers each."""
    assert get_effect("range_scale").implausible([-0.953]) == [
        "range_scale.k = -0.953 lies outside the plausible -0.02 to 0.02"]


def test_fit_refuses_an_effect_whose_map_does_not_trace_before_the_work(tmp_path, capsys):
    """np.sin on the pose runs in the fit and failed in its export, after the work, as an
    "internal error" of posecorr: `fit` traces each loaded effect first and names the line;
    the same effect written with the namespace fits and exports."""
    from posecorr.cli import main
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    data = tmp_path / "s.csv"
    write_table(simulate_session(1, n=20).table, data)
    numpy_only = tmp_path / "wavy.py"
    numpy_only.write_text("import numpy as np\nfrom posecorr.effects import Effect, Param\n\n\nclass Wavy(Effect):\n"
                          "    name = 'wavy'\n    changes_rotation = False\n"
                          "    params = (Param('a', 1, (0.001,), 1e-3, 'm'),)\n\n"
                          "    def forward(self, p, R, theta, ctx):\n        return p + theta[0] * np.sin(p), R\n")
    args = ["fit", str(data), "--effects", "station,mount,wavy", "--method", "none", "-o", str(tmp_path / "m.onnx")]
    assert main([*args, "--effect-file", str(numpy_only)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "effect 'wavy': its map does not trace into the ONNX graph fit exports" in err
    assert "(line 11: return p + theta[0] * np.sin(p), R)" in err and "fold" not in err
    assert "wavy" not in fx.EFFECTS and not (tmp_path / "m.onnx").exists()
    numpy_only.write_text(numpy_only.read_text().replace("Param\n", "Param, to_namespace\n").replace(
        "        return p + theta[0] * np.sin(p), R",
        "        xp, p, R, theta = to_namespace(p, R, theta)\n        return p + theta[..., 0] * xp.sin(p), R"))
    assert main([*args, "--effect-file", str(numpy_only)]) == 0, capsys.readouterr().err
    assert (tmp_path / "m.onnx").exists()
    fx.unregister_effect("wavy")


@pytest.mark.parametrize("length", range(1, 10))
def test_numpy_namespace_sum_gives_numpy_bits(length: int) -> None:
    """The numpy namespace writes short last-axis sums out as adds (ten times faster): the
    bits, signed zeros and dtype must stay numpy's, contiguous or not, with keepdims."""
    from posecorr._xp import NumpyNamespace

    rng = np.random.default_rng(length)
    x = rng.normal(size=(6, 5, length)) * 10.0 ** rng.uniform(-9, 4, size=(6, 5, length))
    x[0] = -0.0
    x[1, :, 0] = -x[1, :, -1] if length > 1 else x[1, :, 0]
    strided = np.swapaxes(np.ascontiguousarray(np.swapaxes(x, -1, -2)), -1, -2)
    for v in (x, x * x, x.astype(np.float32), strided, x[..., ::-1]):
        for keepdims in (False, True):
            got = np.asarray(NumpyNamespace.sum(v, axis=-1, keepdims=keepdims))
            want = np.sum(v, axis=-1, keepdims=keepdims)
            assert got.dtype == want.dtype and got.shape == want.shape
            assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))
    assert NumpyNamespace.sum(np.array([True, False, True])) == 2     # counts, not a logical or
