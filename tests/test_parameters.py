"""The estimators' parameters: out of range refused before any work, naming the parameter and
its range; one changed by set_params after fit refused until the next fit; a refit's state all
its own (an audit of the Python API found each of these)."""
from __future__ import annotations

import numpy as np
import pytest
from sklearn.exceptions import NotFittedError

from posecorr.simulate import simulate
from posecorr.train.mlp import MLP
from posecorr.train.physics import PhysicsModel
from posecorr.train.pipeline import CorrectionPipeline
from posecorr.train.pmc import PMC


@pytest.fixture(scope="module")
def poses():
    table = simulate(3, seed=0).table.draw(120)[0]
    return table.measured, table.reference


@pytest.mark.parametrize("change,expected", [
    # a damping of 0 never grew, a growth of 1 never reached mu_max: the training never ended
    ({"mu": 0.0}, "mu must be None or a finite number > 0, got 0.0"),
    ({"mu": -1.0}, "mu must be None or a finite number > 0, got -1.0"),
    ({"mu": float("nan")}, "mu must be None or a finite number > 0, got nan"),
    ({"mu_inc": 1.0}, "mu_inc must be a finite number > 1, got 1.0"),
    ({"mu_dec": 1.5}, r"mu_dec must be a finite number in \(0, 1\] \(1: held\), got 1.5"),
    ({"mu": 1e11}, r"mu must be at most mu_max \(10000000000.0\), got 100000000000.0"),
    ({"lr": -1.0}, "lr must be a finite number > 0, got -1.0"),
    ({"max_fail": -1}, "max_fail must be a whole number >= 1, got -1"),
    ({"verbose": -1}, r"verbose must be a whole number >= 0 \(0: silent\), got -1"),
    ({"num_threads": 0}, "num_threads must be None or a whole number >= 1, got 0"),
    ({"goal": True}, "goal must be a finite number >= 0, got True"),
    ({"merge_validation": "x"}, "merge_validation must be True or False, got 'x'"),
    ({"hidden": (2.5,)}, r"layer sizes are integers in 1..1024, got 2.5"),
])
def test_an_mlp_parameter_out_of_range_is_refused_before_any_work(poses, change, expected):
    with pytest.raises(ValueError, match=f"^{expected}$"):
        MLP(**{"hidden": (3,), "epochs": 2, "trainer": "lm", **change}).fit(*poses)


@pytest.mark.parametrize("change,expected", [
    # NaN fitted an unpenalised minimum-norm map labelled "ridge"; inf met LAPACK
    ({"alpha": float("nan")}, "alpha must be a finite number >= 0 or 'cv', got nan"),
    ({"alpha": float("inf")}, "alpha must be a finite number >= 0 or 'cv', got inf"),
    ({"alpha": None}, "alpha must be a finite number >= 0 or 'cv', got None"),
    ({"alpha": "cv", "alpha_grid": [-0.5]}, r"alpha_grid must hold one or more finite numbers >= 0, got \[-0.5\]"),
    ({"alpha": "cv", "alpha_grid": []}, r"alpha_grid must hold one or more finite numbers >= 0, got \[\]"),
    ({"alpha": "cv", "cv_folds": 1}, "cv_folds must be a whole number >= 2, got 1"),
    ({"degree": True}, r"degree must be 1 \(affine\) or 2 \(quadratic\), got True"),
])
def test_a_pmc_parameter_out_of_range_is_refused_before_any_work(poses, change, expected):
    with pytest.raises(ValueError, match=f"^{expected}$"):
        PMC(**change).fit(*poses)


@pytest.mark.parametrize("make,change", [
    (lambda: PMC(), {"degree": 1}),
    (lambda: PMC(), {"representation": "quat"}),
    (lambda: MLP(hidden=(3,), epochs=2), {"residual": True}),
    (lambda: MLP(hidden=(3,), epochs=2), {"activation": "logsig"}),
])
def test_a_parameter_changed_after_fit_is_refused_until_the_next_fit(poses, make, change):
    """predict read the parameter and the weights of the fit: residual=True moved the poses by
    0.69 m without a word, degree=1 met numpy's shapes."""
    measured, reference = poses
    estimator = make().fit(measured, reference)
    before = estimator.predict(measured)
    (name, value), = change.items()
    fitted = getattr(estimator, name)
    estimator.set_params(**change)
    with pytest.raises(NotFittedError, match=f"was fitted with {name}={fitted!r}, and set_params made it "
                                             f"{value!r}: call fit again"):
        estimator.predict(measured)
    estimator.set_params(**{name: fitted})   # back as it was fitted: the same model
    np.testing.assert_array_equal(estimator.predict(measured), before)
    estimator.set_params(**change).fit(measured, reference)
    assert estimator.predict(measured).shape == measured.shape


