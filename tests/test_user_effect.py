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
    blind = diagnose(table, CATALOGUE, folds=5, seed=3)
    assert blind["candidates"] == []
    top_two = [row["feature"] for row in blind["features"][:2]]
    assert "azimuth" in top_two and blind["features"][0]["r2"] > 0.05, blind["features"]

    load_effect_file(EXAMPLE)
    informed = diagnose(table, CATALOGUE, folds=5, seed=3)
    assert informed["candidates"][0]["effect"] == "periodic_sweep"
    assert informed["candidates"][0]["present"]
    cv = cross_validate(lambda: CorrectionPipeline(CATALOGUE + ["periodic_sweep"]), table, KFold(5), seed=3)
    assert cv.metrics["rmse_pos"] <= 1.3 * result.noise_floor["rmse_pos"]
    assert cv.metrics["rmse_pos"] < blind["cv_base"]["rmse_pos"]
