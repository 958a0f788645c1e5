"""Folds fitted in other processes (`train.folds.FoldPool`) give what one process gives, to the
last bit, and the models that come back are whole."""
from __future__ import annotations

import json

import numpy as np
import pytest

from bench import forms as study
from posecorr.analysis.diagnose import diagnose
from posecorr.effects import EFFECTS, unregister_effect
from posecorr.simulate import simulate_session
from posecorr.train.folds import FoldPool
from posecorr.train.pipeline import CorrectionPipeline, cross_validate
from posecorr.train.splits import KFold

pytestmark = pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="the pool forks its workers")


def _cv(table, effects, pool):
    return cross_validate(lambda: CorrectionPipeline(effects), table, KFold(5), seed=0, pool=pool)


def test_a_pools_cross_validation_is_one_process_s_to_the_last_bit():
    table = simulate_session(2, n=40, robot="ur5e").table
    alone = _cv(table, ("station", "mount", "sweep"), FoldPool(1))
    with FoldPool(2) as pool:
        pooled = _cv(table, ("station", "mount", "sweep"), pool)
    assert np.array_equal(alone.predicted, pooled.predicted)
    for a, b in zip(alone.fitted, pooled.fitted):
        for name, theta in a.physics_.params_.items():
            assert np.array_equal(theta, b.physics_.params_[name])
            # computed where first asked for, from the data that travelled beside the model
            assert np.array_equal(a.physics_.std_errors_[name], b.physics_.std_errors_[name], equal_nan=True)
        assert [e.name for e in b.physics_._chosen] == ["mount", "sweep", "station"]


def test_a_bare_physics_stage_crosses_whole():
    from posecorr.train.physics import PhysicsModel

    table = simulate_session(4, n=30).table
    runs = []
    for pool in (FoldPool(1), FoldPool(2)):
        with pool:
            runs.append(cross_validate(lambda: PhysicsModel(("station", "mount")), table, KFold(3), pool=pool))
    for a, b in zip(*(run.fitted for run in runs)):
        assert np.array_equal(a.std_errors_["mount"], b.std_errors_["mount"], equal_nan=True)
        assert [e.name for e in b._chosen] == ["mount", "station"]


def test_an_effect_registered_after_the_pool_forked_reaches_its_workers(tmp_path):
    table = simulate_session(3, n=30).table
    source = tmp_path / "late_effect.py"
    source.write_text("from posecorr.effects import Effect, Param\n"
                      "class LateShift(Effect, name='late_shift'):\n"
                      "    params = (Param('d', 3, (0.0, 0.0, 0.0), 1e-3, 'm'),)\n"
                      "    def forward(self, p, R, theta, ctx):\n"
                      "        return p + theta[..., 0:3], R\n")
    from posecorr.effects import load_effect_file

    with FoldPool(2) as pool:
        _cv(table, ("station", "mount"), pool)        # the workers fork without late_shift
        load_effect_file(source)
        try:
            pooled = _cv(table, ("station", "mount", "late_shift"), pool)
            alone = _cv(table, ("station", "mount", "late_shift"), FoldPool(1))
        finally:
            unregister_effect("late_shift")
    assert np.array_equal(alone.predicted, pooled.predicted)


def test_the_diagnosis_in_two_processes_is_the_diagnosis_in_one():
    """A session whose proposal cuts a form to its terms: the cut form is registered during
    the diagnosis, and the pool's workers fork again to hold it."""
    table = study.session("strain", 1, "robot", n=40)
    study.hide_outside()
    alone = diagnose(table, study.BASE, workers=1)
    pooled = diagnose(table, study.BASE, workers=2)
    assert alone["proposal"] is not None and not [name for name in EFFECTS if name.startswith("_")]
    assert json.dumps(alone, sort_keys=True, default=str) == json.dumps(pooled, sort_keys=True, default=str)


def test_workers_must_be_a_whole_number_of_at_least_one():
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="workers must be a whole number >= 1"):
            FoldPool(bad)


def test_report_refuses_workers_without_a_diagnosis(tmp_path, capsys):
    from posecorr.cli import main

    data = tmp_path / "s.csv"
    from posecorr.data import write_table

    write_table(simulate_session(1, n=12).table, data)
    model = tmp_path / "m.onnx"
    assert main(["fit", str(data), "--effects", "station,mount", "--method", "none", "--cv", "3",
                 "-o", str(model)]) == 0
    capsys.readouterr()
    assert main(["report", str(data), "--model", str(model), "-o", str(tmp_path / "r.html"), "--no-diagnosis",
                 "--workers", "2"]) == 2
    assert "--workers sets the diagnosis's processes" in capsys.readouterr().err