def test_a_refit_has_the_standard_errors_of_its_own_data(poses):
    """The first fit's standard errors stayed cached through a refit on other data, and
    describe() showed them beside the new values."""
    other = simulate(3, seed=5).table.draw(120)[0]
    model = PhysicsModel(("station", "mount")).fit(*poses)
    first = model.std_errors_["station"]
    model.fit(other.measured, other.reference)
    fresh = PhysicsModel(("station", "mount")).fit(other.measured, other.reference)
    np.testing.assert_allclose(model.std_errors_["station"], fresh.std_errors_["station"], rtol=1e-9)
    assert not np.allclose(model.std_errors_["station"], first)


def test_effects_given_as_one_string_are_the_names_it_lists(poses):
    """"station,mount", as the command line takes it, was read letter by letter."""
    measured, reference = poses
    assert list(PhysicsModel("station,mount").fit(measured, reference).params_) == ["mount", "station"]
    assert list(PhysicsModel("station").fit(measured, reference).params_) == ["station"]
    assert CorrectionPipeline(effects="station, mount").fit(measured, reference).export_info()["effects"] == [
        "mount", "station"]


def test_a_warm_start_that_is_not_one_is_refused_naming_it(poses):
    """A fitted model of other effects met numpy's shapes ("could not be broadcast"); an
    unknown effect's theta was ignored without a word; an unfitted model, an AttributeError."""
    measured, reference = poses
    wider = PhysicsModel(("station", "mount", "range_scale")).fit(measured, reference)
    model = PhysicsModel(("station", "mount")).fit(measured, reference, warm_start=wider)   # its values, not its folds
    fresh = PhysicsModel(("station", "mount")).fit(measured, reference)
    for name in ("station", "mount"):
        np.testing.assert_allclose(model.params_[name], fresh.params_[name], atol=1e-6)
    for warm, expected in (({"foo": [1.0]}, r"warm_start names 'foo', which is not one of the effects fitted "
                                            r"\(mount, station\)"),
                           ({"station": [1.0, 2.0]}, r"warm_start\['station'\] must be 6 finite numbers, got \[1.0, 2.0\]"),
                           (PhysicsModel(("station", "mount")), "not fitted yet")):
        with pytest.raises(ValueError, match=expected):
            PhysicsModel(("station", "mount")).fit(measured, reference, warm_start=warm)


def test_a_value_that_is_not_finite_is_named_by_row_and_column(poses):
    measured, reference = poses
    broken = measured.copy()
    broken[5, 1] = np.nan
    with pytest.raises(ValueError, match=r"^measured contains NaN or infinite values: row 5, column 1 \(y\) is nan$"):
        PMC().fit(broken, reference)


def test_an_export_refuses_poses_that_are_not_pairs_and_a_folder(poses, tmp_path):
    """to_onnx wrote a training digest of 120 measured poses against 10 references, and on a
    folder failed after the work in a temporary file's name ('/.tmp.NNN.tmp' -> '/tmp')."""
    from posecorr.export import to_onnx
    from posecorr.safeio import OutputPathError

    measured, reference = poses
    model = PMC().fit(measured, reference)
    with pytest.raises(ValueError, match="^reference has 10 rows, expected 120 like measured$"):
        to_onnx(model, tmp_path / "m.onnx", measured=measured, reference=reference[:10])
    with pytest.raises(OutputPathError, match=f"^{tmp_path}: is a folder, expected a file name to write$"):
        to_onnx(model, tmp_path, measured=measured, reference=reference)
    assert not (tmp_path / "m.onnx").exists()


def test_with_rotation_is_true_or_false(poses):
    with pytest.raises(ValueError, match="^with_rotation must be True or False, got 'no'$"):   # was True
        PhysicsModel(("station", "mount"), with_rotation="no").fit(*poses)


def test_every_corrector_exports_itself(poses, tmp_path):
    """The design lists to_onnx among every corrector's methods; the physics stage and the
    rigid fit had none (posecorr.export.to_onnx took them)."""
    import onnxruntime as ort

    from posecorr.train.physics import RigidModel

    measured, reference = poses
    for model in (PhysicsModel(("station", "mount")), RigidModel()):
        model.fit(measured, reference)
        path = tmp_path / f"{type(model).__name__}.onnx"
        model.to_onnx(path, measured=measured, reference=reference)
        session = ort.InferenceSession(str(path))
        got = session.run(None, {"pose": measured[:8].astype(np.float32)})[0]
        np.testing.assert_allclose(got[:, :3], model.predict(measured[:8])[:, :3], atol=1e-5)


@pytest.mark.parametrize("make", [lambda: PhysicsModel(("station", "mount")), lambda: PMC(),
                                  lambda: CorrectionPipeline(effects=("station", "mount"))])
def test_score_names_the_argument_that_is_not_poses(poses, make):
    """The physics stage blamed the reference for one measured pose ('reference has 120 rows,
    expected 7 like measured'); the pipeline scored a reference of any shape."""
    measured, reference = poses
    model = make().fit(measured, reference)
    with pytest.raises(ValueError, match=r"^measured must be a 2-d array of shape \(N, 7\)"):
        model.score(measured[0], reference)
    with pytest.raises(ValueError, match="^reference has 10 rows, expected 120 like measured$"):
        model.score(measured, reference[:10])
    assert model.score(measured, reference) == pytest.approx(model.score(measured.tolist(), reference.tolist()))
