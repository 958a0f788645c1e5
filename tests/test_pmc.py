"""PMC (paper 2.3): exact recovery, ridge / CV, decode validity, namespace parity, Exp III."""
from __future__ import annotations

import numpy as np
import pytest
from sklearn.exceptions import NotFittedError

from posecorr import rotations
from posecorr.metrics import pose_metrics
from posecorr.train import PMC
from posecorr.train.base import decode_pose, encode_pose
from posecorr.train.pmc import n_features, quadratic_features


def random_poses(n, rng, spread=0.5):
    p = rng.uniform(-0.3, 0.3, (n, 3)) + np.array([0.0, -0.6, 0.5])
    q = rotations.matrix_to_quat(rotations.rotvec_to_matrix(rng.normal(0, spread, (n, 3))))
    return np.concatenate([p, q], axis=1)


def quadratic_map(x, rng, scale=0.05):
    """A random full quadratic map of the columns of x (independent of PMC's code)."""
    d = x.shape[1]
    A = rng.normal(0, scale, (d, d, d))
    B = np.eye(d) + rng.normal(0, scale, (d, d))
    c = rng.normal(0, scale, d)
    return np.einsum("ni,kij,nj->nk", x, A, x) + x @ B.T + c


def test_feature_count_matches_paper():
    # eqs. 29-37: d linear + d(d+1)/2 quadratic + constant
    for d, expected in ((3, 10), (6, 28), (7, 36), (12, 91), (9, 55)):
        assert n_features(d) + 1 == expected
    x = np.arange(6.0).reshape(2, 3)
    f = quadratic_features(x)
    assert f.shape == (2, 9)
    np.testing.assert_allclose(f[1], [3, 4, 5, 9, 12, 15, 16, 20, 25])


def test_recovers_exact_quadratic_position_map():
    rng = np.random.default_rng(1)
    meas = random_poses(200, rng)
    ref = meas.copy()
    ref[:, :3] = quadratic_map(meas[:, :3], rng)
    model = PMC("pos").fit(meas, ref)
    test = random_poses(50, rng)
    want = test.copy()
    rng2 = np.random.default_rng(1)
    random_poses(200, rng2)
    want[:, :3] = quadratic_map(test[:, :3], rng2)
    got = model.predict(test)
    assert np.max(np.abs(got[:, :3] - want[:, :3])) < 1e-9
    # position-only passes the orientation through (sign-canonical)
    np.testing.assert_allclose(got[:, 3:], rotations.canonical_quat(test[:, 3:]), atol=1e-15)


@pytest.mark.parametrize("rep", ["eaa", "quat", "R", "zhou"])
def test_recovers_exact_quadratic_vector_map(rep):
    rng = np.random.default_rng(2)
    meas = random_poses(300, rng, spread=0.3)
    X = encode_pose(meas, rep)
    Y = quadratic_map(X, rng, scale=0.01)
    model = PMC(rep)
    model._fit_vectors(X, Y, None)
    model.n_features_in_ = 7
    assert np.max(np.abs(model._core(X) - Y)) < 1e-9


def test_ridge_shrinks_towards_identity_and_cv_picks_from_grid():
    rng = np.random.default_rng(3)
    meas = random_poses(60, rng)
    ref = meas.copy()
    ref[:, :3] += rng.normal(0, 1e-3, (60, 3))  # pure noise: the best correction is none
    heavy = PMC("pos", alpha=1e6).fit(meas, ref)
    np.testing.assert_allclose(heavy.predict(meas)[:, :3], meas[:, :3] + np.mean(ref[:, :3] - meas[:, :3], 0),
                               atol=1e-5)
    cv = PMC("pos", alpha="cv", alpha_grid=(0.0, 1e-4, 1e-2, 1.0)).fit(meas, ref)
    assert cv.alpha_ in (0.0, 1e-4, 1e-2, 1.0)
    assert cv.cv_scores_[cv.alpha_] == min(cv.cv_scores_.values())
    assert cv.alpha_ > 0  # on pure noise the unregularised fit is never the CV optimum
    assert not hasattr(cv.set_params(alpha=0.0).fit(meas, ref), "cv_scores_")   # no scores left from the last fit
    with pytest.raises(ValueError):
        PMC("pos", alpha="bogus").fit(meas, ref)


