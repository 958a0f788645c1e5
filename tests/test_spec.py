"""The model spec (train/spec.py), the held-out plans (train/splits.py) and LM / BR as steps of
the shared training loop."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from posecorr.train.spec import ModelSpec, spec_from_options
from posecorr.train.splits import FixedSplit, HeldOut, KFold, LeaveOneOut, parse_plan, split_indices

ROOT = Path(__file__).resolve().parent.parent


# --- the spec ---------------------------------------------------------------------------------

def test_shipped_models_are_their_specs():
    """Every shipped model file is named and described by its spec exactly as models/index.json
    (written when the models were built) and the file's own metadata record it."""
    pytest.importorskip("onnx")
    from posecorr.controller.onnx_meta import read_info
    from tools.models import SPECS

    index = {m["file"]: m for m in json.loads((ROOT / "models" / "index.json").read_text())["models"]}
    assert {spec.name + ".onnx" for spec in SPECS} == set(index)
    for spec in SPECS:
        model, entry = spec.model, index[spec.name + ".onnx"]
        assert (entry["method"], entry["representation"], entry["activation"], entry["hidden"], entry["trainer"]) \
            == (model.method, model.representation, model.activation, list(model.hidden), model.trainer)
        info = read_info(ROOT / "models" / (spec.name + ".onnx"))
        assert info["representation"] == model.representation
        if model.is_network:
            assert model.file_name == spec.name + ".onnx"
            assert info["architecture"] == "-".join(map(str, model.hidden))
            assert (info["activation"], info["trainer"]) == (model.activation, model.trainer)


def test_spec_builds_the_estimator_it_names():
    from posecorr.train import MLP, PMC

    network = ModelSpec("mlp", "quat", "8-8", "logsig", "rp", epochs=7, options={"lr": 0.05})
    core = network.make(seed=4)
    assert isinstance(core, MLP)
    assert (core.representation, core.hidden, core.activation, core.trainer, core.epochs, core.lr,
            core.random_state) == ("quat", (8, 8), "logsig", "rp", 7, 0.05, 4)
    assert network.key == "quat-logsig-8-8-rp[epochs=7,lr=0.05]"
    assert network.label == "logsig (8-8)/3" and network.stem == "mlp-quat-logsig-8x8-rp"
    # a PMC has no network settings: they are dropped, so equal PMCs are one spec
    pmc = ModelSpec("pmc", "R", hidden=(5,), trainer="lm", epochs=3)
    assert pmc == ModelSpec("pmc", "R") and pmc.key == "R-pmc" and pmc.label == "PMC"
    assert isinstance(pmc.make(), PMC) and pmc.make().alpha == 0.0
    # `fit` gives a PMC its cross-validated ridge penalty; the network label overrides --hidden
    assert spec_from_options("pmc", "R").make().alpha == "cv"
    assert spec_from_options("mlp", "zhou", hidden=(3,), network="2/1").hidden == (10,)
    assert ModelSpec("none").make() is None and not ModelSpec("none").has_core
    with pytest.raises(ValueError, match="a setting of the spec"):
        ModelSpec("mlp", "zhou", options={"epochs": 5})
    with pytest.raises(ValueError, match="unknown method 'svm'"):
        ModelSpec("svm")


# --- the plans --------------------------------------------------------------------------------

@pytest.mark.parametrize("n,k", [(10, 2), (23, 5), (7, 7)])
def test_kfold_partitions_whole_poses(n, k):
    folds = KFold(k).folds(n, seed=3)
    assert len(folds) == k
    held = np.concatenate([h for _, h in folds])
    assert sorted(held.tolist()) == list(range(n))                  # every pose held out once
    assert max(len(h) for _, h in folds) - min(len(h) for _, h in folds) <= 1
    for train, h in folds:
        assert sorted(np.concatenate([train, h]).tolist()) == list(range(n))
        assert not np.intersect1d(train, h).size
    again = KFold(k).folds(n, seed=3)
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(folds, again))
    if k < n:
        other = KFold(k).folds(n, seed=4)
        assert not all(np.array_equal(a[1], b[1]) for a, b in zip(folds, other))


