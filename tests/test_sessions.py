"""Real sessions and the simulator's realistic ones: never worse than the best plain rigid fit.

The rigid fits here are written independently of posecorr (scipy's Rotation.align_vectors
for the rotation, an SVD-truncated least squares for the lever arm, OpenCV for the hand-eye
solution): the plain Kabsch fit, Kabsch with the lever arm in the tracker frame (issue 10's
baseline, "Kabsch from tracker position to reference position plus a constant lever arm"),
Kabsch with the lever arm in the reference frame, and for robot-carried sessions OpenCV's
robot-world-hand-eye solution. Issue 23: auto may be at most 2 % worse than the best of them.
"""
from __future__ import annotations

import json
import multiprocessing
import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr.data import read_table
from posecorr.simulate import simulate_session
from posecorr.train.pipeline import fit_table
from posecorr.train.spec import ModelSpec
from posecorr.train.splits import KFold, LeaveOneOut

REALDATA = Path(__file__).parent / "data" / "realdata"
SESSIONS = 200
TOLERANCE = 1.02                   # auto may be at most 2 % worse than the best plain rigid fit
FLOOR_RATIO = 1.3                  # physics LOO within 1.3x the noise floor (full spread, >= 20 poses)
LEVER_MIN_TURN = np.deg2rad(2.0)   # the lever is fitted along directions the orientations turn 2 deg RMS or more


# --- the independent rigid fit -----------------------------------------------------------

def _rigid(pm: np.ndarray, Rm: np.ndarray, pr: np.ndarray, iterations: int = 100, Rr: np.ndarray | None = None,
           lever_arm: bool = True):
    """p_ref = R (p_meas + R_meas l) + t, alternating Kabsch and the lever arm; with `Rr` the
    lever in the reference frame instead, p_ref + R_ref l = R p_meas + t. The lever comes from
    the centred equations (t eliminated) by a truncated SVD: only along directions about which
    the orientations carrying it turn LEVER_MIN_TURN RMS or more. Returns R, t and a function
    of (p_meas, R_meas, R_ref) giving the lever's contribution to the predicted position."""
    n = len(pm)
    lever = np.zeros(3)
    carrier = Rm if Rr is None else Rr
    for _ in range(iterations if lever_arm else 1):
        source = pm + Rm @ lever if Rr is None else pm
        target = pr if Rr is None else pr + Rr @ lever
        rot, _ = Rotation.align_vectors(target - target.mean(0), source - source.mean(0))
        R = rot.as_matrix()
        if not lever_arm:
            break
        sign = R if Rr is None else -np.eye(3)
        C = np.concatenate([sign @ (carrier[i] - carrier.mean(0)) for i in range(n)])
        b = ((pr - pr.mean(0)) - (pm - pm.mean(0)) @ R.T).reshape(-1)
        U, s, Vt = np.linalg.svd(C, full_matrices=False)
        keep = s / np.sqrt(n) > np.sin(LEVER_MIN_TURN)
        new = Vt[keep].T @ ((U[:, keep].T @ b) / s[keep])
        if np.max(np.abs(new - lever)) < 1e-12:
            break
        lever = new
    if Rr is None:
        t = pr.mean(0) - R @ (pm + Rm @ lever).mean(0)
        return R, t, lambda Rm_, Rr_: Rm_ @ lever @ R.T
    t = (pr + Rr @ lever).mean(0) - R @ pm.mean(0)
    return R, t, lambda Rm_, Rr_: -Rr_ @ lever


def _hand_eye(pm: np.ndarray, Rm: np.ndarray, pr: np.ndarray, Rr: np.ndarray):
    """OpenCV's robot-world-hand-eye solution (Shah): T_ref X = Y T_meas, p_ref = R_Y p_meas + t_Y
    - R_ref t_X."""
    import cv2

    _, t_X, R_Y, t_Y = cv2.calibrateRobotWorldHandEye(list(Rr), list(pr[:, :, None]), list(Rm), list(pm[:, :, None]),
                                                       method=cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH)
    return R_Y, t_Y.ravel(), lambda Rm_, Rr_: -Rr_ @ t_X.ravel()


