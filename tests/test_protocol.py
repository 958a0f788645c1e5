"""The sweep protocol: splits, resumable store, tables, statistics, CLI-facing helpers."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from posecorr import rotations
from posecorr.data import PoseTable
from posecorr.train import protocol
from posecorr.train.protocol import build_grid, fit_one, run_sweep, split_indices
from posecorr.train.spec import ModelSpec


def synthetic_table(n=240, seed=0):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.1, 0.1, (n, 3)) + np.array([0.0, -0.6, 0.5])
    R = rotations.rotvec_to_matrix(rng.normal(0, 0.3, (n, 3)))
    ref_q = rotations.matrix_to_quat(R)
    meas_p = p + 0.01 * (p - p.mean(0)) ** 2 * 30 + 0.002 + rng.normal(0, 2e-4, (n, 3))
    meas_R = R @ rotations.rotvec_to_matrix(np.array([0.01, -0.02, 0.015]) + rng.normal(0, 3e-4, (n, 3)))
    return PoseTable(meas_p, rotations.matrix_to_quat(meas_R), p, ref_q)


def test_splits_are_disjoint_fixed_test_and_70_15_15():
    n = 1000
    tr0, va0, te0 = split_indices(n, seed=3, repeat=0)
    tr1, va1, te1 = split_indices(n, seed=3, repeat=1)
    np.testing.assert_array_equal(te0, te1)  # test set fixed across repeats
    assert (len(tr0), len(va0), len(te0)) == (700, 150, 150)
    assert len(np.intersect1d(tr0, va0)) == 0 and len(np.intersect1d(tr0, te0)) == 0
    assert sorted(np.concatenate([tr0, va0, te0]).tolist()) == list(range(n))
    assert not np.array_equal(va0, va1)  # a fresh train/validation split per repeat
    _, _, te_other = split_indices(n, seed=4, repeat=0)
    assert not np.array_equal(te0, te_other)


def test_grid_builder_and_labels():
    grid = build_grid("paper-exp3")
    assert len(grid) == 4 * (1 + 3 * 16 * 2)
    reduced = build_grid("reduced")
    assert {c.representation for c in reduced} == {"eaa", "quat", "R", "zhou"}
    assert sum(c.method == "pmc" for c in reduced) == 4
    cfg = ModelSpec("mlp", "zhou", (20, 20, 20, 20), "tansig", "br")
    assert cfg.label == "tansig 16/2" and cfg.name == "Zhou-tansig-16/2"
    assert cfg.key == "zhou-tansig-20-20-20-20-br"
    assert ModelSpec("pmc", "R").label == "PMC" and ModelSpec("pmc", "R").name == "R-PMC"
    custom = build_grid(representations=["zhou"], activations=["tansig"], trainers=["adam"],
                        architectures=["8-8"], include_pmc=False, options={"epochs": 5})
    assert len(custom) == 1 and custom[0].label == "tansig (8-8)/adam" and "epochs=5" in custom[0].key


def test_fit_one_reports_raw_and_test_blocks():
    table = synthetic_table()
    res = fit_one(table, ModelSpec("pmc", "zhou"), seed=1)
    assert set(res.test) >= {"rmse_pos", "rmse_rot", "rmse_total", "improvement_pos", "improvement_rot",
                             "improvement_total"}
    assert res.test["improvement_total"] == pytest.approx(res.raw["rmse_total"] / res.test["rmse_total"])
    assert res.test["improvement_total"] > 3
    assert len(res.test_index) == 36
    with pytest.raises(ValueError):
        fit_one(PoseTable(table.meas_p, table.meas_q, table.ref_p, None), ModelSpec("pmc", "zhou"))


def test_sweep_resumes_from_store_and_prints_tables(tmp_path, monkeypatch):
    table = synthetic_table()
    configs = [ModelSpec("pmc", "R"), ModelSpec("pmc", "zhou"), ModelSpec("pmc", "quat"),
               ModelSpec("mlp", "zhou", (4,), "tansig", "lm", epochs=3)]
    store = tmp_path / "runs.jsonl"
    first = run_sweep(table, configs[:2], repeats=4, store=store, workers=1, progress=False)
    assert len(first.rows) == 8
    assert len(store.read_text().splitlines()) == 8
    calls = []
    real = protocol.run_one

    def counting(*args, **kwargs):
        calls.append(args[1].key)
        return real(*args, **kwargs)

    monkeypatch.setattr(protocol, "run_one", counting)
    second = run_sweep(table, configs, repeats=4, store=store, workers=1, progress=False)
    # only the new configurations ran; the stored runs were reused unchanged
    assert sorted(set(calls)) == sorted(c.key for c in configs[2:]) and len(calls) == 8
    assert len(store.read_text().splitlines()) == 16
    old = {(r["key"], r["repeat"]): r["rmse_total"] for r in first.rows}
    for r in second.rows:
        if (r["key"], r["repeat"]) in old:
            assert r["rmse_total"] == old[(r["key"], r["repeat"])]
    summary = {s["key"]: s for s in second.summary()}
    zhou = summary["zhou-pmc"]
    vals = [r["rmse_total"] for r in second.rows if r["key"] == "zhou-pmc"]
    assert zhou["rmse_total"]["min"] == min(vals) and zhou["rmse_total"]["avg"] == pytest.approx(np.mean(vals))
    assert zhou["improvement_total"] == pytest.approx(second.raw["rmse_total"] / min(vals))
    text = second.format()
    assert "raw data" in text and "Zhou representation" in text and "Tier" in text and "Friedman" in text
    out = second.to_json()
    json.dumps(out)
    assert sum(len(t) for t in out["tiers"]) == 4


def test_sweep_in_worker_processes_matches_in_process(tmp_path):
    table = synthetic_table()
    configs = [ModelSpec("pmc", "zhou"), ModelSpec("pmc", "R")]
    a = run_sweep(table, configs, repeats=3, workers=1, progress=False)
    b = run_sweep(table, configs, repeats=3, workers=2, progress=False)
    ka = {(r["key"], r["repeat"]): r["rmse_total"] for r in a.rows}
    kb = {(r["key"], r["repeat"]): r["rmse_total"] for r in b.rows}
    assert ka == kb


def test_sweep_progress_in_a_log_is_whole_lines(tmp_path, capsys):
    """Where stderr is no terminal (a log, a pipe; pytest's capture), the progress is whole
    lines, never a bar's carriage returns, and the last names every run and the best so far,
    the store's runs included."""
    table = synthetic_table()
    configs = [ModelSpec("pmc", "zhou"), ModelSpec("pmc", "R")]
    store = tmp_path / "runs.jsonl"
    first = run_sweep(table, configs[:1], repeats=2, store=store, workers=1, progress=True)
    err = capsys.readouterr().err
    assert "\r" not in err
    best = min(first.rows, key=lambda r: r["rmse_total"])
    assert err.splitlines()[-1].startswith("sweep: 2/2 runs, ")
    assert err.splitlines()[-1].endswith(f"best {best['rmse_total']:.4g} {best['key']}")
    second = run_sweep(table, configs, repeats=2, store=store, workers=1, progress=True)
    best = min(second.rows, key=lambda r: r["rmse_total"])
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith("sweep: 4/4 runs, ") and last.endswith(f"best {best['rmse_total']:.4g} {best['key']}")


SWEEP_SCRIPT = """
from posecorr.simulate import simulate
from posecorr.train.protocol import run_sweep
from posecorr.train.spec import ModelSpec

def main():
    rows = run_sweep(simulate(3, seed=0).table, [ModelSpec("pmc", "zhou")], repeats=2, workers=2,
                     progress=False).rows
    print(len(rows), "runs")
"""


@pytest.mark.parametrize("guarded", [True, False])
def test_a_script_runs_the_sweep_on_workers(tmp_path, guarded):
    """Workers are forked: a script that calls run_sweep with two workers runs, with or
    without `if __name__ == "__main__":` (a pool that spawns its workers imports the main
    script in each, and an unguarded call would run again there)."""
    import subprocess
    import sys

    script = tmp_path / "sweep_script.py"
    script.write_text(SWEEP_SCRIPT + ('if __name__ == "__main__":\n    main()\n' if guarded else "main()\n"))
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "2 runs", r.stderr[-2000:]


AFTER_TORCH_SCRIPT = """
import torch
torch.set_num_threads({parent})
for _ in range(3):
    torch.tanh(torch.ones(1 << 20)).sum()
from posecorr.simulate import simulate
from posecorr.train.protocol import run_sweep
from posecorr.train.spec import ModelSpec
rows = run_sweep(simulate(3, seed=0).table, [ModelSpec("mlp", "zhou", (8,), "tansig", "lm", epochs=2)], repeats=2,
                 workers=2, threads=2, progress=False).rows
print(len(rows), "runs")
"""


@pytest.mark.parametrize("parent", [1, 2])
def test_a_sweep_after_torch_ran_on_threads_does_not_hang(parent):
    """A parent that ran torch on two threads forks workers that would wait forever on a
    second thread (GNU OpenMP's pool is not forked): the sweep runs them on one and says so.
    A parent that ran torch on one thread has no pool to lose; its workers keep two."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", AFTER_TORCH_SCRIPT.format(parent=parent)], capture_output=True,
                       text=True, timeout=240)
    assert r.returncode == 0 and r.stdout.strip() == "2 runs", r.stderr[-2000:]
    assert ("workers run 1 torch thread each, not 2" in r.stderr) == (parent == 2), r.stderr


def test_cross_validation_pools_out_of_fold_predictions():
    """`fit --cv`'s cross-validation (`pipeline.cross_validate`) of a bare core."""
    from posecorr.train.pipeline import CorrectionPipeline, cross_validate
    from posecorr.train.splits import KFold, LeaveOneOut

    table = synthetic_table(n=120)
    out = cross_validate(lambda: CorrectionPipeline(core=ModelSpec("pmc", "zhou").make()), table, KFold(4), seed=0)
    assert len(out.fold_rmse) == 4
    assert out.metrics["improvement_total"] == pytest.approx(out.raw["rmse_total"] / out.metrics["rmse_total"])
    # out-of-fold error is never better than the in-sample fit of the same model
    from posecorr.train import PMC
    from posecorr.metrics import pose_metrics
    full = PMC("zhou").fit(table.measured, table.reference)
    in_sample = pose_metrics(table.reference, full.predict(table.measured))["rmse_total"]
    assert out.metrics["rmse_total"] > in_sample
    small = synthetic_table(n=40)
    position_only = PoseTable(small.meas_p, small.meas_q, small.ref_p, None)
    loo = cross_validate(lambda: CorrectionPipeline(core=ModelSpec("pmc", "pos").make()), position_only,
                         LeaveOneOut())
    assert len(loo.fold_rmse) == 40 and loo.raw["rmse_rot"] is None


# --- the paper's grid, labels and reduction -------------------------------------------------

from posecorr.train.spec import ARCHITECTURES, network_label, parse_network  # noqa: E402
from posecorr.train.trainers import TRAINERS  # noqa: E402
from posecorr.train.protocol import GRID_PRESETS, SweepResult  # noqa: E402


@pytest.mark.parametrize("preset,networks,reps", [("paper-exp1", 1536, 1), ("paper-exp2", 384, 4),
                                                  ("paper-exp3", 96, 4)])
def test_presets_match_table_1_counts(preset, networks, reps):
    # paper section 2.4: 1536 networks in Exp I (12 algorithms x 8 activations x 16
    # architectures), 384 in Exp II (3 x 8 x 16), 96 in Exp III (2 x 3 x 16), per representation
    grid = build_grid(preset)
    assert sorted({c.representation for c in grid}) == sorted(GRID_PRESETS[preset]["representations"])
    assert len({c.representation for c in grid}) == reps
    for rep in {c.representation for c in grid}:
        mlps = [c for c in grid if c.representation == rep and c.method == "mlp"]
        assert len(mlps) == networks
        assert len({(c.activation, c.hidden, c.trainer) for c in mlps}) == networks
        assert sum(c.method == "pmc" and c.representation == rep for c in grid) == 1
        assert all(c.trainer in TRAINERS for c in mlps)
    if preset == "paper-exp1":
        assert {network_label(ARCHITECTURES[0], c.trainer).split("/")[1] for c in grid if c.method == "mlp"} \
            == {str(n) for n in range(1, 13)}


def test_labels_are_the_papers_and_one_per_network():
    cfg = ModelSpec("mlp", "zhou", (20, 20, 20, 20), "tansig", "br")
    assert cfg.label == "tansig 16/2" and cfg.name == "Zhou-tansig-16/2"
    assert ModelSpec("mlp", "R", (5, 5, 5), "radbas", "lm").label == "radbas 9/1"  # table 1's own example
    # one layer of 16 is not table 1's architecture 16: different networks, different labels
    assert ModelSpec("mlp", "zhou", (16,), "tansig", "lm").label == "tansig (16)/1"
    assert ModelSpec("mlp", "zhou", (8, 8), "tansig", "adam").label == "tansig (8-8)/adam"
    grid = build_grid("paper-exp1", architectures=[*ARCHITECTURES, (16,), (8, 8), (3,)],
                      trainers=list(TRAINERS))
    mlps = [c for c in grid if c.method == "mlp"]
    assert len({c.label for c in mlps}) == len(mlps)
    for c in mlps:  # every label reads back as its network
        assert parse_network(c.label.split(" ", 1)[1]) == (c.hidden, c.trainer)
    assert parse_network("16/2") == ((20, 20, 20, 20), "br")
    assert parse_network("(16)/lm") == ((16,), "lm")
    for bad in ("16", "17/1", "16/13", "x/1", "(0)/1"):
        with pytest.raises(ValueError):
            parse_network(bad)


def test_reduction_keeps_the_best_network_per_representation_and_activation():
    from scipy.stats import friedmanchisquare

    rng = np.random.default_rng(7)
    configs = build_grid(representations=["R", "zhou"], activations=["logsig", "tansig"], networks=["1/1", "16/2"])
    rows, totals = [], {}
    for c in configs:
        base = rng.uniform(0.005, 0.05)
        for r in range(5):
            value = float(base + rng.uniform(0, 0.01))
            totals.setdefault(c, []).append(value)
            rows.append({"key": c.key, "repeat": r, "seconds": 0.1, "rmse_pos": value / 2, "rmse_rot": value / 2,
                         "rmse_total": value})
    result = SweepResult(configs, rows, {"rmse_pos": 0.02, "rmse_rot": 0.03, "rmse_total": 0.05}, 5)
    # independently: per (representation, method, activation) the lowest minimum over the runs
    want = set()
    for rep in ("R", "zhou"):
        want.add(ModelSpec("pmc", rep))
        for act in ("logsig", "tansig"):
            group = [c for c in configs if c.representation == rep and c.activation == act]
            want.add(min(group, key=lambda c: min(totals[c])))
    methods = result.methods()
    assert set(methods) == want and len(methods) == 6
    st = result.statistics()
    assert [c.name for c in st["configs"]] == [c.name for c in methods]
    chi2, p = friedmanchisquare(*[totals[c] for c in methods])
    assert st["friedman"].statistic == pytest.approx(chi2) and st["friedman"].p_value == pytest.approx(p)
    assert len(st["comparisons"]) == 15
    text = result.format(comparisons=True, table=4)
    assert "Table 4" in text and "Table 5" in text and "Table A1" in text and "6 methods" in text
    for c in methods:
        assert c.name in text
    out = result.to_json()
    assert len(out["methods"]) == 6 and len(out["summary"]) == len(configs)


def test_sweep_cli_takes_the_papers_network_labels(tmp_path, capsys):
    from posecorr.cli import main
    from posecorr.data import write_table

    data = tmp_path / "poses.csv"
    write_table(synthetic_table(n=120), data)
    argv = ["sweep", str(data), "--representations", "zhou", "--activations", "purelin", "--networks", "1/1,(3)/1",
            "--epochs", "2", "--repeats", "2", "--workers", "1", "--threads", "1", "--store",
            str(tmp_path / "s.jsonl"), "--comparisons"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "purelin 1/1" in out or "purelin (3)/1" in out  # the better of the two is the purelin method
    assert "Zhou-PMC" in out and "Friedman" in out and "2 methods" in out
    assert main(argv[:7] + ["17/1"] + argv[8:]) == 2
    assert "architecture '17'" in capsys.readouterr().err


@pytest.mark.parametrize("n", range(3, 16))
def test_the_fewest_poses_a_fold_fits_on_are_those_of_its_folds(n: int) -> None:
    """`fewest_to_fit` against the folds themselves: the smallest training set of each plan,
    and, nested, the smallest an inner plan (`plan_for(m, nested=True)`) leaves in any fold."""
    from posecorr.train.splits import KFold, LeaveOneOut, fewest_to_fit, plan_for

    def smallest(m: int, plan, nested: bool) -> int:
        sizes = []
        for train, _ in plan.folds(m, seed=n):
            inner = plan_for(len(train), nested=True)
            sizes.append(smallest(len(train), inner, False) if nested and len(train) > 1 else len(train))
        return min(sizes)

    for plan in [LeaveOneOut(), *(KFold(k) for k in range(2, n + 1))]:
        for nested in (False, True):
            assert fewest_to_fit(n, plan, nested) == smallest(n, plan, nested), (plan, nested)


def test_folds_too_small_to_fit_are_refused_with_the_folds_that_fit() -> None:
    from posecorr.train.splits import FixedSplit, KFold, LeaveOneOut, MIN_FIT_POSES, fewest_to_fit, \
        require_enough_to_fit

    with pytest.raises(ValueError, match=r"^4 rows, but with 2 folds a fold fits on 2 of them, and a fit needs at "
                                         r"least 3: more folds \(--cv 4\)$"):
        require_enough_to_fit(4, KFold(2))
    assert fewest_to_fit(4, KFold(4)) >= MIN_FIT_POSES
    with pytest.raises(ValueError, match=r"inside a fold \(auto's\) fits on 2 of them.*: at least 5 rows \(with --cv loo\)$"):
        require_enough_to_fit(4, LeaveOneOut(), nested=True)
    assert fewest_to_fit(5, LeaveOneOut(), nested=True) >= MIN_FIT_POSES
    require_enough_to_fit(6, KFold(3), nested=True)
    require_enough_to_fit(4, FixedSplit())  # the protocol's split: tables that small are cross-validated first
    # more folds than rows said only "100 folds need at least 100 poses, got 50", once the fit began
    with pytest.raises(ValueError, match=r"^50 rows, but 100 folds need at least 100: at most 50 folds \(--cv 50\), "
                                         r"or --cv loo$"):
        require_enough_to_fit(50, KFold(100))
    require_enough_to_fit(50, KFold(50))


def test_a_grid_the_split_cannot_train_is_refused_before_any_run(tmp_path):
    """A 50-pose session: the split trains on 34 poses, fewer than a quadratic PMC on
    quaternions (1 + 7 + 28 terms) or on zhou's 9 numbers (1 + 9 + 45) takes. The sweep says so
    before any run, with the rows it would need; a grid without them runs."""
    from posecorr.simulate import simulate

    table = simulate(3, seed=0).table.subset(np.arange(50))
    grid = [ModelSpec("pmc", rep) for rep in ("pos", "quat", "zhou")]
    store = tmp_path / "store.jsonl"
    with pytest.raises(ValueError) as refused:
        run_sweep(table, grid, repeats=2, store=store, workers=1, progress=False)
    message = str(refused.value)
    assert message.startswith("50 rows: the sweep's split trains on 34 of them, and 2 of its 3 configurations")
    assert "zhou-pmc 55, quat-pmc 36 poses" in message
    rows = next(m for m in range(50, 200) if m - 2 * round(0.15 * m) >= 55)
    assert f"at least {rows} rows" in message and not store.exists()
    assert len(run_sweep(table, grid[:1], repeats=2, workers=1, progress=False).rows) == 2


def _kabsch_test_rmse_pos(table, fitted_on, test) -> float:
    """An independent plain Kabsch fit (ref = R meas + t, positions alone), scored on `test`."""
    P, Q = table.meas_p[fitted_on], table.ref_p[fitted_on]
    Pc, Qc = P - P.mean(0), Q - Q.mean(0)
    U, _, Vt = np.linalg.svd(Pc.T @ Qc)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    t = Q.mean(0) - R @ P.mean(0)
    miss = table.meas_p[test] @ R.T + t - table.ref_p[test]
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))))


