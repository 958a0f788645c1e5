"""scikit-learn's estimator checks on every corrector (issue 12, item 2).

A corrector is a regressor from (N, 7) poses (x, y, z, qw, qx, qy, qz) to (N, 7) poses. Every
check of `check_estimator` runs; the ones that cannot apply to such a regressor are named in
`SKIPPED` with the reason, and must indeed not pass (a stale entry fails the test). The checks
skipped only because sklearn draws its X with 2 to 10 columns are run again below on pose
tables (`test_skipped_checks_hold_on_pose_tables`): the property they test, on the data a
corrector takes. The counts are printed into the test output.
"""
from __future__ import annotations

import pickle
import warnings

import numpy as np
import pytest

pytest.importorskip("sklearn")
pytest.importorskip("torch")

from sklearn.base import clone  # noqa: E402
from sklearn.exceptions import NotFittedError  # noqa: E402
from sklearn.utils.estimator_checks import check_estimator  # noqa: E402
from sklearn.utils.validation import check_is_fitted  # noqa: E402

from posecorr.simulate import simulate_session  # noqa: E402
from posecorr.train.mlp import MLP  # noqa: E402
from posecorr.train.physics import PhysicsModel, RigidModel  # noqa: E402
from posecorr.train.pipeline import CorrectionPipeline  # noqa: E402
from posecorr.train.pmc import PMC  # noqa: E402


def _estimators() -> dict:
    return {
        "PMC": PMC(),
        "MLP": MLP(hidden=(3,), epochs=5, trainer="lm"),
        "PhysicsModel": PhysicsModel(),
        "RigidModel": RigidModel(),
        "CorrectionPipeline": CorrectionPipeline(("station", "mount"), PMC(alpha=1e-6)),
    }


COLUMNS = "draws X with {} columns; a corrector's input is an (N, 7) pose table (run on poses below)"
SKIPPED = {
    # sklearn's generic data: random X of 2 to 10 columns, never 7.
    "check_dict_unchanged": COLUMNS.format(3),
    "check_dont_overwrite_parameters": COLUMNS.format(3),
    "check_dtype_object": COLUMNS.format(10),
    "check_estimators_dtypes": COLUMNS.format(5),
    "check_estimators_fit_returns_self": COLUMNS.format(2),
    "check_estimators_overwrite_params": COLUMNS.format(2),
    "check_estimators_pickle": COLUMNS.format(3),
    "check_f_contiguous_array_estimator": COLUMNS.format(3),
    "check_fit2d_predict1d": COLUMNS.format(3),
    "check_fit_check_is_fitted": COLUMNS.format(2),
    "check_fit_idempotent": COLUMNS.format(2),
    "check_fit_score_takes_y": COLUMNS.format(3),
    "check_methods_sample_order_invariance": COLUMNS.format(3),
    "check_methods_subset_invariance": COLUMNS.format(3),
    "check_n_features_in": COLUMNS.format(2),
    "check_n_features_in_after_fitting": COLUMNS.format(4),
    "check_pipeline_consistency": COLUMNS.format(3),
    "check_readonly_memmap_input": COLUMNS.format(2),
    "check_estimators_nan_inf": COLUMNS.format(3) + " after the NaN and inf refusals",
    "check_positive_only_tag_during_fit": COLUMNS.format(5),
    "check_regressor_data_not_an_array": COLUMNS.format(10),
    "check_regressor_multioutput": COLUMNS.format(10),
    "check_regressors_int": COLUMNS.format(10) + " (integer poses are not a pose table either)",
    "check_regressors_no_decision_function": COLUMNS.format(4),
    "check_regressors_train": COLUMNS.format(10) + " and scores it by R^2 of a 1-d target",
    "check_fit2d_1sample": "fits one row of 10 columns and wants the refusal to speak of the 1 sample; "
                           "a corrector refuses the 10 columns first",
    # Not something the correctors do.
    "check_array_api_input": "the correctors compute in numpy float64 (posecorr._xp is their own namespace "
                             "layer for torch and ONNX); array-API inputs are not supported",
}


@pytest.fixture(scope="module")
def table():
    return simulate_session(2, n=80).table