def test_plans_parse_once_and_say_what_they_are():
    assert [h.tolist() for _, h in LeaveOneOut().folds(4)] == [[0], [1], [2], [3]]
    assert parse_plan(None) == parse_plan("none") == FixedSplit()
    assert parse_plan("loo") == LeaveOneOut() and parse_plan("7") == KFold(7) == parse_plan(7)
    for plan in (FixedSplit(), LeaveOneOut(), KFold(4)):
        assert parse_plan(str(plan)) == plan
    assert FixedSplit().heldout is HeldOut.TEST and KFold(3).heldout is LeaveOneOut().heldout is HeldOut.CV
    for tr, fixed in zip(split_indices(200, 5, 2), FixedSplit().indices(200, 5, 2)):
        assert np.array_equal(tr, fixed)
    for bad in ("x", "1", "-3"):
        with pytest.raises(ValueError):
            parse_plan(bad)
    with pytest.raises(ValueError, match="5 folds need at least 5 poses"):
        KFold(5).folds(4)


# --- LM and BR in the shared loop ---------------------------------------------------------------

@pytest.mark.parametrize("trainer", ["lm", "br"])
def test_levenberg_marquardt_gives_up_at_mu_max_in_the_shared_loop(trainer):
    """A damping held at its cap (mu = mu_max, mu_dec 1) ends the run at the first failed step
    with "Maximum MU reached"; the point it could not leave is the last one recorded, every
    history list has a value per recorded epoch, and trainlm returns its best validation
    network, trainbr its last."""
    from posecorr.train import MLP
    from posecorr.train.base import Validation, encode_pose
    from posecorr.simulate import simulate

    table = simulate(3, seed=0).table.subset(np.arange(400))
    M, R = table.measured, table.reference
    model = MLP("pos", (5,), "logsig", trainer, epochs=60, mu=1e-3, mu_max=1e-3, mu_dec=1.0, random_state=2).fit(
        M[:300], R[:300], validation=Validation(M[300:], R[300:]))
    assert model.stop_reason_ == "Maximum MU reached" and model.n_epochs_ < 60
    assert {len(v) for v in model.history_.values()} == {model.n_epochs_ + 1}
    assert model.history_["mse"][-1] == model.history_["mse"][-2]       # the step did not move
    assert all(mu == 1e-3 for mu in model.history_["mu"][:-1]) and model.history_["mu"][-1] > 1e-3
    val = np.mean((encode_pose(model.predict(M[300:]), "pos") - encode_pose(R[300:], "pos")) ** 2)
    want = min(model.history_["val_mse"]) if trainer == "lm" else model.history_["val_mse"][-1]
    assert val == pytest.approx(want, rel=1e-9)


def test_one_plan_rule_for_small_tables():
    """train/splits.py's plan_for is the one rule: a table's held-out score leaves one out up
    to LOO_MAX_POSES poses; a choice nested in an outer fold only below NESTED_LOO_BELOW."""
    from posecorr.train.splits import LOO_MAX_POSES, NESTED_LOO_BELOW, KFold, LeaveOneOut, plan_for

    assert isinstance(plan_for(LOO_MAX_POSES), LeaveOneOut) and isinstance(plan_for(LOO_MAX_POSES + 1), KFold)
    assert isinstance(plan_for(NESTED_LOO_BELOW - 1, nested=True), LeaveOneOut)
    assert isinstance(plan_for(NESTED_LOO_BELOW, nested=True), KFold)


def test_fit_sizes_its_default_network_to_the_table():
    """The paper's 20-20-20-20 in zhou has (9+1)20 + 3(21)20 + 21(9) = 1,649 weights; with ten
    numbers (9 a pose) for each it wants 1,833 poses: from there on it is the default, below
    it the session network (5 units, 200 epochs), and the choice is said. A method that is not
    a network is left alone."""
    from posecorr.train.spec import (DEFAULT_HIDDEN, SESSION_EPOCHS, SESSION_HIDDEN, session_network)

    spec = spec_from_options("mlp", "zhou")
    assert spec.make().n_weights() == 10 * 20 + 3 * 21 * 20 + 21 * 9 == 1649
    small, said = session_network(spec, 1832)
    assert (small.hidden, small.epochs) == (SESSION_HIDDEN, SESSION_EPOCHS)
    assert small.make().residual and "1,649 weights" in said and "1,833 poses" in said
    paper, said = session_network(spec, 1833)
    assert (paper.hidden, paper.epochs) == (DEFAULT_HIDDEN, None) and "16,497 numbers" in said
    # position only: 3 numbers a pose, (3+1)20 + 3(21)20 + 21(3) = 1,403 weights
    small, said = session_network(spec_from_options("mlp", "pos"), 4676)
    assert small.hidden == SESSION_HIDDEN and "4,677 poses" in said
    pmc = spec_from_options("pmc", "zhou")
    assert session_network(pmc, 10) == (pmc, "")