def test_on_unregistered_frames_the_sweep_says_what_the_rigid_fit_reaches():
    """Raw measures the frames' offset on a session in the tracker's own frame: the sweep
    names the best rigid fit on the same test poses (no worse than an independent Kabsch fit)
    and how the best method compares with it; on the paper's registered data it says nothing."""
    from posecorr.simulate import simulate, simulate_session

    session = simulate_session(2, n=50).table
    result = run_sweep(session, [ModelSpec("pmc", "pos")], repeats=2, workers=1, progress=False)
    train, val, test = split_indices(session.n, 0, 0)
    assert result.frames_unregistered and result.raw["rmse_pos"] > 1.0
    assert result.rigid["rmse_pos"] <= _kabsch_test_rmse_pos(session, np.union1d(train, val), test) * (1 + 1e-9)
    pmc = result.summary()[0]["rmse_total"]["min"]
    ratio = max(pmc, result.rigid["rmse_total"]) / min(pmc, result.rigid["rmse_total"])
    text = result.format()
    assert (f"against {1e3 * result.rigid['rmse_pos']:.4g} mm for the best rigid fit ({result.rigid['name']})"
            in text) and f"{ratio:.3g}x {'lower' if pmc <= result.rigid['rmse_total'] else 'higher'}" in text
    assert json.loads(json.dumps(result.to_json()))["frames_unregistered"] is True

    registered = run_sweep(simulate(3, seed=0).table.subset(np.arange(300)), [ModelSpec("pmc", "pos")], repeats=1,
                           workers=1, progress=False)
    assert not registered.frames_unregistered and "unregistered" not in registered.format()
    assert registered.to_json()["rigid"]["rmse_pos"] < registered.raw["rmse_pos"]


