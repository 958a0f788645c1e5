"""Hidden-effect tests: diagnose finds the effect the model lacks, and nothing else.

Each scenario simulates Experiment III (a random subset of its poses, for speed) with the
catalogue's effects at realistic magnitudes, hides one of them from the model, and also
switches one other effect off in the simulation while leaving it out of the model too:
the hidden effect must rank first and be marked present, the absent one must not be, and
adding the hidden effect must bring the cross-validated rmse_pos within 1.3x of the
simulator's noise floor. Seeds and magnitudes vary across scenarios.
"""
from __future__ import annotations

import numpy as np
import pytest

from posecorr.analysis.diagnose import diagnose, feature_r2
from posecorr.simulate import DEFAULT_MIX, simulate

CATALOGUE = ["mount", "sweep", "range_scale", "incidence", "drift", "station"]
SUBSET = 900

# (hidden effect, effect absent from the data, seed, magnitude factor of the hidden one)
SCENARIOS = [
    ("mount", "incidence", 0, 1.0),
    ("sweep", "range_scale", 1, 1.0),
    ("range_scale", "sweep", 2, 2.0),
    ("incidence", "drift", 3, 1.5),
    ("drift", "mount", 4, 1.0),
    ("station", "sweep", 5, 0.5),
]


def _scenario_table(hidden: str, absent: str | None, seed: int, factor: float):
    mix = {name: list(values) for name, values in DEFAULT_MIX[3].items()}
    if hidden == "drift":
        mix["drift"] = [v * factor for v in mix["drift"][:3]] + [mix["drift"][3]]
    else:
        mix[hidden] = [v * factor for v in mix[hidden]]
    if absent is not None:
        mix.pop(absent)
    result = simulate(3, effects=mix, seed=seed, base="none")
    subset = np.random.default_rng(seed).permutation(result.table.n)[:SUBSET]
    return result, result.table.subset(subset)


@pytest.mark.slow
@pytest.mark.parametrize("hidden, absent, seed, factor", SCENARIOS)
def test_hidden_effect_is_found_and_fixes_the_error(hidden, absent, seed, factor) -> None:
    result, table = _scenario_table(hidden, absent, seed, factor)
    model = [e for e in CATALOGUE if e not in (hidden, absent)]
    report = diagnose(table, model, folds=5, seed=seed, forms=False)
    by_name = {row["effect"]: row for row in report["candidates"]}
    assert set(by_name) == {hidden, absent}
    assert report["candidates"][0]["effect"] == hidden, report["candidates"]
    assert by_name[hidden]["present"], by_name[hidden]
    assert not by_name[absent]["present"], by_name[absent]
    assert by_name[hidden]["cv_rmse_pos_after"] <= 1.3 * result.noise_floor["rmse_pos"]


@pytest.mark.slow
def test_nothing_missing_nothing_present() -> None:
    result, table = _scenario_table("mount", "sweep", 7, 1.0)
    report = diagnose(table, [e for e in CATALOGUE if e != "sweep"], folds=5, seed=7, forms=False)
    assert [row["effect"] for row in report["candidates"]] == ["sweep"]
    assert not report["candidates"][0]["present"]
    # registered frames: the sweep is taken about the station where it stands, without a caveat
    assert not [note for note in report["notes"] if "about where the base station stands" in note], report["notes"]
    assert report["cv_base"]["rmse_pos"] <= 1.3 * result.noise_floor["rmse_pos"]


def test_feature_r2_finds_the_feature_that_carries_the_error() -> None:
    rng = np.random.default_rng(0)
    n = 600
    features = {name: rng.uniform(-1, 1, n) for name in ("x", "y", "azimuth", "yaw")}
    residuals = np.stack([np.sin(6 * features["azimuth"]), rng.normal(scale=0.1, size=n)], axis=1)
    rows = feature_r2(residuals, features)
    assert rows[0]["feature"] == "azimuth"
    # sin(6a) carries 0.5 of the variance against 0.01 of noise: R^2 near 0.98 of the total.
    assert rows[0]["r2"] > 0.9
    assert all(row["r2"] < 0.05 for row in rows[1:])