@pytest.mark.parametrize("name", list(_estimators()))
def test_check_estimator(name: str, summary) -> None:
    estimator = _estimators()[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        results = check_estimator(estimator, expected_failed_checks=SKIPPED, on_fail=None, on_skip=None)
    failed = [f"{r['check_name']}: {type(r['exception']).__name__}: {r['exception']}"
              for r in results if r["status"] == "failed"]
    stale = sorted({r["check_name"] for r in results if r["status"] == "passed" and r["expected_to_fail"]})
    passed = sorted({r["check_name"] for r in results if r["status"] == "passed"})
    skipped = sorted({r["check_name"] for r in results if r["status"] in ("xfail", "skipped")})
    summary(f"check_estimator {name}: {len(passed)} checks passed, {len(skipped)} skipped (named in "
            f"SKIPPED), {len(failed)} failed")
    assert not failed, "\n".join(failed)
    assert not stale, f"checks in SKIPPED that now pass (remove them from the table): {stale}"
    # The checks every estimator must pass whatever its data: the API contract and the refusals.
    assert {"check_estimator_cloneable", "check_get_params_invariance", "check_set_params",
            "check_estimators_unfitted", "check_no_attributes_set_in_init", "check_parameters_default_constructible",
            "check_complex_data", "check_estimator_sparse_array", "check_requires_y_none",
            "check_estimators_empty_data_messages", "check_fit1d", "check_fit2d_1feature"} <= set(passed)


def _fit(estimator, table, **kwargs):
    return estimator.fit(table.measured, table.reference, **kwargs)


@pytest.mark.parametrize("name", list(_estimators()))
def test_skipped_checks_hold_on_pose_tables(name: str, table) -> None:
    """The properties of the checks skipped for their random X, on an (N, 7) pose table."""
    M, R = table.measured, table.reference
    estimator = _estimators()[name]
    params = estimator.get_params()
    # check_fit_check_is_fitted / check_n_features_in: fitted state only after fit
    with pytest.raises(NotFittedError):
        check_is_fitted(estimator)
    assert not hasattr(estimator, "n_features_in_")
    # check_estimators_nan_inf: NaN and inf refused in fit and predict
    for bad in (np.nan, np.inf):
        X = M.copy()
        X[3, 1] = bad
        with pytest.raises(ValueError, match="NaN or infinite"):
            clone(estimator).fit(X, R)
    # check_estimators_fit_returns_self
    fitted = _fit(estimator, table)
    assert fitted is estimator
    check_is_fitted(estimator)
    assert estimator.n_features_in_ == 7
    # check_dont_overwrite_parameters / check_estimators_overwrite_params
    assert repr(estimator.get_params()) == repr(params)
    X = M.copy()
    X[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        estimator.predict(X)
    # check_fit2d_predict1d
    with pytest.raises(ValueError, match="2-d"):
        estimator.predict(M[0])
    # a zero or norm-2 quaternion is refused as the runtime and the table reader refuse it
    for scale, what in ((0.0, "a zero quaternion"), (2.0, "quaternion norm 2 is off 1 by more than 0.001")):
        X = M.copy()
        X[5, 3:] *= scale
        with pytest.raises(ValueError, match=f"^measured: row 5: {what} "):
            estimator.predict(X)
        with pytest.raises(ValueError, match="row 5: .*unit quaternion"):
            clone(estimator).fit(X, R)
    # check_dict_unchanged
    before = {k: repr(v) for k, v in estimator.__dict__.items()}
    expected = estimator.predict(M)
    assert {k: repr(v) for k, v in estimator.__dict__.items()} == before
    # check_methods_sample_order_invariance / check_methods_subset_invariance
    order = np.random.default_rng(0).permutation(len(M))
    assert np.allclose(estimator.predict(M[order]), expected[order], rtol=0, atol=1e-12)
    assert np.allclose(np.concatenate([estimator.predict(part) for part in np.array_split(M, 4)]), expected,
                       rtol=0, atol=1e-12)
    # check_fit_idempotent, check_f_contiguous_array_estimator, check_readonly_memmap_input,
    # check_dtype_object, check_estimators_dtypes: the same fit from the same poses in another form
    readonly_M, readonly_R = M.copy(), R.copy()
    readonly_M.flags.writeable = readonly_R.flags.writeable = False
    for X, Y in [(M, R), (np.asfortranarray(M), np.asfortranarray(R)), (readonly_M, readonly_R),
                 (M.astype(object), R.astype(object))]:
        again = clone(estimator).fit(X, Y)
        assert np.allclose(again.predict(M), expected, rtol=0, atol=1e-9)
    single = clone(estimator).fit(M.astype(np.float32), R.astype(np.float32))
    assert single.predict(M).dtype == np.float64
    objects = M.astype(object)
    objects[0, 0] = {"x": 1}
    with pytest.raises(TypeError):
        clone(estimator).fit(objects, R)
    # check_estimators_pickle
    restored = pickle.loads(pickle.dumps(estimator))
    assert np.array_equal(restored.predict(M), expected)
    # check_fit_score_takes_y / check_regressors_train: score is -rmse_total of the correction
    assert estimator.score(M, R) == pytest.approx(-_rmse_total(R, expected), rel=1e-9)


def _rmse_total(reference: np.ndarray, predicted: np.ndarray) -> float:
    """Paper eq. 43 independently of posecorr.metrics: the RMS over poses of |dp| (m) + angle
    (rad, scipy's), the weights of posecorr.metrics being 1 and 1."""
    from scipy.spatial.transform import Rotation

    dp = np.linalg.norm(predicted[:, :3] - reference[:, :3], axis=1)
    ref = Rotation.from_quat(reference[:, [4, 5, 6, 3]])
    pred = Rotation.from_quat(predicted[:, [4, 5, 6, 3]])
    angle = (ref.inv() * pred).magnitude()
    return float(np.sqrt(np.mean((dp + angle) ** 2)))