RIGID_FITS = {
    "kabsch": lambda pm, Rm, pr, Rr: _rigid(pm, Rm, pr, lever_arm=False),
    "lever": lambda pm, Rm, pr, Rr: _rigid(pm, Rm, pr),
    "lever-ref": lambda pm, Rm, pr, Rr: _rigid(pm, Rm, pr, Rr=Rr),
    "hand-eye": _hand_eye,
}


def rigid_heldout(table, splits, variant: str = "lever") -> tuple[float, float]:
    """(rmse_pos, rmse_total) of an independent rigid fit (`RIGID_FITS`), out of fold.
    Orientation: the chordal mean of the mount rotation, R_ref = R R_meas X^T. The
    reference-frame variants predict the held-out position with the rotation R R_meas X^T in
    place of the reference orientation a user would not have."""
    pm, pr = table.meas_p, table.ref_p
    Rm = Rotation.from_quat(table.meas_q[:, [1, 2, 3, 0]]).as_matrix()
    Rr = None if table.ref_q is None else Rotation.from_quat(table.ref_q[:, [1, 2, 3, 0]]).as_matrix()
    dp, dr = np.empty(table.n), np.zeros(table.n)
    for train, held in splits:
        R, t, lever = RIGID_FITS[variant](pm[train], Rm[train], pr[train], None if Rr is None else Rr[train])
        X = (np.eye(3) if Rr is None
             else Rotation.from_matrix(np.swapaxes(Rr[train], 1, 2) @ R @ Rm[train]).mean().as_matrix())
        predicted_R = R @ Rm[held] @ X.T
        dp[held] = np.linalg.norm(pm[held] @ R.T + t + lever(Rm[held], predicted_R) - pr[held], axis=1)
        if Rr is not None:
            dr[held] = (Rotation.from_matrix(Rr[held]).inv() * Rotation.from_matrix(predicted_R)).magnitude()
    return float(np.sqrt(np.mean(dp ** 2))), float(np.sqrt(np.mean((dp + dr) ** 2)))


def best_rigid_heldout(table, splits) -> tuple[str, float, float]:
    """(variant, rmse_pos, rmse_total) of the best independent rigid fit the table allows."""
    variants = ["kabsch", "lever"]
    if table.ref_q is not None:
        variants.append("lever-ref")
        if table.n >= 6 and _turns_about_two_axes(table):
            variants.append("hand-eye")
    results = {v: rigid_heldout(table, splits, v) for v in variants}
    best = min(results, key=lambda v: results[v][1])
    return (best, *results[best])


def _turns_about_two_axes(table) -> bool:
    R = Rotation.from_quat(table.ref_q[:, [1, 2, 3, 0]])
    w = (R.mean().inv() * R).as_rotvec()
    return bool(np.sum(np.linalg.svd(w / np.sqrt(len(w)), compute_uv=False) > np.deg2rad(1.0)) >= 2)


def test_independent_rigid_fit_meets_the_published_baselines() -> None:
    """The README of the real sessions publishes 10.1 and 14.5 mm leave-one-out for Kabsch
    plus a constant lever arm. Ours (the lever along the yaw plane where the orientations
    turn, none where they do not) gives the published 14.5 mm on Exp2, and on Exp1 6.39 mm,
    below the published 10.1 mm, which it does not reproduce (plain Kabsch: 15.0 mm; the
    README does not say how its lever was fitted). Its figures are pinned, so that the
    baseline every "never worse than rigid" test leans on cannot drift unseen."""
    exp1, exp2 = read_table(REALDATA / "20201002_Exp1.csv"), read_table(REALDATA / "20200717_Exp2.csv")
    pos1, _ = rigid_heldout(exp1, LeaveOneOut().folds(exp1.n))
    pos2, _ = rigid_heldout(exp2, LeaveOneOut().folds(exp2.n))
    assert pos1 == pytest.approx(0.00639, abs=0.0001) and pos1 <= 0.0101
    assert rigid_heldout(exp1, LeaveOneOut().folds(exp1.n), "kabsch")[0] == pytest.approx(0.0150, abs=0.0001)
    assert pos2 == pytest.approx(0.0145, abs=0.0002)


# --- the two real sessions ---------------------------------------------------------------

