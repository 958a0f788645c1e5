"""The loop's worked example (docs/guides/loop.md): an effect outside the catalogue, found
by its feature, added as a user effect, and the error falls to the noise floor."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from posecorr.analysis.diagnose import diagnose
from posecorr.effects import EFFECTS, load_effect_file, unregister_effect
from posecorr.simulate import simulate
from posecorr.train.pipeline import CorrectionPipeline, cross_validate
from posecorr.train.splits import KFold

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "periodic_sweep.py"
CATALOGUE = ["mount", "sweep", "range_scale", "incidence", "drift", "station"]


@pytest.fixture
def periodic_sweep():
    yield load_effect_file(EXAMPLE)
    if "periodic_sweep" in EFFECTS:
        unregister_effect("periodic_sweep")


@pytest.mark.slow
def test_periodic_sweep_is_seen_under_azimuth_then_added(periodic_sweep) -> None:
    result = simulate(3, seed=3, effect_files=[str(EXAMPLE)])
    table = result.table.subset(np.random.default_rng(3).permutation(result.table.n)[:1200])
    # Without the effect in the registry, only the residual features can point at it.
    unregister_effect("periodic_sweep")
    # A period of 6 degrees of azimuth is far above the generic forms' second harmonic: the
    # catalogue alone is asked here, as a user without the forms would.
    blind = diagnose(table, CATALOGUE, folds=5, seed=3, forms=False)
    assert blind["candidates"] == []
    top_two = [row["feature"] for row in blind["features"][:2]]
    assert "azimuth" in top_two and blind["features"][0]["r2"] > 0.05, blind["features"]

    load_effect_file(EXAMPLE)
    informed = diagnose(table, CATALOGUE, folds=5, seed=3, forms=False)
    assert informed["candidates"][0]["effect"] == "periodic_sweep"
    assert informed["candidates"][0]["present"]
    cv = cross_validate(lambda: CorrectionPipeline(CATALOGUE + ["periodic_sweep"]), table, KFold(5), seed=3)
    assert cv.metrics["rmse_pos"] <= 1.3 * result.noise_floor["rmse_pos"]
    assert cv.metrics["rmse_pos"] < blind["cv_base"]["rmse_pos"]


USER_FRAME = '''
import numpy as np
from posecorr._xp import namespace
from posecorr.effects import Effect, Param
from posecorr.rotations import matrix_to_rotvec, rotvec_to_matrix


class MyFrame(Effect):
    """The station registration written again by a user: p <- c + Exp(w)(p - c) + v, R <- Exp(w) R."""

    name = "my_frame"
    order = 6
    registration = "frame"
    per_row_theta = True
    params = (Param("w", 3, (0.0, 0.0, 0.0), 1e-2, "rad", unbounded=True),
              Param("v", 3, (0.0, 0.0, 0.0), 1e-2, "m", unbounded=True))

    def forward(self, p, R, theta, ctx):
        xp = namespace(p, R, theta)
        W = rotvec_to_matrix(theta[..., 0:3])
        c = xp.const(ctx.c, p)
        d = p - c
        moved = xp.sum(W * xp.reshape(d, tuple(d.shape[:-1]) + (1, 3)), axis=-1)
        return c + moved + theta[..., 3:6], xp.matmul(W, R)

    def inverse(self, p, R, theta, ctx):
        xp = namespace(p, R, theta)
        Wt = xp.swap_last(rotvec_to_matrix(theta[..., 0:3]))
        c = xp.const(ctx.c, p)
        d = p - theta[..., 3:6] - c
        return c + xp.sum(Wt * xp.reshape(d, tuple(d.shape[:-1]) + (1, 3)), axis=-1), xp.matmul(Wt, R)

    def start(self, rigid, ctx, roles, mean_turn):
        W = rigid.R.T
        return np.concatenate([matrix_to_rotvec(W), -W @ rigid.t - ctx.c + W @ ctx.c])

    def frame_rotation(self, theta):
        return theta[..., 0:3]
'''


@pytest.mark.parametrize("position_only", [False, True])
def test_a_user_effect_declares_the_registration_role(tmp_path, position_only) -> None:
    """What the fitter gives the built-in station (the closed-form start, the frame role, no
    typical size for its parameters) a user's effect declares for itself: fitted on a simulated
    session, it gives the station's result."""
    from posecorr.simulate import simulate_session
    from posecorr.train.physics import PhysicsModel

    path = tmp_path / "my_frame.py"
    path.write_text(USER_FRAME)
    load_effect_file(path)
    try:
        table = simulate_session(4, n=30, spread="full", position_only=position_only, unremovable=0.0).table
        m, r = table.measured, table.reference
        ours = PhysicsModel(("my_frame", "mount"), with_rotation=table.has_orientation).fit(m, r)
        builtin = PhysicsModel(("station", "mount"), with_rotation=table.has_orientation).fit(m, r)
        np.testing.assert_allclose(ours.params_["my_frame"], builtin.params_["station"], rtol=0, atol=1e-9)
        np.testing.assert_allclose(ours.params_["mount"], builtin.params_["mount"], rtol=0, atol=1e-9)
        assert ours.fixed_ == builtin.fixed_
        assert np.abs(ours.predict(m) - builtin.predict(m)).max() < 1e-9
    finally:
        unregister_effect("my_frame")