@pytest.mark.parametrize("rep", ["eaa", "quat", "R", "zhou"])
def test_decode_always_gives_proper_rotations(rep):
    rng = np.random.default_rng(4)
    size = rotations.REPRESENTATIONS[rep].size
    raw = np.concatenate([rng.normal(0, 1, (500, 3)), rng.normal(0, 2, (500, size))], axis=1)
    raw[:5, 3:] = 0.0  # degenerate outputs too
    pose = decode_pose(raw, np.tile([0, 0, 0, 1.0, 0, 0, 0], (500, 1)), rep)
    q = pose[:, 3:]
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    R = rotations.quat_to_matrix(q)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-10)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-10)


@pytest.mark.parametrize("rep", ["pos", "eaa", "quat", "R", "zhou"])
def test_forward_torch_equals_predict_numpy(rep):
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(5)
    meas = random_poses(120, rng, spread=0.4)
    ref = random_poses(120, rng, spread=0.4) * 0.01 + meas * 0.99
    ref[:, 3:] /= np.linalg.norm(ref[:, 3:], axis=1, keepdims=True)   # the blend of two rotations, a rotation
    model = PMC(rep).fit(meas, ref)
    test = random_poses(40, rng, spread=0.4)
    out = model.forward(torch.tensor(test, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(out, model.predict(test), atol=1e-12, rtol=0)


def test_contract_score_params_and_errors():
    rng = np.random.default_rng(6)
    meas = random_poses(80, rng)
    ref = meas.copy()
    ref[:, :3] += 0.01 * meas[:, :3] ** 2
    model = PMC("zhou").fit(meas, ref)
    assert model.score(meas, ref) == pytest.approx(-pose_metrics(ref, model.predict(meas))["rmse_total"])
    assert model.get_params()["representation"] == "zhou"
    sklearn_base = pytest.importorskip("sklearn.base")
    clone = sklearn_base.clone(model)
    assert not hasattr(clone, "coef_") and clone.representation == "zhou"
    info = model.export_info()
    assert info["method"] == "pmc" and info["representation"] == "zhou" and info["trainer"] == "lstsq"
    # a penalty (fit chooses one by cross-validation) is a ridge fit: it said "lstsq"
    assert PMC("zhou", alpha=0.1).fit(meas, ref).export_info()["trainer"] == "ridge"
    with pytest.raises(ValueError):
        PMC("euler").fit(meas, ref)
    with pytest.raises(ValueError):
        model.predict(meas[:, :6])
    with pytest.raises(NotFittedError):  # scikit-learn's, as its estimators raise
        PMC("R").predict(meas)
    with pytest.raises(ValueError):
        PMC("R").fit(meas[:20], ref[:20])  # 91 coefficients need more than 20 poses


@pytest.fixture(scope="module")
def exp3():
    simulate = pytest.importorskip("posecorr.simulate")
    return simulate.simulate(3, seed=0)


@pytest.mark.parametrize("rep", ["R", "zhou"])
def test_exp3_pmc_improves_to_the_noise_floor(exp3, rep):
    from posecorr.train.protocol import fit_one
    from posecorr.train.spec import ModelSpec

    res = fit_one(exp3.table, ModelSpec("pmc", rep), seed=0)
    # measured 51.6x (R) and 47.4x (zhou); rmse_total 1.04x and 1.13x the floor
    assert res.test["improvement_total"] >= 35.0
    assert res.test["rmse_total"] >= 0.9 * exp3.noise_floor["rmse_total"]  # cannot beat the noise
    assert res.test["rmse_total"] <= 1.25 * exp3.noise_floor["rmse_total"]


@pytest.mark.parametrize("rep", ["R", "zhou", "quat"])
def test_a_yaw_only_session_exports_and_a_tilt_stays_near_the_correction(tmp_path, rep):
    """Exp II turns the tracker about one axis: the tilt columns hold noise only. Scaled per
    column, the ridge let them carry terms that moved a pose tilted 5 deg by decimetres to metres
    and took float32 rounding past the export's parity check (seeds 0 and 2 refused, R and
    zhou). The export's own check against onnxruntime is the truth here, and the move of a
    tilted pose against the largest correction on the training poses."""
    from posecorr.export.parity import quat_multiply
    from posecorr.simulate import simulate
    from posecorr.train.pipeline import CorrectionPipeline

    table = simulate(2, seed=2).table
    M, R = table.measured, table.reference
    model = CorrectionPipeline((), PMC(rep, alpha="cv")).fit(M, R)
    model.to_onnx(tmp_path / "m.onnx", measured=M, reference=R)   # parity refused: raises
    largest = np.max(np.linalg.norm(model.predict(M)[:, :3] - M[:, :3], axis=1))
    tilt = np.array([np.cos(np.radians(2.5)), np.sin(np.radians(2.5)), 0.0, 0.0])
    tilted = np.concatenate([M[:, :3], quat_multiply(M[:, 3:], tilt[None])], axis=1)
    moved = np.max(np.linalg.norm(model.predict(tilted)[:, :3] - M[:, :3], axis=1))
    assert moved <= 3.0 * largest, (moved, largest)


def test_fit_says_where_a_model_extrapolates(tmp_path, capsys):
    """A PMC in eaa fitted on Exp II (yaw only; the CV keeps its tilt terms) moves poses of
    other orientations by metres, which the runtimes accept (they bound positions, not
    orientations): `fit` says so, with the figures. onnxruntime on the written file is the
    truth of the claim; on Exp III (every orientation) nothing is said."""
    from posecorr.cli import main
    from posecorr.data import write_table
    from posecorr.export.parity import run_onnx
    from posecorr.simulate import simulate

    said = {}
    for experiment, rep in ((2, "eaa"), (3, "zhou")):
        table = simulate(experiment, seed=0).table
        data, model = tmp_path / f"e{experiment}.csv", tmp_path / f"e{experiment}.onnx"
        write_table(table, data)
        capsys.readouterr()
        assert main(["fit", str(data), "--method", "pmc", "--representation", rep, "-o", str(model)]) == 0
        said[experiment] = [line for line in capsys.readouterr().out.splitlines() if "it extrapolates" in line]
        tilted = table.measured.copy()
        tilted[:, 3:] = rotations.matrix_to_quat(rotations.quat_to_matrix(tilted[:, 3:]) @ rotations.rotvec_to_matrix(
            np.array([0.5, 0.0, 0.0])))
        moved = np.linalg.norm(run_onnx(model, tilted)[:, :3] - tilted[:, :3], axis=1).max()
        largest = np.linalg.norm(run_onnx(model, table.measured)[:, :3] - table.measured[:, :3], axis=1).max()
        assert (moved > 10 * largest) == (experiment == 2), (experiment, moved, largest)
    assert len(said[2]) == 1 and " times its largest correction of the training poses " in said[2][0], said
    assert said[3] == [], said


def test_the_extrapolation_note_compares_like_with_like():
    """The note compared the reach, margin included (twice the largest plus 1 cm), with the
    training poses' largest correction: a sub-millimetre model was said to extrapolate, and a
    model that leaves its training poses as they are divided by zero."""
    from posecorr.fitting import extrapolation_note

    def note(training, accepted):
        return extrapolation_note({"largest_correction": {"training": [training, 0.0], "accepted": [accepted, 0.0]}})

    assert note(0.0005, 0.004) is None                # 8 times, and under a centimetre
    assert note(0.01, 0.09) is None                   # 9 times
    assert "11 times its largest correction" in note(0.01, 0.11)
    assert "where it leaves the training poses as they are" in note(0.0, 0.5)
    assert extrapolation_note({"largest_correction": None}) is None   # a reach given, not measured