@pytest.mark.parametrize("name, published", [("20201002_Exp1", 0.0101), ("20200717_Exp2", 0.0145)])
def test_real_session_auto_no_worse_than_rigid(name: str, published: float, summary) -> None:
    table = read_table(REALDATA / f"{name}.csv")
    report = fit_table(table, ["station", "mount"], ModelSpec("auto"), LeaveOneOut(), seed=0)
    variant, rigid_pos, rigid_total = best_rigid_heldout(table, LeaveOneOut().folds(table.n))
    summary(f"{name}: auto ({report.chosen}; floor {report.baseline_name}) LOO rmse_pos "
            f"{1000 * report.heldout['rmse_pos']:.2f} mm, rmse_total {1000 * report.heldout['rmse_total']:.2f}; "
            f"best independent rigid ({variant}) {1000 * rigid_pos:.2f} mm, {1000 * rigid_total:.2f}; "
            f"published rigid {1000 * published:.1f} mm; fixed {report.fixed}")
    assert report.heldout["rmse_pos"] <= published
    assert report.heldout["rmse_total"] <= TOLERANCE * rigid_total
    # What the data cannot see is named: the lever arm along the yaw axis, or all of it.
    assert any(key.startswith("mount.e") for key in report.fixed)


def test_a_model_whose_file_fails_parity_gives_way_to_the_rigid_fit(tmp_path: Path, monkeypatch, capsys) -> None:
    """Where the chosen model's graph fails the parity check, fit wrote nothing ("could not be
    exported") after all its work; it writes the rigid fit, and says why. The failure is made
    real: mapminmax as it was (a row that float32 cannot resolve scaled to [-1, 1]), on the six
    poses the test above exports."""
    import posecorr.train.mlp as mlp
    from posecorr.cli import main
    from posecorr.controller.onnx_meta import read_info

    monkeypatch.setattr(mlp, "CONSTANT_STEPS", 0)
    data = tmp_path / "six.csv"
    data.write_text("\n".join((REALDATA / "20200717_Exp2.csv").read_text().splitlines()[:7]) + "\n")
    model = tmp_path / "m.onnx"
    assert main(["fit", str(data), "--effects", "station,mount", "--method", "mlp", "--cv", "3", "-o", str(model),
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["fell_back_to_rigid"] and out["chosen"].startswith("rigid-"), out["chosen"]
    note = next(n for n in out["notes"] if "could not be written" in n)
    assert note.startswith("physics+mlp-zhou could not be written: exported graph differs from predict()")
    assert note.endswith(f"; the rigid fit ({out['chosen']}) is written in its place, its figures on the same "
                         "held-out poses"), note
    assert not any("beats the rigid fit" in n for n in out["notes"])   # of the model not written
    assert out[out.get("cv") and "cv" or "test"]["rmse_total"] == pytest.approx(out["baseline"]["rmse_total"])
    assert read_info(model).get("method") == "rigid"
    ledger = [json.loads(line) for line in (tmp_path / "six.csv.ledger.jsonl").read_text().splitlines()]
    assert ledger[-1]["asked"]["why"] == "its file failed the export's parity check"


def test_a_model_that_trades_position_for_rotation_is_said_to() -> None:
    """On 20200717_Exp2 `fit`'s default (physics + PMC) beats the rigid fit in rmse_total
    with a better rotation and a worse position held out; the data's README asks that no
    model be worse than the rigid fit's position: the fit says so, with both figures."""
    table = read_table(REALDATA / "20200717_Exp2.csv")
    from posecorr.train.spec import DEFAULT_REPRESENTATION, spec_from_options

    spec = spec_from_options("pmc", DEFAULT_REPRESENTATION)   # `fit`'s default
    report = fit_table(table, ["station", "mount"], spec, LeaveOneOut(), seed=0)
    held, floor = report.heldout, report.baseline
    assert held["rmse_total"] < floor["rmse_total"] and held["rmse_pos"] > floor["rmse_pos"] * 1.01
    note = next(n for n in report.notes if "beats the rigid fit" in n)
    assert f"{1e3 * held['rmse_pos']:.4g} against {1e3 * floor['rmse_pos']:.4g} mm held out" in note
    assert f"{1e3 * held['rmse_rot']:.4g} against {1e3 * floor['rmse_rot']:.4g} mrad in rmse_rot" in note
    assert note.endswith("fit the physics stage alone (`--effects station,mount --method none`)")
    rigid = fit_table(table, ["station", "mount"], ModelSpec("none"), LeaveOneOut(), seed=0)
    assert rigid.heldout["rmse_pos"] == pytest.approx(floor["rmse_pos"], rel=1e-3)   # what the note advises
    assert not any("beats the rigid fit" in n for n in rigid.notes)


def test_bad_position_only_session_keeps_the_plain_kabsch_floor(summary) -> None:
    """Issue 23's first case: 22 poses, position-only reference, the tracker's orientations
    spanning about 62 degrees about one axis, 100 mm of error no model removes. A plain Kabsch
    fit (no lever) was 16 % better than posecorr's rigid fit; now it is one of the floor's
    variants, and auto is within 2 % of the best independent rigid fit, leave-one-out."""
    from dataclasses import replace

    from posecorr.simulate import draw_session_spec

    spec = replace(draw_session_spec(np.random.default_rng(0), n=22, spread="yaw", position_only=True,
                                     unremovable=0.1), max_angle=np.deg2rad(31.0), robot="")
    table = simulate_session(1, spec=spec).table
    splits = LeaveOneOut().folds(table.n)
    report = fit_table(table, [], ModelSpec("auto"), LeaveOneOut(), seed=0)
    kabsch = rigid_heldout(table, splits, "kabsch")[1]
    variant, _, best = best_rigid_heldout(table, splits)
    summary(f"bad position-only session: auto ({report.chosen}) {1000 * report.heldout['rmse_total']:.1f}, "
            f"floor {report.baseline_name} {1000 * report.baseline['rmse_total']:.1f} (rigid-lever "
            f"{1000 * report.rigid_scores['rigid-lever']:.1f}), independent kabsch "
            f"{1000 * kabsch:.1f}, best independent ({variant}) {1000 * best:.1f} rmse_total x 1000, LOO")
    assert report.rigid_scores["rigid-kabsch"] == pytest.approx(kabsch, rel=1e-6)
    assert report.heldout["rmse_total"] <= TOLERANCE * best


@pytest.mark.parametrize("unremovable", [0.03, 0.074])
def test_single_orientation_session_physics_keeps_the_rigid_registration(unremovable: float, summary) -> None:
    """All orientations alike: the orientations cannot tell the mount's rotation from the
    station's, so the mount's is held, at the rigid registration's value. Held at the identity
    (as it was), the station turned to fit the orientations against positions tens of mm off:
    0.83 m held out where plain Kabsch left 34 mm. The physics stage must be as good as an
    independent Kabsch fit."""
    table = simulate_session(5, n=20, spread="none", unremovable=unremovable, robot="").table
    splits = LeaveOneOut().folds(table.n)
    report = fit_table(table, ["station", "mount"], ModelSpec("none"), LeaveOneOut(), seed=0)
    _, kabsch = rigid_heldout(table, splits, "kabsch")
    summary(f"single orientation, {1000 * unremovable:.0f} mm unremovable: physics LOO rmse_total "
            f"{1000 * report.heldout['rmse_total']:.1f}, independent kabsch {1000 * kabsch:.1f} (x 1000)")
    assert "mount.d" in " ".join(report.fixed)
    assert not report.fell_back
    assert report.heldout["rmse_total"] <= TOLERANCE * kabsch
    # The diagnosis of the bare table tests each registration effect given the other: with
    # the mount's held rotation at the identity, or at the turn a mount fitted alone takes
    # (the frames' whole rotation), one of the two seemed to add nothing.
    # (Named as candidates: the bare diagnosis itself starts from the registration where the
    # frames are unregistered.)
    from posecorr.analysis.diagnose import candidate_effects, diagnose

    found = diagnose(table, [], folds=5, seed=0, candidates=candidate_effects(table, []))
    assert {c["effect"] for c in found["candidates"] if c["present"]} == {"station", "mount"}


def test_real_session_cli_names_fixed_parameters(tmp_path: Path) -> None:
    out, data = tmp_path / "exp2.onnx", tmp_path / "exp2.csv"
    data.write_bytes((REALDATA / "20200717_Exp2.csv").read_bytes())     # fit appends a ledger beside its data
    run = subprocess.run([sys.executable, "-m", "posecorr.cli", "fit", str(data),
                          "-o", str(out), "--effects", "station,mount", "--method", "none", "--cv", "loo", "--json"],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    payload = json.loads(run.stdout)
    # The cause, then the figure that decided: one orientation cannot tell a lever arm from a shift.
    assert list(payload["fixed"]) == ["mount.e"]
    assert payload["fixed"]["mount.e"].startswith("orientations within 0.4 deg of their mean: only 0% of its effect on these poses "
                                                  "is its own"), payload["fixed"]
    assert payload["effects"]["mount"]["e"][1] == [None, None, None]        # no standard error: not determined
    assert payload["cv"]["rmse_pos"] <= payload["baseline"]["rmse_pos"] * TOLERANCE
    # The floor: every rigid variant this table allows (one orientation: no hand-eye), the best named.
    floor = payload["rigid_rmse_total"]
    assert set(floor) == {"rigid-kabsch", "rigid-lever", "rigid-lever-ref", "rigid-joint"}
    assert payload["baseline"]["name"] == min(floor, key=floor.get)
    assert payload["baseline"]["rmse_total"] == pytest.approx(min(floor.values()), rel=1e-12)
    # each variant's position error too: the plain Kabsch fit's is the independent one's
    assert set(payload["rigid_rmse_pos"]) == set(floor)
    assert payload["baseline"]["rmse_pos"] == pytest.approx(payload["rigid_rmse_pos"][payload["baseline"]["name"]],
                                                            rel=1e-12)
    table = read_table(data)
    independent, _ = rigid_heldout(table, LeaveOneOut().folds(table.n), "kabsch")
    assert payload["rigid_rmse_pos"]["rigid-kabsch"] == pytest.approx(independent, rel=1e-4)
    assert out.stat().st_size > 0
    assert "Traceback" not in run.stderr


# --- the simulated corpus ------------------------------------------------------------------

def session_class(spec) -> str:
    """The corpus' classes: robot-carried, bad (an unremovable error), set down by hand."""
    if spec.robot:
        return "robot"
    return ("bad " if spec.unremovable else "") + ("position-only" if spec.position_only else "full pose")


def _session_result(seed: int) -> dict:
    """auto (nested, 3 outer folds) against the best independent rigid fit on the same folds;
    and, for full spread with 20 poses or more, the physics stage's leave-one-out error against
    the floor."""
    from posecorr.train.physics import single_threaded

    session = simulate_session(seed)
    table, spec = session.table, session.spec
    plan = KFold(3) if table.n >= 9 else LeaveOneOut()
    with single_threaded():
        auto = fit_table(table, [], ModelSpec("auto"), plan, seed=seed)
        variant, _, rigid_total = best_rigid_heldout(table, plan.folds(table.n, seed))
        physics = None
        if spec.spread == "full" and table.n >= 20 and not spec.robot:
            physics = fit_table(table, ["station", "mount"], ModelSpec("none"), LeaveOneOut()).heldout["rmse_total"]
        recovery = _hand_eye_recovery(session) if spec.robot else None
    return {"recovery": recovery, "seed": seed, "n": table.n, "spread": spec.spread, "position_only": spec.position_only,
            "unremovable": spec.unremovable, "class": session_class(spec), "auto": auto.heldout["rmse_total"],
            "chosen": auto.chosen, "rigid": rigid_total, "rigid_variant": variant, "physics_loo": physics,
            "floor": session.noise_floor["rmse_total"]}


def _hand_eye_recovery(session) -> dict[str, float]:
    """Worst error (m, rad) of the registration and the mount of the hand-eye variant and of the
    joint fit (`rigid_registration`'s closed form and the physics stage), against the simulated
    truth and against OpenCV's solution of T_ref X = Y T_meas."""
    import cv2

    from posecorr.train.physics import RigidModel

    table, truth = session.table, session.effects
    R_ref = Rotation.from_quat(table.ref_q[:, [1, 2, 3, 0]]).as_matrix()
    R_meas = Rotation.from_quat(table.meas_q[:, [1, 2, 3, 0]]).as_matrix()
    R_X, t_X, R_Y, _ = cv2.calibrateRobotWorldHandEye(list(R_ref), list(table.ref_p[:, :, None]), list(R_meas),
                                                      list(table.meas_p[:, :, None]),
                                                      method=cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH)
    opencv = {"mount": np.concatenate([Rotation.from_matrix(R_X).as_rotvec(), t_X.ravel()]),
              "station_w": Rotation.from_matrix(R_Y).inv().as_rotvec()}

    def angle(a, b):
        return float((Rotation.from_rotvec(a).inv() * Rotation.from_rotvec(b)).magnitude())

    out = {"truth_m": 0.0, "truth_rad": 0.0, "opencv_m": 0.0, "opencv_rad": 0.0}
    for variant in ("hand-eye", "joint"):
        fitted = RigidModel(variant=variant).fit(table.measured, table.reference).params_
        station, mount = fitted["station"], fitted["mount"]
        out["truth_m"] = max(out["truth_m"], np.linalg.norm(mount[3:] - truth["mount"][3:]),
                             np.linalg.norm(station[3:] - truth["station"][3:]))
        out["truth_rad"] = max(out["truth_rad"], angle(mount[:3], truth["mount"][:3]),
                               angle(station[:3], truth["station"][:3]))
        out["opencv_m"] = max(out["opencv_m"], np.linalg.norm(mount[3:] - opencv["mount"][3:]))
        out["opencv_rad"] = max(out["opencv_rad"], angle(mount[:3], opencv["mount"][:3]),
                                angle(station[:3], opencv["station_w"]))
    return out


@pytest.fixture(scope="module")
def corpus() -> list[dict]:
    # Two processes even beside the other test process of `make test` (pytest-xdist): this
    # file starts first there (conftest.LONG_FIRST), and the pool keeps both cores once the
    # other process's files are done.
    workers = min(2, os.cpu_count() or 1)
    # forkserver: a fork of this process would copy torch's and BLAS's threads' locks.
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("forkserver")) as pool:
        return list(pool.map(_session_result, range(SESSIONS), chunksize=4))


def test_corpus_covers_what_real_cells_produce(corpus: list[dict]) -> None:
    kinds = {(r["spread"], r["position_only"]) for r in corpus}
    assert kinds == {(s, p) for s in ("none", "yaw", "full") for p in (False, True)}
    assert min(r["n"] for r in corpus) <= 8 and max(r["n"] for r in corpus) >= 38
    assert sum(r["unremovable"] > 0 for r in corpus) >= 15
    classes = {r["class"] for r in corpus}
    assert {"robot", "bad position-only", "bad full pose", "position-only", "full pose"} <= classes
    assert sum(r["class"] == "robot" for r in corpus) >= 15


def test_corpus_auto_never_worse_than_rigid(corpus: list[dict], summary) -> None:
    ratios = np.array([r["auto"] / r["rigid"] for r in corpus])
    worst = corpus[int(np.argmax(ratios))]
    chosen = {name: sum(r["chosen"] == name for r in corpus) for name in sorted({r["chosen"] for r in corpus})}
    lines = [f"{len(corpus)} sessions: auto / best independent rigid held-out rmse_total",
             f"{'class':<20} {'n':>4} {'median':>7} {'worst':>7} {'better':>6}"]
    for name in sorted({r["class"] for r in corpus}):
        mine = np.array([r["auto"] / r["rigid"] for r in corpus if r["class"] == name])
        lines.append(f"{name:<20} {len(mine):>4} {np.median(mine):>7.3f} {mine.max():>7.3f} {int(np.sum(mine < 1)):>6}")
    lines.append(f"worst {ratios.max():.3f} (seed {worst['seed']}, {worst['class']}, auto {worst['chosen']}, "
                 f"rigid {worst['rigid_variant']}); chosen {chosen}; worse than the best rigid by more than "
                 f"{100 * (TOLERANCE - 1):.0f} %: {int(np.sum(ratios > TOLERANCE))}")
    summary("\n".join(lines))
    assert len(corpus) >= 200
    assert np.all(ratios <= TOLERANCE), [r for r in corpus if r["auto"] > TOLERANCE * r["rigid"]]


def test_corpus_robot_sessions_recover_registration_and_mount(corpus: list[dict], summary) -> None:
    """The robot-carried class: the hand-eye closed form and the joint fit recover the station
    registration and the flange-to-tracker mount within 1 mm / 1 mrad of the simulated truth
    (at the tracker's noise), and agree with OpenCV's hand-eye solution."""
    rows = [r["recovery"] for r in corpus if r["recovery"] is not None]
    worst = {key: max(row[key] for row in rows) for key in rows[0]}
    summary(f"{len(rows)} robot sessions: worst error against the truth {1000 * worst['truth_m']:.3f} mm, "
            f"{1000 * worst['truth_rad']:.3f} mrad; against OpenCV {1000 * worst['opencv_m']:.3f} mm, "
            f"{1000 * worst['opencv_rad']:.3f} mrad")
    assert len(rows) >= 15
    assert worst["truth_m"] < 1e-3 and worst["truth_rad"] < 1e-3
    assert worst["opencv_m"] < 1e-3 and worst["opencv_rad"] < 1e-3


def test_corpus_physics_reaches_the_noise_floor_with_full_spread(corpus: list[dict], summary) -> None:
    rows = [r for r in corpus if r["physics_loo"] is not None]
    ratios = np.array([r["physics_loo"] / r["floor"] for r in rows])
    summary(f"{len(rows)} sessions with full spread and >= 20 poses: physics LOO / noise floor "
            f"median {np.median(ratios):.3f}, worst {ratios.max():.3f}")
    assert len(rows) >= 20
    assert np.all(ratios <= FLOOR_RATIO), [r for r in rows if r["physics_loo"] > FLOOR_RATIO * r["floor"]]


def test_diagnose_names_what_a_session_cannot_determine_instead_of_ranking_it() -> None:
    """Every pose of 20200717_Exp2 has the same orientation: incidence (a bias that depends on
    the tracker's tilt against the line of sight) cannot be seen, so it is listed, not ranked."""
    from posecorr.analysis.diagnose import diagnose

    table = read_table(REALDATA / "20200717_Exp2.csv")
    result = diagnose(table, ["station", "mount"], folds=3, seed=0)
    undetermined = {row["effect"]: row["reason"] for row in result["undetermined"]}
    ranked = {row["effect"] for row in result["candidates"]}
    assert "incidence" in undetermined and "incidence" not in ranked
    assert "orientations within 0.4 deg of their mean" in undetermined["incidence"]
    assert ranked, "the effects the data can see are still ranked"


def test_a_network_on_a_session_held_at_one_orientation_exports_within_parity(tmp_path: Path) -> None:
    """Six poses of 20200717_Exp2 (one orientation): the network's inputs after station and
    mount span a few hundred float32 steps, and scaled to [-1, 1] the graph's float32
    rounding of them moved the output by 1.1 mm from predict's (the export refused it, `fit`
    wrote nothing). Held constant, the graph is within the parity tolerance."""
    from posecorr.export import to_onnx
    from posecorr.train.pipeline import CorrectionPipeline
    from posecorr.train.spec import ModelSpec

    table = read_table(REALDATA / "20200717_Exp2.csv").subset(np.arange(6))
    core = ModelSpec("mlp", "zhou", (5,), "tansig", "br", epochs=200).make()   # fit's network for 6 poses
    model = CorrectionPipeline(effects=("station", "mount"), core=core).fit(table.measured, table.reference)
    parity = to_onnx(model, tmp_path / "m.onnx", measured=table.measured)["parity"]
    assert parity["passed"] and parity["max_pos_m"] < 1e-5 and parity["max_rot_rad"] < 1e-5, parity


def test_a_model_that_is_the_rigid_fit_is_not_said_to_lose_to_it() -> None:
    """On a table without orientations the physics stage of station and mount is a rigid
    variant; its held-out score and the variant's differ by iterative rounding, and fit fell
    back to the variant, "0.0000024 % worse", as if the model asked for had lost."""
    from posecorr.train.pipeline import fit_table
    from posecorr.train.spec import ModelSpec

    table = simulate_session(14, n=36, robot="", position_only=True).table
    report = fit_table(table, ["station", "mount"], ModelSpec("none"), LeaveOneOut(), seed=0)
    assert report.heldout["rmse_total"] == pytest.approx(report.baseline["rmse_total"], rel=1e-6)
    assert not report.fell_back and report.chosen == "physics", (report.chosen, report.notes)