def test_a_cross_validated_fit_reports_its_folds_as_they_start():
    """`fit --cv` said one line and then nothing for minutes (an MLP on each of 11 folds): the
    folds are reported as they start, at most about ten lines."""
    from posecorr.simulate import simulate_session
    from posecorr.train.pipeline import fit_table
    from posecorr.train.splits import KFold, LeaveOneOut

    table = simulate_session(3, n=30).table
    for plan, n_folds in ((LeaveOneOut(), 30), (KFold(5), 5)):
        said: list[str] = []
        fit_table(table, ["station", "mount"], ModelSpec("none"), plan, progress=said.append)
        folds = [line for line in said if line.startswith("fold ")]
        step = max(1, n_folds // 10)
        assert folds == [f"fold {k + 1}/{n_folds}" for k in range(0, n_folds, step)], said


@pytest.mark.parametrize("representation", ["zhou", "quat", "pos"])
def test_a_core_knows_its_weights_before_the_fit(representation):
    """`n_weights` (before the fit) is the count of numbers the fit sets."""
    from posecorr.simulate import simulate
    from posecorr.train.mlp import MLP
    from posecorr.train.pmc import PMC

    table = simulate(1, seed=0).table
    for core in (MLP(representation, hidden=(5, 4), epochs=2), PMC(representation), PMC(representation, degree=1)):
        expected = core.n_weights()
        core.fit(table.measured, table.reference)
        arrays = (core.coefs_ + core.intercepts_) if isinstance(core, MLP) else (core.coef_, core.intercept_)
        assert expected == sum(np.size(a) for a in arrays), core


def test_a_network_with_more_weights_than_numbers_is_noted_before_the_work():
    """The default network (20-20-20-20, 1,649 weights on zhou's 9 numbers) on 11 poses: each
    leave-one-out fit has 10 poses, 90 numbers. Said before the first fold, and kept in the
    notes; an affine PMC on positions there (12 weights against 30 numbers) is no surprise."""
    from posecorr.simulate import simulate_session
    from posecorr.train.pipeline import fit_table
    from posecorr.train.splits import LeaveOneOut

    table = simulate_session(3, n=11, spread="full", position_only=False, unremovable=0.0).table
    said: list[str] = []
    report = fit_table(table, [], ModelSpec("mlp", epochs=1), LeaveOneOut(), progress=said.append)
    note = "mlp-zhou has 1,649 weights to fit on 10 poses (90 numbers) in each fit"
    assert said[0].startswith(f"note: {note}") and said[1].startswith("cross-validating"), said[:2]
    assert any(n.startswith(note) for n in report.notes)
    said.clear()
    report = fit_table(table, [], ModelSpec("pmc", "pos", options={"degree": 1}), LeaveOneOut(), progress=said.append)
    assert not any("weights" in line for line in said + report.notes)


def test_a_damaged_line_inside_the_store_is_said(tmp_path, capsys):
    """A line inside the store that is no result (hand-edited, a disk error) was skipped in
    silence: its run was done again and appended. It is now named by line in one warning, and
    left as it is; the other runs are reused."""
    table = synthetic_table()
    configs = [ModelSpec("pmc", "zhou")]
    store = tmp_path / "runs.jsonl"
    run_sweep(table, configs, repeats=3, store=store, workers=1, progress=False)
    lines = store.read_text().splitlines()
    lines[1] = "garbage"
    store.write_text("\n".join(lines + ['{"no": "key"}']) + "\n")
    capsys.readouterr()
    again = run_sweep(table, configs, repeats=3, store=store, workers=1, progress=False)
    assert len(again.rows) == 3
    err = capsys.readouterr().err.splitlines()
    assert [e for e in err if "no sweep result" in e] == [
        f"posecorr: warning: {store}: lines 2, 4 are no sweep result (not a JSON row with a key and a repeat): "
        "left as they are and not read; a run they held is done again"], err
    kept = store.read_text().splitlines()
    assert kept[1] == "garbage" and len(kept) == 5


def test_a_store_of_another_table_is_said_and_kept(tmp_path, capsys):
    """A store holding another table's runs took this table's beside them without a word
    (nothing mixed: rows are matched by the table's fingerprint and the seed); one warning now
    says so, and the other runs stay."""
    configs = [ModelSpec("pmc", "zhou")]
    store = tmp_path / "runs.jsonl"
    run_sweep(synthetic_table(), configs, repeats=2, store=store, workers=1, progress=False)
    capsys.readouterr()
    other = synthetic_table(n=300)
    again = run_sweep(other, configs, repeats=2, store=store, workers=1, progress=False)
    assert len(again.rows) == 2
    err = capsys.readouterr().err.splitlines()
    assert [e for e in err if "another table" in e] == [
        f"posecorr: warning: {store}: holds 2 runs of another table or seed: kept as they are, not resumed; "
        "this sweep's runs are added beside them"], err
    assert len(store.read_text().splitlines()) == 4


def test_a_sweep_too_small_to_rank_says_why_it_shows_no_ranking():
    """One run of two methods, or three runs of one: no Friedman test is possible, and the
    output said nothing of it (`--comparisons` seemed ignored)."""
    table = synthetic_table()
    one_run = run_sweep(table, [ModelSpec("pmc", "zhou"), ModelSpec("pmc", "R")], repeats=1, workers=1,
                        progress=False)
    assert one_run.format(comparisons=True).endswith(
        "No Friedman test, tier list or comparisons: they rank at least 2 methods over at least 2 runs each "
        "method has, and there are 2 methods over 1 such run")
    one_method = run_sweep(table, [ModelSpec("pmc", "zhou")], repeats=3, workers=1, progress=False)
    assert one_method.format().endswith("No Friedman test or tier list: they rank at least 2 methods over at "
                                        "least 2 runs each method has, and there is 1 method over 3 such runs")
    assert "Friedman:" in run_sweep(table, [ModelSpec("pmc", "zhou"), ModelSpec("pmc", "R")], repeats=2,
                                    workers=1, progress=False).format()


def test_a_ray_address_where_nothing_listens_is_refused_at_once():
    """`--ray HOST:PORT` with no head there: Ray's client retried for minutes, printing only
    its log (the sweep hung). A connection refused now ends it in one line, before any run."""
    import socket

    pytest.importorskip("ray")
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    with pytest.raises(ConnectionError, match=rf"--ray 127\.0\.0\.1:{port}: nothing answers at 127\.0\.0\.1:{port} "
                                              r"\(Connection refused\): start the head there"):
        run_sweep(synthetic_table(), [ModelSpec("pmc", "zhou")], repeats=2, workers=1, progress=False,
                  ray_address=f"127.0.0.1:{port}")


def test_ray_auto_with_no_cluster_running_is_refused_at_once(tmp_path, monkeypatch, capsys):
    """`--ray auto` with no cluster: Ray's own error came through, naming an --address flag
    posecorr does not have. One line now, before any run: how to start one, or what to give."""
    pytest.importorskip("ray")
    from ray._private import services

    from posecorr.cli import main
    from posecorr.data import write_table

    # Nothing for "auto" to find (it never starts a cluster): no RAY_ADDRESS, no address file of
    # a `ray start` (Ray's temporary folder is an empty one), no raylet among the processes
    # (tests/test_sweep_ray.py may run a cluster alongside).
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setenv("RAY_TMPDIR", str(tmp_path))
    monkeypatch.setattr(services, "_find_address_from_flag", lambda flag: set())    # Ray's scan of the processes
    services.find_gcs_addresses.cache_clear()
    data = tmp_path / "poses.csv"
    write_table(synthetic_table(), data)
    store = tmp_path / "s.jsonl"
    assert main(["sweep", str(data), "--representations", "zhou", "--activations", "purelin", "--networks", "1/1",
                 "--epochs", "2", "--repeats", "2", "--store", str(store), "--ray", "auto"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"posecorr sweep: error: {data}: --ray auto: no Ray cluster is running on this machine and RAY_ADDRESS is "
        "unset: start one (ray start --head) or give its head's address (--ray HOST:PORT)"]
    assert not store.exists()
    # "auto" resolving to a head that is gone (RAY_ADDRESS left set): probed as HOST:PORT is
    import socket
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
    assert main(["sweep", str(data), "--representations", "zhou", "--activations", "purelin", "--networks", "1/1",
                 "--epochs", "2", "--repeats", "2", "--store", str(store), "--ray", "auto"]) == 2
    err = capsys.readouterr().err.splitlines()
    # (Ray writes the loopback as this machine's address)
    assert len(err) == 1 and re.match(rf"posecorr sweep: error: {re.escape(str(data))}: --ray auto: nothing answers "
                                      rf"at [^ ]+:{port} \(", err[0]), err