def test_feature_r2_scores_position_and_orientation_apart() -> None:
    """A drift of position along t under orientation noise larger than it: pooled into
    one R^2 the diagnosis read 'none (cv R^2 0 along ... t)' on a session where drift was
    present; by block, t explains the position error."""
    from posecorr.analysis.diagnose import ERROR_BLOCKS

    rng = np.random.default_rng(4)
    n = 40
    features = {"t": np.sort(rng.uniform(0, 1600, n)), "x": rng.uniform(-1, 1, n)}
    drift = 4.0 * (1 - np.exp(-features["t"] / 400.0))          # mm
    position = np.outer(drift - drift.mean(), [1.0, -0.5, 0.8]) + rng.normal(scale=0.3, size=(n, 3))
    residuals = np.concatenate([position, rng.normal(scale=3.0, size=(n, 3))], axis=1)
    pooled = {row["feature"]: row["r2"] for row in feature_r2(residuals, features)}
    rows = feature_r2(residuals, features, blocks=ERROR_BLOCKS)
    assert pooled["t"] < 0.1
    assert rows[0]["feature"] == "t" and rows[0]["error"] == "position" and rows[0]["r2"] > 0.5, rows


def test_diagnose_text_lists_only_features_with_structure() -> None:
    """`posecorr diagnose`'s feature table holds the features that explain something; pure noise
    reads as one line, not a table of zeros."""
    from posecorr.cli.diagnose import _feature_lines

    rng = np.random.default_rng(1)
    n = 400
    features = {name: rng.uniform(-1, 1, n) for name in ("x", "y", "azimuth", "yaw")}
    carried = np.stack([np.sin(6 * features["azimuth"]), rng.normal(scale=0.1, size=n)], axis=1)
    rows = feature_r2(carried, features)
    text = "\n".join(_feature_lines(rows))
    zero = [row["feature"] for row in rows if row["r2"] == 0.0]
    listed = [line.split()[0] for line in text.splitlines()[3:] if not line.startswith("cv R^2 0 along")]
    assert listed == [row["feature"] for row in rows if row["r2"] > 0.0] and listed[0] == "azimuth"
    assert zero and f"cv R^2 0 along {', '.join(zero)}" in text
    # on noise a smooth fit predicts the held-out residual worse than its mean: R^2 clipped to 0
    noise = feature_r2(rng.normal(size=(n, 2)), features)
    assert [row["r2"] for row in noise] == [0.0] * 4
    assert _feature_lines(noise) == ["Residual structure by feature (smooth fit, cross-validated): none "
                                     "(cv R^2 0 along " + ", ".join(row["feature"] for row in noise) + ")"]


def test_auto_never_returns_a_model_worse_than_the_rigid_fit() -> None:
    """A small real-sized data set (30 poses): a 55-term quadratic would overfit it."""
    from posecorr.metrics import pose_metrics
    from posecorr.train.pipeline import fit_table
    from posecorr.train.spec import ModelSpec
    from posecorr.train.splits import KFold

    table = simulate(3, seed=11).table.subset(np.arange(30))
    report = fit_table(table, ["station", "mount"], ModelSpec("auto"), KFold(5), seed=0)
    scores = report.auto_scores
    # Small tables: the cheap candidates only, no network: the plain Kabsch fit and the
    # physics stage at every prior strength, alone or with a core.
    assert set(scores) == {"rigid-kabsch", "physics", "physics(prior 0.1)", "physics(prior 1)", "physics(prior 10)",
                           "physics+affine-zhou", "physics+pmc-zhou"}
    assert scores[report.chosen] == min(scores.values()) or report.fell_back
    # The floor on the same folds (every rigid variant; orientations about three axes: the
    # hand-eye solution too), recomputed here from each variant's out-of-fold predictions.
    from posecorr.train.physics import RigidModel

    floor = {}
    for variant in ("kabsch", "lever", "lever-ref", "hand-eye", "joint"):
        predicted = np.empty_like(table.measured)
        for train, held in KFold(5).folds(table.n, 0):
            rigid = RigidModel(variant=variant).fit(table.measured[train], table.reference[train])
            predicted[held] = rigid.predict(table.measured[held])
        floor[variant] = pose_metrics(table.reference, predicted)["rmse_total"]
    # The closed forms agree to rounding; the joint fit within 0.1 %: fit_table's folds start
    # from the fit on all poses and keep its noise levels, a cold fit re-estimates them.
    for variant, value in floor.items():
        assert report.rigid_scores[f"rigid-{variant}"] == pytest.approx(value, rel=1e-3 if variant == "joint" else 1e-9)
    best = min(report.rigid_scores, key=report.rigid_scores.get)
    assert report.baseline_name == best
    assert report.baseline["rmse_total"] == report.rigid_scores[best]
    assert report.baseline["rmse_total"] == pytest.approx(min(floor.values()), rel=1e-3)
    assert report.heldout["rmse_total"] <= report.baseline["rmse_total"]
