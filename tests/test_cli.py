"""The command line as a user meets it: JSON outputs, one-line errors, exit codes."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr.data import PoseTable, write_table
from posecorr.simulate import simulate

PAPER_RAW = {1: {"rmse_pos": 0.0440}, 2: {"rmse_pos": 0.0058, "rmse_rot": 0.0115},
             3: {"rmse_pos": 0.0222, "rmse_rot": 0.0508}}


def posecorr(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    return subprocess.run([sys.executable, "-m", "posecorr.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=600)


def test_python_dash_m_posecorr_is_the_command() -> None:
    via_package = subprocess.run([sys.executable, "-m", "posecorr", "--help"], capture_output=True, text=True,
                                 timeout=120)
    assert via_package.returncode == 0 and via_package.stdout == posecorr("--help").stdout


@pytest.mark.parametrize("experiment", [1, 2, 3])
def test_simulate_json_matches_the_paper_raw_rows(tmp_path, experiment: int) -> None:
    out = posecorr("simulate", "--experiment", str(experiment), "--seed", "0", "-o", str(tmp_path / "x.csv"), "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert set(result) >= {"n", "raw", "noise_floor"}
    for key, paper in PAPER_RAW[experiment].items():
        assert abs(result["raw"][key] - paper) <= 0.02 * paper, (key, result["raw"][key], paper)
    assert result["noise_floor"]["rmse_total"] < result["raw"]["rmse_total"] / 10
    if experiment == 1:
        assert result["raw"]["rmse_rot"] is None
    # the line that marks it simulated, the header, the poses
    text = (tmp_path / "x.csv").read_text()
    assert text.startswith(f"# written by posecorr simulate (seed 0): simulated poses")
    assert text.count("\n") == result["n"] + 2


def test_a_session_with_drift_needs_a_duration_and_then_has_times(tmp_path) -> None:
    out_csv = tmp_path / "s.csv"
    base = ("simulate", "--session", "--poses", "12", "--seed", "2", "--effects", "drift=0.002,0,0,900",
            "-o", str(out_csv))
    out = posecorr(*base)
    assert out.returncode == 2 and not out_csv.exists()
    assert out.stderr.strip().splitlines()[-1].endswith(
        "error: drift acts over the session's time, and the session has none: give --duration SECONDS "
        "(a robot takes about 40 s a pose: 50 poses, --duration 2000)"), out.stderr
    out = posecorr("simulate", "--experiment", "3", "--duration", "60", "-o", str(out_csv))
    assert out.returncode == 2 and "--duration goes with --session" in out.stderr
    out = posecorr(*base, "--duration", "600", "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["session"]["duration"] == 600.0
    from posecorr.data import read_table

    np.testing.assert_allclose(read_table(out_csv).time(), 50.0 * np.arange(1, 13))


def test_simulate_does_what_its_options_say_or_refuses_them(tmp_path) -> None:
    """Seed 8 draws a robot, which turns the tracker every way: asked for no spread, the session
    is set down by hand with none (it was carried by a robot, spread full); asked for a robot
    too, the two are refused together. An experiment's table refuses a session's options (they
    were ignored), and --targets goes with --recording. An effect's values that hold another
    effect's name were meant as two effects: the message says how to separate them."""
    out_csv = tmp_path / "s.csv"
    drawn = json.loads(posecorr("simulate", "--session", "--seed", "8", "-o", str(out_csv), "--json").stdout)
    assert drawn["session"]["robot"] and drawn["session"]["spread"] == "full"
    out = posecorr("simulate", "--session", "--spread", "none", "--poses", "10", "--seed", "8", "-o", str(out_csv),
                   "--json")
    assert out.returncode == 0, out.stderr
    session = json.loads(out.stdout)["session"]
    assert session["spread"] == "none" and not session["robot"]
    from posecorr.data import read_table

    turns = Rotation.from_quat(read_table(out_csv).ref_q, scalar_first=True)
    assert np.max((turns[0].inv() * turns).magnitude()) < 1e-9
    for argv, said in [
        (("--session", "--spread", "yaw", "--robot", "ur5e"), "spread 'yaw' goes with a tracker set down by hand"),
        (("--experiment", "1", "--poses", "10", "--unremovable", "50", "--spread", "yaw"),
         "--poses, --spread, --unremovable go with --session"),
        (("--experiment", "1", "--robot", "ur5e", "--position-only"), "--position-only, --robot go with --session"),
        (("--experiment", "1", "--targets", "5"), "--targets goes with --recording"),
        (("--experiment", "1", "--effects", "range_scale=0.01,sweep"),
         "expected 1 number (k 1), got '0.01,sweep'; separate effects with ';', as values take ','")]:
        out = posecorr("simulate", *argv, "-o", str(tmp_path / "refused.csv"))
        assert out.returncode == 2 and said in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
        assert not (tmp_path / "refused.csv").exists()


def test_simulate_robot_takes_every_arm_that_kinematics_holds(tmp_path, capsys) -> None:
    """docs/guides/sessions.md points --robot to `kinematics.UR_ARMS`, which holds the ur5 (and
    the ur3, ur10, ...: Universal Robots' published DH parameters), but `--robot ur5` was
    refused ("takes ur5e, ur10e or none"): each arm there carries the tracker, its flange
    within the arm's reach, and the help names them."""
    from posecorr.cli import build_parser, main
    from posecorr.data import read_table
    from posecorr.kinematics import UR_ARMS

    for name, arm in UR_ARMS.items():
        capsys.readouterr()
        assert main(["simulate", "--session", "--robot", name, "--seed", "1", "-o", str(tmp_path / "s.csv"),
                     "--json"]) == 0
        payload = json.loads(capsys.readouterr().out)
        assert payload["session"]["robot"] == name and 30 <= payload["n"] <= 60, payload["session"]
        reach = sum(map(abs, arm.a)) + sum(arm.d)
        distance = np.linalg.norm(read_table(tmp_path / "s.csv").ref_p, axis=1)
        assert 0.5 * reach < distance.max() <= reach, (name, distance.max(), reach)
    robot = next(a for a in next(a for a in build_parser()._actions if a.dest == "verb").choices["simulate"]._actions
                 if a.dest == "robot")
    assert f"a robot arm ({', '.join(UR_ARMS)}) carries the tracker" in robot.help


def test_a_session_pins_a_full_pose_reference_or_a_tracker_set_down_by_hand(tmp_path, capsys) -> None:
    """`--position-only` could only switch position-only on and `--robot` took no "no robot":
    where the seed drew a position-only reference or a robot, a session could not be had
    without. `--no-position-only` and `--robot none` pin them; the help says what is drawn,
    and --only's help says what it does (no noise unless named, as the run shows)."""
    from posecorr.cli import build_parser, main
    from posecorr.data import read_table

    def session(*argv: str) -> dict:
        capsys.readouterr()
        assert main(["simulate", "--session", *argv, "-o", str(tmp_path / "s.csv"), "--json"]) == 0
        return json.loads(capsys.readouterr().out)["session"]

    assert session("--seed", "22")["position_only"] is True   # what the seed draws
    full = session("--seed", "22", "--no-position-only")
    assert full["position_only"] is False and read_table(tmp_path / "s.csv").has_orientation
    assert session("--seed", "8")["robot"] == "ur10e"
    assert session("--seed", "8", "--robot", "none")["robot"] == ""
    assert _refusal(capsys, "simulate", "--session", "--robot", "kuka", "-o", str(tmp_path / "k.csv")) == (
        "posecorr simulate: error: --robot takes ur3, ur5, ur10, ur3e, ur5e, ur10e, ur16e or none (a tracker set "
        "down by hand), got 'kuka'")
    assert _refusal(capsys, "simulate", "--experiment", "1", "--no-position-only", "-o", str(tmp_path / "k.csv")) == (
        "posecorr simulate: error: --no-position-only goes with --session: an experiment's table is the paper's "
        "protocol, its poses, orientations and times its own")
    helps = {a.dest: a.help for a in next(a for a in build_parser()._actions if a.dest == "verb")
             .choices["simulate"]._actions}
    assert "0 in 85 %% of sessions set down by hand, else 60-110 mm; 0 with a robot" in helps["unremovable"]
    assert "no noise unless noise is named" in helps["only"] and "plus noise" not in helps["only"]
    capsys.readouterr()
    assert main(["simulate", "--experiment", "1", "--only", "--effects", "sweep", "-o", str(tmp_path / "o.csv"),
                 "--json"]) == 0
    assert list(json.loads(capsys.readouterr().out)["effects"]) == ["sweep"]


def test_quaternions_written_scalar_last_are_named_by_fit_and_diagnose(tmp_path) -> None:
    """A robot session whose measured quaternions were written with scipy's as_quat() (x, y, z,
    w) under qw, qx, qy, qz: fit and diagnose say the quaternions look written in another order;
    the table as simulated draws no such note."""
    from posecorr.data import read_table

    good = tmp_path / "good.csv"
    assert posecorr("simulate", "--session", "--robot", "ur5e", "--poses", "30", "--seed", "3", "-o",
                    str(good)).returncode == 0
    table = read_table(good)
    swapped = tmp_path / "swapped.csv"
    write_table(PoseTable(table.meas_p, Rotation.from_quat(table.meas_q, scalar_first=True).as_quat(), table.ref_p,
                          table.ref_q), swapped)
    for data, told in ((good, False), (swapped, True)):
        fit = posecorr("fit", str(data), "--effects", "station,mount", "--method", "none", "--cv", "5", "-o",
                       str(tmp_path / "m.onnx"), "--json")
        diagnosed = posecorr("diagnose", str(data), "--effects", "station,mount", "--json")
        for out in (fit, diagnosed):
            assert out.returncode == 0, out.stderr
            notes = json.loads(out.stdout)["notes"]
            assert any("written in another order" in note for note in notes) == told, notes


HEADER = "meas_x,meas_y,meas_z,meas_qw,meas_qx,meas_qy,meas_qz,ref_x,ref_y,ref_z"
GOOD = "0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3"


@pytest.mark.parametrize("body, where", [
    (HEADER.replace("meas_qz,", "") + "\n" + GOOD.replace(",0,0,0,", ",0,0,", 1) + "\n", "row 1, column meas_qz"),
    (f"{HEADER}\n{GOOD}\n0.1,x,0.3,1,0,0,0,0.1,0.2,0.3\n", "row 3, column meas_y"),
    (f"{HEADER}\n{GOOD}\n0.1,0.2,0.3,1,0,0,0,0.1,nan,0.3\n", "row 3, column ref_y"),
    (f"{HEADER}\n{GOOD}\n0.1,0.2,0.3,1,0,0,0,0.1,0.2,-inf\n", "row 3, column ref_z"),
    (f"{HEADER}\n{GOOD}\n0.1,0.2,0.3,0.9,0,0,0,0.1,0.2,0.3\n", "row 3, column meas_qw..meas_qz"),
    (f"{HEADER}\n" + f"{GOOD}\n" * 3, "3 rows, but"),
])
def test_malformed_tables_fail_in_one_line_with_exit_2(tmp_path, body: str, where: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(body)
    out = posecorr("fit", str(path), "-o", str(tmp_path / "m.onnx"), "--method", "pmc")
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert str(path) in lines[0] and where in lines[0]


def test_unknown_effect_is_a_one_line_error(tmp_path) -> None:
    path = tmp_path / "d.csv"
    write_table(simulate(2, seed=0).table.subset(np.arange(40)), path)
    out = posecorr("fit", str(path), "-o", str(tmp_path / "m.onnx"), "--effects", "station,wobble")
    assert out.returncode == 2 and "wobble" in out.stderr and "Traceback" not in out.stderr


def _frame_from_three_points(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """x along a->b, z normal to the plane (a, b, c), y completing a right-handed frame."""
    x = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    z = np.cross(x, c - a)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], axis=2)


def test_fit_station_and_mount_in_the_trackers_own_frame_with_loo(tmp_path) -> None:
    """Measured poses in an arbitrary frame (any rotation and offset), reference orientation
    from three probed points per pose: the closed-form start must still converge."""
    rng = np.random.default_rng(3)
    n = 30
    # Reference: 30 poses in the workspace; orientation from three points on a probe.
    centre = np.array([0.0, -0.6, 0.5])
    origin = centre + rng.uniform(-0.1, 0.1, (n, 3))
    R_true = Rotation.from_euler("xyz", rng.uniform(-0.5, 0.5, (n, 3))).as_matrix()
    arm = 0.05
    a, b, c = origin, origin + arm * R_true[:, :, 0], origin + arm * R_true[:, :, 1]
    R_ref = _frame_from_three_points(a, b, c)
    np.testing.assert_allclose(R_ref, R_true, atol=1e-12)
    # Tracker frame: rotated 2 rad about an oblique axis and 1.7 m away; mount offset 4 cm.
    W_R, W_t = Rotation.from_rotvec([1.2, -0.9, 1.3]).as_matrix(), np.array([1.2, -0.4, 0.9])
    X_R, X_t = Rotation.from_rotvec([0.02, -0.01, 0.03]).as_matrix(), np.array([0.01, -0.02, 0.04])
    R_meas = W_R @ R_ref @ X_R
    p_meas = (origin + R_ref @ X_t) @ W_R.T + W_t
    p_meas += rng.normal(scale=2e-4, size=p_meas.shape)
    to_q = lambda R: Rotation.from_matrix(R).as_quat(scalar_first=True)  # noqa: E731
    table = PoseTable(p_meas, to_q(R_meas), origin, to_q(R_ref))
    path = tmp_path / "frame.csv"
    write_table(table, path)
    out = posecorr("fit", str(path), "-o", str(tmp_path / "m.onnx"), "--effects", "station,mount",
                   "--method", "none", "--cv", "loo", "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["raw"]["rmse_pos"] > 1.0                  # metres apart before
    assert result["cv"]["rmse_pos"] < 1e-3                  # sub-millimetre after, held out
    assert result["cv"]["rmse_rot"] < 1e-6                  # orientations carry no noise here
    assert set(result["effects"]) == {"station", "mount"}
    assert result["representation"] is None   # no core, so no core input (it said "R")
    mount_e, _ = result["effects"]["mount"]["e"]
    np.testing.assert_allclose(mount_e, X_t, atol=1e-3)
    # Raw measures the frame's 1.7 m: the ratio that means something is against the rigid floor.
    assert result["frames_unregistered"] is True
    assert result["vs_floor"]["improvement_total"] == pytest.approx(
        result["baseline"]["rmse_total"] / result["cv"]["rmse_total"], rel=1e-12)
    text = posecorr("fit", str(path), "-o", str(tmp_path / "m.onnx"), "--effects", "station,mount",
                    "--method", "none", "--cv", "loo")
    assert text.returncode == 0, text.stderr
    header, _, raw_row = text.stdout.splitlines()[1:4]
    assert header.split()[-3:] == ["improvement", "vs", "floor"] and raw_row.startswith("raw (frames unregistered)")


def test_controller_side_verbs_import_nothing_heavier_than_numpy(tmp_path) -> None:
    """apply (C backend), info and bench's C part run on a numpy-only install."""
    model = Path(__file__).resolve().parents[1] / "models" / "pmc-zhou.onnx"
    table = simulate(3, seed=9).table.subset(np.arange(20))
    write_table(table, tmp_path / "in.csv")
    script = f"""
import sys
from posecorr.cli import main
assert main(["apply", {str(model)!r}, {str(tmp_path / 'in.csv')!r}, "-o", {str(tmp_path / 'out.csv')!r}]) == 0
assert main(["info", {str(model)!r}]) == 0
from posecorr.latency import c_bench
assert c_bench({str(model)!r}, n_single=100, batch=10)["single_pose_median_us"] > 0
heavy = sorted(m for m in ("torch", "scipy", "sklearn", "onnx", "onnxruntime", "matplotlib") if m in sys.modules)
print("HEAVY", heavy)
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "HEAVY []" in out.stdout, out.stdout


@pytest.mark.parametrize("method, extra", [("none", []), ("pmc", []), ("auto", []),
                                           ("mlp", ["--hidden", "4", "--epochs", "5", "--trainer", "lm"])])
def test_fit_save_round_trips_every_estimator_through_export(tmp_path, method: str, extra: list[str]) -> None:
    """Issue 11: `fit --save` pickles every kind (effects included) and `export` of the saved
    estimator writes a file that computes what fit's file computes (onnxruntime as the judge)."""
    import onnxruntime as ort

    from posecorr.simulate import simulate_session

    data = tmp_path / "s.csv"
    write_table(simulate_session(2, n=30).table, data)
    fitted, saved, exported = tmp_path / "fit.onnx", tmp_path / "est.pkl", tmp_path / "export.onnx"
    run = posecorr("fit", str(data), "-o", str(fitted), "--effects", "station,mount",
                   "--method", method, "--cv", "3", "--save", str(saved), *extra, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    run = posecorr("export", str(saved), "-o", str(exported), cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    poses = np.loadtxt(data, delimiter=",", skiprows=1, usecols=range(1, 8), dtype=np.float32)
    outputs = [ort.InferenceSession(str(p), providers=["CPUExecutionProvider"]).run(None, {"pose": poses})[0]
               for p in (fitted, exported)]
    assert np.array_equal(outputs[0], outputs[1])
    # and states the fit's figures: held out, raw and the rigid floor
    from posecorr.controller import read_info

    stated = [read_info(p)["test_metrics"] for p in (fitted, exported)]
    assert stated[0] == stated[1] and {"cv", "raw", "rigid"} <= set(stated[0])


def test_fit_prints_the_metrics_of_the_file_it_writes(tmp_path) -> None:
    """Issue 11: the test-split figures fit prints are those of the exported graph; apply of
    that file to the same poses (onnxruntime back-end: the same float32 graph) gives them."""
    from posecorr.train.protocol import split_indices

    table = simulate(3, seed=5).table.subset(np.arange(300))
    data, model = tmp_path / "d.csv", tmp_path / "m.onnx"
    write_table(table, data)
    run = posecorr("fit", str(data), "-o", str(model), "--effects", "station,mount,drift", "--method", "pmc",
                   "--json", "--save", str(tmp_path / "m.pkl"), cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    fitted = json.loads(run.stdout)
    printed = fitted["test"]
    # export of the saved estimator states the same test figures: the graph scores the same poses
    from posecorr.controller import read_info

    assert posecorr("export", str(tmp_path / "m.pkl"), "-o", str(tmp_path / "e.onnx"), cwd=tmp_path).returncode == 0
    infos = [read_info(p) for p in (model, tmp_path / "e.onnx")]
    stated = [info["test_metrics"] for info in infos]
    assert stated[0] == stated[1] and stated[0]["test"]["rmse_pos"] == pytest.approx(printed["rmse_pos"], rel=1e-12)
    # and the digests of the whole table it split, by which apply and report know that table
    for key in ("fitted_table_digest", "fitted_table_set_digest", "training_data_digest", "training_set_digest"):
        assert infos[0].get(key) and infos[0].get(key) == infos[1].get(key), key
    # the paper's frames are registered: raw is a few cm, and the ratio stays against it
    assert fitted["frames_unregistered"] is False
    _, _, test = split_indices(table.n, 0)
    held = tmp_path / "test_rows.csv"
    write_table(table.subset(test), held)
    run = posecorr("apply", str(model), str(held), "-o", str(tmp_path / "out.csv"), "--backend", "onnxruntime",
                   "--json", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    applied = json.loads(run.stdout)["corrected"]
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        assert printed[key] == pytest.approx(applied[key], rel=1e-12), key


def test_fit_names_the_network_it_sized_to_the_table(tmp_path) -> None:
    """`fit --method mlp` with no network named fits the session network on a session's
    poses, says so first among its notes, and records that network in the ledger (a report
    rebuilds the held-out poses with it); a network named is fitted as named, without the note."""
    from posecorr.analysis.ledger import read_ledger
    from posecorr.simulate import simulate_session
    from posecorr.train.spec import SESSION_EPOCHS, SESSION_HIDDEN

    data = tmp_path / "s.csv"
    write_table(simulate_session(5, n=30).table, data)
    run = posecorr("fit", str(data), "-o", str(tmp_path / "m.onnx"), "--effects", "station,mount", "--method", "mlp",
                   "--cv", "3", "--json", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    notes = json.loads(run.stdout)["notes"]
    assert notes[0].startswith(f"network {'-'.join(map(str, SESSION_HIDDEN))} (hidden units), {SESSION_EPOCHS} epochs "
                               "(the default for 30 poses"), notes
    spec = read_ledger(data)[-1]["spec"]
    assert tuple(spec["hidden"]) == SESSION_HIDDEN and spec["epochs"] == SESSION_EPOCHS
    run = posecorr("fit", str(data), "-o", str(tmp_path / "n.onnx"), "--method", "mlp", "--hidden", "3",
                   "--epochs", "3", "--cv", "3", "--json", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert not any(note.startswith("network ") for note in json.loads(run.stdout)["notes"])
    assert read_ledger(data)[-1]["spec"]["hidden"] == [3]


def test_one_grammar_of_layer_sizes(tmp_path) -> None:
    """`fit --hidden 20-20`, `20x20` and `20,20` are one network: the same file, byte for
    byte after its time stamp; a size out of bounds is refused in one line by each verb."""
    from posecorr.simulate import simulate_session

    data = tmp_path / "s.csv"
    write_table(simulate_session(5, n=30).table, data)
    weights = []
    for spelling in ("3-2", "3x2", "3,2"):
        out = tmp_path / f"m{spelling.replace(',', 'c')}.onnx"
        run = posecorr("fit", str(data), "-o", str(out), "--method", "mlp", "--hidden", spelling, "--epochs", "3",
                       "--trainer", "lm", "--cv", "3", "--json", cwd=tmp_path)
        assert run.returncode == 0, run.stderr
        import onnx

        model = onnx.load(out)
        weights.append([onnx.numpy_helper.to_array(t).tobytes() for t in model.graph.initializer])
    assert weights[0] == weights[1] == weights[2]
    for verb, option in (("fit", "--hidden"), ("sweep", "--architectures")):
        args = [verb, str(data), "-o", str(tmp_path / "x")] if verb == "fit" else [verb, str(data)]
        run = posecorr(*args, option, "3-0", cwd=tmp_path)
        line = run.stderr.strip()
        assert run.returncode == 2 and "\n" not in line and line.startswith(f"posecorr {verb}: error: ") \
            and line.endswith(f"{option}: layer sizes are integers in 1..1024, got 0"), run.stderr


def test_folds_too_small_to_fit_end_in_one_line_that_names_the_folds_that_fit(tmp_path) -> None:
    """Four poses in two folds leave two to fit on: fit, diagnose and report refuse it in one
    line that names the folds that would do, and those folds do."""
    from posecorr.simulate import simulate_session

    data = tmp_path / "four.csv"
    write_table(simulate_session(3, n=6).table.subset(np.arange(4)), data)
    for verb, extra in (("diagnose", ["--effects", "station,mount"]),
                        ("fit", ["--effects", "station,mount", "--method", "none", "-o", "m.onnx"])):
        run = posecorr(verb, str(data), *extra, "--cv", "2", cwd=tmp_path)
        assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
        assert run.stderr.strip() == (f"posecorr {verb}: error: {data}: 4 rows, but with 2 folds a fold fits on 2 of "
                                      "them, and a fit needs at least 3: more folds (--cv 4)")
        assert not (tmp_path / "m.onnx").exists()  # the refused fit wrote nothing; the fit below writes it
        assert posecorr(verb, str(data), *extra, "--cv", "4", cwd=tmp_path).returncode == 0


def test_a_core_that_needs_more_poses_than_a_fold_leaves_is_refused_before_the_work(tmp_path) -> None:
    """An MLP fits on four poses at least: `fit --method mlp --cv 2` on six poses began the
    first fold and then failed ("MLP(zhou) needs at least 4 poses, got 3"); it is refused
    before any work, with the folds that leave enough, and those do."""
    from posecorr.simulate import simulate_session

    data = tmp_path / "six.csv"
    write_table(simulate_session(3, n=6).table, data)
    fit = ("fit", str(data), "--method", "mlp", "--hidden", "3", "--epochs", "5", "-o", "m.onnx")
    run = posecorr(*fit, "--cv", "2", cwd=tmp_path)
    assert run.returncode == 2 and run.stderr.strip() == (
        f"posecorr fit: error: {data}: 6 rows, but with 2 folds a fold fits on 3 of them, and mlp-zhou needs at "
        "least 4: more folds (--cv 3)"), run.stderr
    assert "fold" not in run.stdout and not (tmp_path / "m.onnx").exists()
    assert posecorr(*fit, "--cv", "3", cwd=tmp_path).returncode == 0


def test_more_folds_than_poses_end_in_one_line_that_names_the_most_there_are(tmp_path) -> None:
    """`fit --cv 20` on 12 poses said "20 folds need at least 20 poses, got 12", after the
    fit began, and not what to do: now before any work, with the folds that do, and they do."""
    from posecorr.simulate import simulate_session

    data, model = tmp_path / "twelve.csv", tmp_path / "m.onnx"
    write_table(simulate_session(3, n=12).table, data)
    fit = ("fit", str(data), "--effects", "station,mount", "--method", "none", "-o", str(model))
    run = posecorr(*fit, "--cv", "20")
    assert run.returncode == 2 and run.stderr.strip().splitlines() == [
        f"posecorr fit: error: {data}: 12 rows, but 20 folds need at least 20: at most 12 folds (--cv 12), or "
        "--cv loo"], run.stderr
    assert not model.exists()
    for cv in ("12", "loo"):
        assert posecorr(*fit, "--cv", cv).returncode == 0


def test_drift_on_a_table_without_time_is_refused_before_any_work(tmp_path) -> None:
    """Drift works on each pose's time: on a session with no t column, fit ran every fold
    and then failed at the export asking for a Python argument; now fit (every method) and
    diagnose refuse it in one line naming the column, and the table with t is fitted. The
    model it gives is refused the timeless table by apply and report."""
    from posecorr.data import read_table

    table = simulate(1, seed=5).table
    table = table.subset(np.arange(0, table.n, 10))          # 134 poses over the session
    timed = tmp_path / "timed.csv"
    write_table(table, timed)
    del table.extras["t"]
    timeless = tmp_path / "timeless.csv"
    write_table(table, timeless)
    assert read_table(timeless).time() is None
    refused = ("drift needs each pose's time (seconds since the session's start), and the table has no such column")
    for verb, extra in (("diagnose", ["--effects", "station,drift"]),
                        ("fit", ["--effects", "station,drift", "--method", "none", "-o", "m.onnx"]),
                        ("fit", ["--effects", "drift", "--method", "auto", "-o", "m.onnx"])):
        run = posecorr(verb, str(timeless), *extra, cwd=tmp_path)
        assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
        assert run.stderr.strip() == f"posecorr {verb}: error: {timeless}, column t: {refused}"
    assert not (tmp_path / "m.onnx").exists()
    fitted = posecorr("fit", str(timed), "--effects", "station,drift", "--method", "none", "-o", "m.onnx", "--json",
                      cwd=tmp_path)
    assert fitted.returncode == 0 and json.loads(fitted.stdout)["chosen"] == "physics", fitted.stderr
    # The model takes time: apply and report refuse the timeless table (corrected as at t = 0,
    # the API's default, its drift would be left out without a word) and write nothing.
    for verb, argv in (("apply", ["apply", "m.onnx", str(timeless), "-o", "out.csv"]),
                       ("report", ["report", str(timeless), "--model", "m.onnx", "-o", "out.html"])):
        run = posecorr(*argv, cwd=tmp_path)
        assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
        assert run.stderr.strip() == (f"posecorr {verb}: error: {timeless}, row 1, column t: m.onnx takes each pose's "
                                      "time (it models a time-dependent effect such as drift), and the table has no "
                                      "such column (seconds since the session's start)")
    assert not list(tmp_path.glob("out.*"))
    assert posecorr("apply", "m.onnx", str(timed), "-o", "out.csv", cwd=tmp_path).returncode == 0


def test_info_says_what_the_file_is_before_its_metadata(tmp_path, capsys) -> None:
    """`info` starts with a few lines read from the metadata: what corrects, the size, the
    held-out figures (a shipped model's test split; a fitted one's cross-validation), the
    parity and the box; then every key. A file whose metadata is missing or of other types
    still gets its first line."""
    import onnx

    from posecorr.cli import main
    from posecorr.controller.onnx_meta import read_info
    from posecorr.simulate import simulate_session

    shipped = Path(__file__).resolve().parents[1] / "models" / "mlp-zhou-tansig-20x20x20x20-br.onnx"
    meta = read_info(shipped)
    assert main(["info", str(shipped)]) == 0
    lines = capsys.readouterr().out.splitlines()
    test = meta["test_metrics"]
    assert lines[0] == f"{shipped.name}: mlp 20-20-20-20 (tansig, br) on zhou; physical effects: none"
    assert lines[1] == (f"  {meta['n_parameters']:,} fitted parameters, {meta['parameter_count']:,} numbers in the "
                        f"graph's constants, {meta['node_count']} nodes, {meta['file_size']:,} bytes")
    assert lines[2] == (f"  held out (test split, {test['n']} poses): rmse_pos {1e3 * test['rmse_pos']:.4g} mm, "
                        f"rmse_rot {1e3 * test['rmse_rot']:.4g} mrad")
    assert lines[3] == (f"  raw: rmse_pos {1e3 * test['raw']['rmse_pos']:.4g} mm, "
                        f"rmse_rot {1e3 * test['raw']['rmse_rot']:.4g} mrad")   # registered: raw is the tracker's
    assert lines[4].startswith("  parity with the fitted estimator: passed, worst ")
    assert lines[5].startswith("  corrects positions within x ")
    within = np.rad2deg(meta["training_orientations"]["within"])
    assert lines[6] == (f"  fitted on orientations within {within:.3g} deg of their mean "
                        "(apply counts the poses turned beyond)")
    assert lines[7:9] == ["", "metadata and structure:"]
    assert sum(line.split(":")[0].strip() in meta for line in lines[9:]) == len(meta)
    # the metadata's numbers of one kind carry their unit
    box = next(line for line in lines[9:] if line.split(":")[0].strip() == "input_bounds")
    reach = next(line for line in lines[9:] if line.split(":")[0].strip() == "correction_reach")
    assert box.endswith("]] [m]") and reach.endswith("] [m, rad]"), (box, reach)

    data = tmp_path / "s.csv"
    write_table(simulate_session(2, n=12, spread="full", position_only=False, unremovable=0.0).table, data)
    fitted = json.loads(posecorr("fit", str(data), "--effects", "station,mount", "--method", "none", "--cv", "4",
                                 "-o", str(tmp_path / "m.onnx"), "--json").stdout)
    assert main(["info", str(tmp_path / "m.onnx")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].endswith("; physical effects: station, mount") or lines[0].endswith("; physical effects: mount, station")
    assert lines[2].startswith(f"  held out (cross-validated): rmse_pos {1e3 * fitted['cv']['rmse_pos']:.4g} mm")
    # a fitted model states its floor, the best rigid fit scored alike; raw is the frames' offset here
    rigid = fitted["baseline"]
    assert fitted["frames_unregistered"] and lines[3] == (
        f"  the best rigid fit ({rigid['name']}), same poses: rmse_pos {1e3 * rigid['rmse_pos']:.4g} mm, "
        f"rmse_rot {1e3 * rigid['rmse_rot']:.4g} mrad")
    assert lines[4] == (f"  raw: rmse_pos {1e3 * fitted['raw']['rmse_pos']:.4g} mm, rmse_rot "
                        f"{1e3 * fitted['raw']['rmse_rot']:.4g} mrad (frames unregistered: their offset, not the "
                        "tracker's error)")
    # a model that takes the time says in which span, beside its box
    timed = tmp_path / "timed.csv"
    write_table(simulate_session(2, n=30, spread="full", position_only=False, unremovable=0.0, duration=600.0,
                                 extra={"drift": [0.003, -0.002, 0.002, 300.0]}).table, timed)
    assert posecorr("fit", str(timed), "--effects", "station,mount,drift", "--method", "none", "--cv", "4",
                    "-o", str(tmp_path / "d.onnx")).returncode == 0
    assert main(["info", str(tmp_path / "d.onnx")]) == 0
    lo, hi = read_info(tmp_path / "d.onnx")["time_bounds"]
    assert (f"  takes each pose's time t (s since the session's start) within {lo:g}..{hi:g} s"
            in capsys.readouterr().out.splitlines())

    bare = onnx.load(shipped)
    del bare.metadata_props[:]
    entry = bare.metadata_props.add()
    entry.key, entry.value = "test_metrics", "[1, 2]"
    onnx.save(bare, tmp_path / "bare.onnx")
    assert main(["info", str(tmp_path / "bare.onnx")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "bare.onnx: unknown method; physical effects: none"
    assert lines[2].startswith("  DAMAGED or unsigned, every runtime refuses it: no metadata model_digest")
    assert lines[3:5] == ["", "metadata and structure:"]

    # One byte of a weight flipped: the metadata still reads, the digest no longer matches.
    data = bytearray(shipped.read_bytes())
    weights = max(onnx.load(shipped).graph.initializer, key=lambda t: len(t.raw_data)).raw_data
    data[data.find(weights) + 5] ^= 1
    (tmp_path / "flipped.onnx").write_bytes(bytes(data))
    assert main(["info", str(tmp_path / "flipped.onnx"), "--json"]) == 0
    integrity = json.loads(capsys.readouterr().out)["integrity"]
    assert not integrity["ok"] and f"where its metadata model_digest says {meta['model_digest']}" in integrity["why"]
    assert main(["info", str(shipped), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["integrity"] == {"ok": True, "why": None}


def test_a_new_verb_is_one_file(tmp_path, capsys) -> None:
    """A module defining `VERB = Verb(...)` beside its add_arguments and run, dropped into
    the package's folder, is a verb of `posecorr` (its help, its options, its run); a
    module there that is no verb is refused by name."""
    import posecorr.cli as cli

    (tmp_path / "hello.py").write_text(
        "from posecorr.cli.common import Verb, emit\n"
        "def add_arguments(p):\n    p.add_argument('--name', default='world')\n"
        "def run(args):\n    emit(args, {'hello': args.name}, lambda: f'hello, {args.name}')\n"
        "VERB = Verb(help='say hello', rank=99, add_arguments=add_arguments, run=run)\n")
    cli.__path__.append(str(tmp_path))
    try:
        assert "say hello" in cli.build_parser().format_help()
        capsys.readouterr()
        assert cli.main(["hello", "--name", "posecorr"]) == 0
        assert capsys.readouterr().out.strip() == "hello, posecorr"
        assert cli.main(["hello", "--json"]) == 0
        assert json.loads(capsys.readouterr().out) == {"hello": "world"}
        (tmp_path / "stray.py").write_text("X = 1\n")
        with pytest.raises(TypeError, match=r"posecorr\.cli\.stray is no verb"):
            cli.verbs()
    finally:
        cli.__path__.remove(str(tmp_path))
        for name in ("posecorr.cli.hello", "posecorr.cli.stray"):
            sys.modules.pop(name, None)


def _refusal(capsys, *argv: str) -> str:
    """The one stderr line of a command refused with exit code 2."""
    from posecorr.cli import main

    capsys.readouterr()
    assert main(list(argv)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    return err.rstrip("\n")


def test_a_misspelled_option_is_named_by_its_verb_before_a_missing_required_argument(tmp_path, capsys) -> None:
    """`--efects` hid behind "the following arguments are required: -o/--output", and with -o
    it was the top parser's "posecorr: error: unrecognized arguments" pointing to
    `posecorr --help`: now it is the verb's line, with the option it likely meant."""
    data = tmp_path / "good.csv"
    write_table(simulate(2, seed=0).table.subset(np.arange(20)), data)
    line = "posecorr fit: error: unrecognized option --efects (did you mean --effects?) (see posecorr fit --help)"
    assert _refusal(capsys, "fit", str(data), "--efects", "station") == line
    assert _refusal(capsys, "fit", str(data), "--efects", "station", "-o", str(tmp_path / "a.onnx")) == line
    assert _refusal(capsys, "fit", str(data)) == ("posecorr fit: error: the following arguments are required: "
                                                  "-o/--output (see posecorr fit --help)")
    assert _refusal(capsys, "fit", str(data), "more.csv", "-o", str(tmp_path / "a.onnx")) == (
        "posecorr fit: error: unrecognized arguments: more.csv (see posecorr fit --help)")
    assert not (tmp_path / "a.onnx").exists()


def test_a_bad_option_value_names_the_option_not_the_table(tmp_path, capsys) -> None:
    """`--cv lo` and `--effects station,mout` were reported as the table's faults
    ("good.csv: unknown effect 'mout'"); they are the option's, with the likely name, and
    fit finds them before it reads the table."""
    from posecorr.effects import EFFECTS

    data = tmp_path / "good.csv"
    write_table(simulate(2, seed=0).table.subset(np.arange(20)), data)
    out = str(tmp_path / "a.onnx")
    assert _refusal(capsys, "fit", str(data), "--cv", "lo", "-o", out) == (
        "posecorr fit: error: --cv takes none, loo or a number of folds in 2..1000, got 'lo'")
    fitted = [name for name, effect in EFFECTS.items() if not effect.random]   # noise is refused by name
    assert "noise" in EFFECTS and "noise" not in fitted
    for verb, extra in (("fit", ["-o", out]), ("diagnose", [])):
        assert _refusal(capsys, verb, str(data), "--effects", "station,mout", *extra) == (
            f"posecorr {verb}: error: --effects: unknown effect 'mout' (did you mean mount?); "
            f"expected one of {', '.join(fitted)}; for an effect of your own, give the --effect-file that defines it")
    assert _refusal(capsys, "fit", "/no/such.csv", "--cv", "lo", "-o", out).startswith(
        "posecorr fit: error: /no/such.csv")  # a missing table is still found first, by its path check


def test_an_effect_of_ones_own_without_its_effect_file_is_told_to_give_it(tmp_path, capsys) -> None:
    """`fit --effects station,mount,session_strain` without the --effect-file that defines
    session_strain (a proposal of diagnose) only offered "did you mean strain?": the likely
    fault is the file forgotten, which every verb's --effects now names, in the words of
    diagnose and report --model; and with the file the name is taken."""
    from posecorr.cli import main
    from posecorr.effects import unregister_effect

    data, mine = tmp_path / "session.csv", tmp_path / "mine.py"
    write_table(simulate(2, seed=0).table.subset(np.arange(20)), data)
    mine.write_text("from posecorr.forms import Strain\n\n\nclass SessionStrain(Strain):\n"
                    "    name = 'session_strain'\n    generic = False\n")
    out = str(tmp_path / "a.onnx")
    for verb, extra in (("fit", ["-o", out]), ("diagnose", [])):
        said = _refusal(capsys, verb, str(data), "--effects", "station,mount,session_strain", *extra)
        assert said.startswith(f"posecorr {verb}: error: --effects: unknown effect 'session_strain' (did you mean "
                               "strain?); expected one of "), said
        assert said.endswith("; for an effect of your own, give the --effect-file that defines it"), said
    said = _refusal(capsys, "simulate", "--session", "--effects", "session_strain", "-o", str(tmp_path / "s.csv"))
    assert said.endswith("; for an effect of your own, give the --effect-file that defines it"), said
    try:
        assert main(["fit", str(data), "--effect-file", str(mine), "--effects", "station,mount,session_strain",
                     "--method", "none", "--cv", "loo", "-o", out]) == 0
    finally:
        unregister_effect("session_strain")   # as the next process finds the catalogue


def test_an_effect_named_twice_or_an_empty_name_is_refused_by_every_verb(tmp_path, capsys) -> None:
    """`fit --effects station,mount,mount` fitted, and wrote mount both fitted and held;
    diagnose and report with `station,station` ended in numpy's "matmul: Input operand 1 has a
    mismatch"; `station,,mount` was taken as `station,mount`. Each is the option's fault, in
    simulate's words, before any work."""
    from posecorr.cli import main

    data, model, page = tmp_path / "good.csv", tmp_path / "m.onnx", tmp_path / "r.html"
    write_table(simulate(2, seed=0).table.subset(np.arange(20)), data)
    assert main(["fit", str(data), "--effects", "station", "--method", "none", "--cv", "none", "-o",
                 str(model)]) == 0
    capsys.readouterr()
    for verb, extra in (("fit", ["--method", "none", "--cv", "loo", "-o", str(tmp_path / "x.onnx")]),
                        ("diagnose", []), ("report", ["--model", str(model), "-o", str(page)])):
        assert _refusal(capsys, verb, str(data), "--effects", "station,mount,mount", *extra) == (
            f"posecorr {verb}: error: --effects: effect 'mount' is given twice in 'station,mount,mount'")
        assert _refusal(capsys, verb, str(data), "--effects", "station,,mount", *extra) == (
            f"posecorr {verb}: error: --effects: an effect name is empty in 'station,,mount' (two separators in a "
            "row, or one at an end)")
    assert _refusal(capsys, "simulate", "--session", "--effects", "sweep,sweep", "-o", str(tmp_path / "s.csv")) == (
        "posecorr simulate: error: --effects: effect 'sweep' is given twice in 'sweep,sweep'")
    assert not (tmp_path / "x.onnx").exists() and not page.exists()


def test_diagnose_cv_takes_a_number_of_folds_and_says_so(capsys) -> None:
    """diagnose's help said "as fit's --cv K" and `--cv loo` got "expected an integer": the
    help and the error say it takes a number of folds, and why not loo."""
    from posecorr.cli import build_parser

    verb_parsers = next(a for a in build_parser()._actions if a.dest == "verb").choices
    for verb in ("diagnose", "report"):
        cv = next(a for a in verb_parsers[verb]._actions if "--cv" in a.option_strings)
        assert cv.help.startswith("number of folds of the diagnosis's held-out test (whole poses), 2..1000 (default: 5)")
    assert _refusal(capsys, "diagnose", "d.csv", "--cv", "loo") == (
        "posecorr diagnose: error: argument --cv: expected a number of folds in 2..1000, got 'loo' (the diagnosis "
        "needs folds: fit's none and loo are not taken here) (see posecorr diagnose --help)")


def test_simulate_takes_bare_effect_names_separated_by_commas(tmp_path, capsys) -> None:
    """`--effects sweep,range_scale` was "unknown effect 'sweep,range_scale'"; bare names may
    be separated by ',', and where values make ',' ambiguous the error says to use ';'. A
    session of 50 poses, beyond the drawn 6-40, is what --poses asks."""
    from posecorr.cli import main

    capsys.readouterr()
    assert main(["simulate", "--session", "--seed", "3", "--poses", "50", "--effects", "sweep,range_scale",
                 "-o", str(tmp_path / "s.csv"), "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["n"] == 50 and {"sweep", "range_scale"} <= set(payload["effects"])
    assert _refusal(capsys, "simulate", "--session", "--effects", "sweep,range_scale=0.01", "-o",
                    str(tmp_path / "t.csv")) == (
        "posecorr simulate: error: --effects: unknown effect 'sweep,range_scale': separate effects with ';', "
        "as values take ',' (sweep;drift=0.002,-0.001,0.0015,1800)")


def test_every_argument_of_the_main_verbs_has_help_with_its_default() -> None:
    """fit's --method had no help and showed no default; now every argument of these verbs
    says what it is, and fit's --effects names the registry's effects."""
    from posecorr.cli import build_parser
    from posecorr.effects import EFFECTS

    verb_parsers = next(a for a in build_parser()._actions if a.dest == "verb").choices
    for verb in ("simulate", "fit", "diagnose", "report", "apply", "demo"):
        bare = [a.dest for a in verb_parsers[verb]._actions if not a.help]
        assert bare == [], (verb, bare)
    fit = {a.dest: a.help for a in verb_parsers["fit"]._actions}
    assert fit["method"].endswith("(default: pmc)")
    # a network nobody named is sized to the table: both defaults are said
    assert fit["epochs"].endswith("(default: 1000; 200 for the network a smaller table gets, see --hidden)")
    assert fit["hidden"].endswith("(default: 20-20-20-20 where the table holds 10 numbers for each of its weights, "
                                  "else 5 trained 200 epochs)")
    # the effects a model fits: not the noise a simulation draws, which simulate's help names too
    assert f"known: {', '.join(name for name in EFFECTS if name != 'noise')} (" in fit["effects"]
    simulated = next(a for a in verb_parsers["simulate"]._actions if a.dest == "effects")
    assert f"known: {', '.join(EFFECTS)} (" in simulated.help
    session = next(a for a in verb_parsers["simulate"]._actions if a.dest == "session")
    assert session.help.startswith("a realistic session: 6-40 poses unless --poses or --robot (30-60) says otherwise")
    assert "Experiment III" in verb_parsers["demo"].description


def test_percentages_print_in_plain_digits() -> None:
    """A fit that does far worse than the rigid fit said "3.2e+02 % worse"."""
    from posecorr.textui import percent
    from posecorr.train.pipeline import Candidate, _note_fallback

    assert [percent(v) for v in (6.81, 0.0512, 320.4, 1e4, 12345.0, -3.2, 0.0)] == \
        ["6.8", "0.051", "320", "10,000", "12,000", "-3.2", "0"]
    notes: list[str] = []
    _note_fallback(Candidate("pmc"), Candidate("rigid-joint", rigid="joint"), {"rmse_total": 4.204},
                   {"rmse_total": 1.0}, False, notes, {"rmse_pos": 0.001})
    assert notes == ["pmc did worse on held-out poses than the best rigid fit, rigid-joint (4.204 against 1 "
                     "rmse_total, 320 % worse): returning rigid-joint"]


def test_a_core_without_the_physics_stage_on_unregistered_frames_is_told_why(tmp_path) -> None:
    """A core asked for with no effects on frames metres apart has to learn their offset and
    falls back to the rigid fit; the note says so and names the stage that fits the
    registration first. With the stage, or with registered frames, no such words."""
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    data = tmp_path / "s.csv"
    write_table(simulate_session(2, n=12, spread="full", position_only=False, unremovable=0.0).table, data)
    hint = "no physics stage came before the core, so it had to learn their offset: --effects station,mount fits"
    for effects, told in (([], True), (["--effects", "station,mount"], False)):
        out = posecorr("fit", str(data), "--method", "pmc", *effects, "--json", "-o", str(tmp_path / "m.onnx"))
        assert out.returncode == 0, out.stderr
        notes = " ".join(json.loads(out.stdout)["notes"])
        assert (hint in notes) is told, notes
        assert ("the frames are unregistered (raw rmse_pos" in notes) is told


def test_a_fit_that_falls_back_says_so_where_it_names_the_model(tmp_path) -> None:
    """On the real 11-pose session auto's choice does worse held out than the joint rigid fit
    (tests/test_sessions.py): the written model is the rigid fit, and the line naming it says
    that it is not the one asked for, before the scores of auto's choice on all poses."""
    import shutil

    data = tmp_path / "exp1.csv"
    shutil.copy(Path(__file__).resolve().parent / "data" / "realdata" / "20201002_Exp1.csv", data)
    run = posecorr("fit", str(data), "--effects", "station,mount", "--method", "auto", "--cv", "loo",
                   "-o", str(tmp_path / "m.onnx"), cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert ("; model: rigid-joint, not the one asked for: it did worse held out (see the note); auto's inner "
            "cross-validation on all poses, rmse_total: physics ") in lines[0]
    assert any(line.startswith("  note: auto (its choice in each outer fold; physics on all poses) did worse on "
                               "held-out poses than the best rigid fit, rigid-joint") for line in lines)
    # the rigid fit's registration and lever in the effects' units (Param.unit): rad, m
    mount = next(line for line in lines if line.startswith("  mount: d = ["))
    assert re.fullmatch(r"  mount: d = \[[^]]+\] rad; e = \[[^]]+\] m", mount), mount


def test_a_model_and_a_table_given_in_each_others_place_are_named_with_the_order(tmp_path, capsys) -> None:
    """`apply DATA MODEL` (report's order) said "not a valid ONNX model (unsupported wire type
    4 (field 5))" of the table, and `report MODEL --model DATA` "missing column meas_x" of the
    model: every verb that takes a model or a table says which the file is, by its first bytes
    or else its name, and the order, in one line before any work."""
    import importlib.util

    from posecorr.cli.failures import EXTRA_MODULES

    model = Path(__file__).resolve().parents[1] / "models" / "pmc-zhou.onnx"
    data = tmp_path / "d.csv"
    write_table(simulate(3, seed=0).table.subset(np.arange(20)), data)
    table_dat, model_bin, text_onnx, empty_onnx = (tmp_path / n for n in ("t.dat", "m.bin", "text.onnx", "e.onnx"))
    table_dat.write_bytes(data.read_bytes())          # the bytes say what each is, not the name
    model_bin.write_bytes(model.read_bytes())
    text_onnx.write_text("meas_x,meas_y\n1,2\n")
    empty_onnx.write_bytes(b"")                       # no bytes to go by: the name says it
    out = tmp_path / "out"
    table_first = {"report": "the order is posecorr report DATA --model MODEL",
                   "diagnose": "the order is posecorr diagnose DATA --model MODEL"}
    cases = [
        (["apply", str(data), str(model), "-o", str(out)], f"{data} is a pose table, not a model: "
                                                           "the order is posecorr apply MODEL DATA"),
        (["apply", str(table_dat), str(model_bin), "-o", str(out)], f"{table_dat} is a pose table, not a model: "
                                                                     "the order is posecorr apply MODEL DATA"),
        (["apply", str(model), str(model), "-o", str(out)], f"{model} is a model, not a pose table: "
                                                            "the order is posecorr apply MODEL DATA"),
        (["apply", str(model), str(empty_onnx), "-o", str(out)], f"{empty_onnx} is a model, not a pose table: "
                                                                 "the order is posecorr apply MODEL DATA"),
        (["fit", str(model), "-o", str(out)], f"{model} is a model, not the pose table posecorr fit takes"),
        (["sweep", str(model_bin)], f"{model_bin} is a model, not the pose table posecorr sweep takes"),
    ]
    for verb, order in table_first.items():
        extra = ["-o", str(out)] if verb == "report" else []
        cases += [([verb, str(model), "--model", str(data), *extra], f"{model} is a model, not a pose table: {order}"),
                  ([verb, str(data), "--model", str(text_onnx), *extra],
                   f"{text_onnx} is a pose table, not a model: {order}")]
    ros2 = all(importlib.util.find_spec(m) is not None for m in EXTRA_MODULES["ros2"])
    for verb in ("info", "bench", "compile", *(("ros2",) if ros2 else ())):
        extra = ["-o", str(out)] if verb == "compile" else []
        cases.append(([verb, str(data), *extra], f"{data} is a pose table, not the model posecorr {verb} takes"))
    for argv, message in cases:
        assert _refusal(capsys, *argv) == f"posecorr {argv[0]}: error: {message}", argv
    assert not out.exists()
    from posecorr.cli import main

    assert main(["apply", str(model_bin), str(table_dat), "-o", str(out)]) == 0   # in their places: no refusal


def test_simulate_says_when_an_effect_value_is_beyond_any_tracker(tmp_path) -> None:
    """`--effects sweep=5,5,0,0` (degrees typed for radians) was simulated without a word; the
    values outside the catalogue's plausible range are named, the table written as asked."""
    out = posecorr("simulate", "--session", "--poses", "8", "--effects", "sweep=5,0.002,0,0", "-o",
                   str(tmp_path / "s.csv"))
    assert out.returncode == 0 and (tmp_path / "s.csv").exists()
    assert out.stderr.strip().splitlines() == [
        "posecorr: warning: --effects: sweep.phase_x = 5 rad lies outside the plausible -0.01 to 0.01 rad; "
        "simulated as given"]
    quiet = posecorr("simulate", "--session", "--poses", "8", "--effects", "sweep=0.005,0.002,0,0", "-o",
                     str(tmp_path / "q.csv"))
    assert quiet.returncode == 0 and quiet.stderr == ""


def test_an_output_over_a_file_of_the_other_kind_is_refused(tmp_path) -> None:
    """fit's model written over a pose table, simulate's and apply's table over a model, an
    effect file or a page, compile's C over either, report's page, diagnose's proposal or
    fit's saved estimator over a table or a model, is refused before any work (they replaced
    the file without a word); the files are intact."""
    table, model = tmp_path / "session.csv", tmp_path / "model.onnx"
    assert posecorr("simulate", "--session", "--poses", "12", "--seed", "1", "-o", str(table)).returncode == 0
    assert posecorr("fit", str(table), "--effects", "station,mount", "--method", "none", "-o",
                    str(model)).returncode == 0
    other, effect_file, page = tmp_path / "other.csv", tmp_path / "mine.py", tmp_path / "page.html"
    other.write_bytes(table.read_bytes())
    effect_file.write_text("from posecorr.effects import Effect\n")
    page.write_text("<!DOCTYPE html>\n<html><body>a report</body></html>\n")
    kept = {path: path.read_bytes() for path in (table, model, other, effect_file, page)}
    for argv, said in [
        (("fit", str(table), "--effects", "station,mount", "--method", "none", "-o", str(other)),
         f"{other} is a pose table, and posecorr fit writes a model there"),
        (("simulate", "--session", "--poses", "12", "-o", str(model)),
         f"{model} is a model, and posecorr simulate writes a pose table there"),
        (("apply", str(model), str(table), "-o", str(model)), str(model)),
        (("compile", str(model), "-o", str(other)), f"{other} is a pose table, and posecorr compile writes a C source"),
        (("report", str(table), "--model", str(model), "-o", str(other)),
         f"{other} is a pose table, and posecorr report writes a report page there"),
        (("diagnose", str(table), "--effects", "station,mount", "--propose", str(model)),
         f"{model} is a model, and posecorr diagnose writes an effect file there"),
        (("fit", str(table), "--method", "none", "--save", str(model), "-o", str(tmp_path / "new.onnx")),
         f"{model} is a model, and posecorr fit writes a saved estimator there"),
        (("apply", str(model), str(table), "-o", str(effect_file)),
         f"{effect_file} is an effect file, and posecorr apply writes a pose table there"),
        (("apply", str(model), str(table), "-o", str(page)),
         f"{page} is a report page, and posecorr apply writes a pose table there")]:
        out = posecorr(*argv)
        assert out.returncode == 2 and said in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert {path: path.read_bytes() for path in kept} == kept


def test_diagnose_propose_refuses_a_hand_written_effect_file(tmp_path) -> None:
    """`diagnose --propose FILE` replaced a hand-written effect file (a copy of
    examples/space_strain.py) without a word, as an effect file is what it writes; now only an
    earlier proposal is replaced (tests/test_propose.py), this one is refused before any work,
    in one line that names it and what to do, and it is intact."""
    table, mine = tmp_path / "session.csv", tmp_path / "mine.py"
    assert posecorr("simulate", "--session", "--poses", "12", "--seed", "1", "-o", str(table)).returncode == 0
    mine.write_bytes((Path(__file__).parents[1] / "examples" / "space_strain.py").read_bytes())
    kept = mine.read_bytes()
    out = posecorr("diagnose", str(table), "--effects", "station,mount", "--propose", str(mine))
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [
        f"posecorr diagnose: error: {mine} is an effect file that posecorr diagnose did not write: refusing to "
        "replace it (give another name, or remove it)"], out.stderr
    assert mine.read_bytes() == kept


def test_a_model_with_a_user_effect_names_its_effect_file_before_the_work(tmp_path) -> None:
    """diagnose/report --model on a model fitted with an --effect-file, given without it,
    blamed the table ("session.csv: unknown effect 'z_scale'"), report only after rebuilding
    its held-out predictions; now the model is named, with what to give, before any work."""
    table, model, page = tmp_path / "session.csv", tmp_path / "model.onnx", tmp_path / "r.html"
    effect_file = Path(__file__).parent / "data" / "example_effect.py"
    assert posecorr("simulate", "--session", "--robot", "ur5e", "--poses", "30", "--seed", "1", "--effect-file",
                    str(effect_file), "--effects", "z_scale", "-o", str(table)).returncode == 0
    fitted = posecorr("fit", str(table), "--effect-file", str(effect_file), "--effects", "station,mount,z_scale",
                      "--method", "none", "--cv", "loo", "-o", str(model), "--json")
    assert fitted.returncode == 0 and "z_scale" in json.loads(fitted.stdout)["effects"], fitted.stderr
    for verb, extra in (("diagnose", ()), ("report", ("-o", str(page)))):
        out = posecorr(verb, str(table), "--model", str(model), *extra)
        assert out.returncode == 2 and out.stderr.strip().splitlines() == [
            f"posecorr {verb}: error: {model}: uses effect 'z_scale', which is not in the catalogue: give the "
            "--effect-file that defines it"], out.stderr
    assert not page.exists()
    # another file's z_scale (a proposal of another session: every proposal names its effect
    # session_strain) gave another model than the one fitted, without a word
    other = tmp_path / "other_effect.py"
    other.write_text(effect_file.read_text().replace('Param("k", 1, (0.01,)', 'Param("k", 2, (0.01, 0.0)'))
    for verb, extra in (("diagnose", ()), ("report", ("-o", str(page)))):
        out = posecorr(verb, str(table), "--model", str(model), "--effect-file", str(other), *extra)
        assert out.returncode == 2 and out.stderr.strip().splitlines() == [
            f"posecorr {verb}: error: {model} was fitted with z_scale.k of 1 values; z_scale as {other} defines it "
            "has 2: give the effect file the model was fitted with"], out.stderr
    assert not page.exists()
    # the same name and sizes, another map (x scaled, not z): another model, said before any work
    swapped = tmp_path / "x_scale.py"
    swapped.write_text(effect_file.read_text().replace("p[..., 2] + k * (p[..., 2] - xp.const(ctx.c, p)[..., 2])",
                                                       "p[..., 2] + k * (p[..., 0] - xp.const(ctx.c, p)[..., 0])"))
    assert swapped.read_text() != effect_file.read_text()
    for verb, extra in (("diagnose", ()), ("report", ("-o", str(page)))):
        out = posecorr(verb, str(table), "--model", str(model), "--effect-file", str(swapped), *extra)
        assert out.returncode == 2 and out.stderr.strip().splitlines() == [
            f"posecorr {verb}: error: {model} was fitted with another z_scale than {swapped} defines: at the "
            "model's values its map moves the same poses elsewhere (other terms, another formula): give the effect "
            "file the model was fitted with"], out.stderr
    assert not page.exists()
    # the file it was fitted with, a copy under another name with another comment: the same map
    copy = tmp_path / "copy.py"
    copy.write_text("# my copy\n" + effect_file.read_text())
    out = posecorr("diagnose", str(table), "--model", str(model), "--effect-file", str(copy))
    assert out.returncode == 0, out.stderr


def test_diagnosis_options_are_checked_first_and_say_what_they_did(tmp_path) -> None:
    """`noise` is refused by fit and diagnose as the option's fault (it named the table);
    report refuses a misspelled effect before rebuilding any prediction, and --effects beside
    --no-diagnosis; diagnose --model with --effects that are not the model's says what it
    ranks against, and on a table without times, which effects it did not try; diagnose --propose with nothing proposed says the file was not written
    (and that one already there is from before)."""
    table, model = tmp_path / "session.csv", tmp_path / "model.onnx"
    assert posecorr("simulate", "--session", "--poses", "12", "--seed", "1", "-o", str(table)).returncode == 0
    for argv in (("fit", "-o", str(model)), ("diagnose",)):
        out = posecorr(argv[0], str(table), "--effects", "station,noise", *argv[1:])
        assert out.returncode == 2 and out.stderr.strip().splitlines()[-1].endswith(
            "error: --effects: noise is random measurement noise, which a simulation draws and no model corrects; "
            "leave it out (the fit weighs the residuals by the noise it estimates)"), out.stderr
    assert posecorr("fit", str(table), "--effects", "station,mount", "--method", "none", "-o", str(model)).returncode == 0
    out = posecorr("report", str(table), "--model", str(model), "--effects", "station,mout", "-o", str(tmp_path / "r.html"))
    assert out.returncode == 2 and "unknown effect 'mout' (did you mean mount?)" in out.stderr
    assert "rebuilding" not in out.stderr and not (tmp_path / "r.html").exists()
    out = posecorr("report", str(table), "--model", str(model), "--effects", "station", "--no-diagnosis", "-o",
                   str(tmp_path / "r.html"))
    assert out.returncode == 2 and "which --no-diagnosis leaves out" in out.stderr
    # --cv K beside --no-diagnosis was ignored without a word (the model keeps its fit's folds)
    for cv in (("--cv", "3"), ("--folds", "3")):
        out = posecorr("report", str(table), "--model", str(model), *cv, "--no-diagnosis", "-o",
                       str(tmp_path / "r.html"))
        assert out.returncode == 2 and out.stderr.strip().splitlines()[-1].endswith(
            "error: --cv sets the diagnosis's folds, which --no-diagnosis leaves out"), out.stderr
    assert not (tmp_path / "r.html").exists()
    diagnosed = [json.loads(posecorr("diagnose", str(table), "--model", str(model), *extra, "--json").stdout)["notes"]
                 for extra in ((), ("--effects", "station,sweep"))]
    untimed = ("not tried: drift, time_trend (acting over the session's time, they need a time column t, which this "
               "table lacks)")
    # the frames are unregistered: no feature is taken from a station nobody placed in them
    from posecorr.analysis.features import UNPLACED_STATION

    unplaced = f"residual structure by feature: {UNPLACED_STATION}"
    # nor is a verdict on an effect that bends about that station (sweep, in the model in the second) more than
    # one about the nominal station, and each says so
    bound = [[note for note in notes if "about where the base station stands" in note] for notes in diagnosed]
    assert all(len(notes) == 1 for notes in bound) and bound[1][0].startswith("sweep"), bound
    diagnosed = [[note for note in notes if note not in said] for notes, said in zip(diagnosed, bound)]
    assert diagnosed[0] == [untimed, unplaced] and diagnosed[1][:3] == [
        untimed, unplaced, f"--effects station, sweep are not {model}'s (mount, station): the candidates are ranked "
        "against a refit of --effects; the model's own residuals feed the residual structure by feature"]
    # and the advice completes the registration --effects leave half-done
    assert len(diagnosed[1]) == 4 and diagnosed[1][3].startswith("mount joins station in the advice"), diagnosed[1]
    stale = tmp_path / "proposed.py"   # an earlier proposal: the one effect file --propose may replace
    old = '"""Proposed by `posecorr diagnose session.csv --effects station --propose proposed.py`.\n"""\n'
    stale.write_text(old)
    out = posecorr("diagnose", str(table), "--effects", "station,mount", "--propose", str(stale))
    assert out.returncode == 0, out.stderr
    assert "no proposal: " in out.stdout and f"{stale}: not written (the file there is from before)" in out.stdout
    assert stale.read_text() == old


def test_network_options_go_with_the_mlp(tmp_path) -> None:
    """--hidden, --network, --activation, --trainer and --epochs set an MLP: with another method
    they were ignored without a word; now refused, naming them."""
    table = tmp_path / "session.csv"
    assert posecorr("simulate", "--session", "--poses", "12", "--seed", "1", "-o", str(table)).returncode == 0
    for method, extra, said in [("none", ("--hidden", "5", "--trainer", "adam", "--epochs", "3"),
                                 "--hidden, --trainer, --epochs set the network of --method mlp; --method none "
                                 "takes none"),
                                ("pmc", ("--network", "16/2"), "--network sets the network of --method mlp"),
                                ("auto", ("--activation", "tansig"), "--activation sets the network")]:
        out = posecorr("fit", str(table), "--method", method, *extra, "-o", str(tmp_path / "m.onnx"))
        assert out.returncode == 2 and said in out.stderr, out.stderr
        assert not (tmp_path / "m.onnx").exists()


def test_a_fit_on_the_test_split_keeps_its_rigid_floor_and_a_timed_model_benches(tmp_path) -> None:
    """The file of a fit on the fixed test split states the best rigid fit beside its held-out
    figures (the graph's own figures replaced the floor); a saved estimator given where a
    model goes is named as one, with the command that exports it; `bench` runs a model that
    takes time (onnxruntime was fed no t)."""
    from posecorr.controller import read_info

    table, model = tmp_path / "e3.csv", tmp_path / "e3.onnx"
    assert posecorr("simulate", "--experiment", "3", "--seed", "0", "-o", str(table)).returncode == 0
    assert posecorr("fit", str(table), "--method", "none", "--effects", "station,mount", "-o", str(model)).returncode == 0
    saved = tmp_path / "e3.est"
    assert posecorr("fit", str(table), "--method", "none", "--effects", "station,mount", "-o", str(tmp_path / "x.onnx"),
                    "--save", str(saved)).returncode == 0
    for verb in (("info", str(saved)), ("apply", str(saved), str(table), "-o", str(tmp_path / "o.csv"))):
        out = posecorr(*verb)   # it said "not a valid ONNX model (model field 14 at byte 0 is not bytes)"
        assert out.returncode == 2 and f"{saved} is a saved estimator (fit --save), not the model posecorr " \
            f"{verb[0]} takes: `posecorr export {saved} -o MODEL.onnx` writes its model" in out.stderr, out.stderr
    metrics = read_info(model)["test_metrics"]
    assert metrics["rigid"]["name"].startswith("rigid-") and {"test", "raw", "rigid"} <= set(metrics)
    assert posecorr("info", str(model)).stdout.count("the best rigid fit (") == 1
    timed, drift = tmp_path / "drift.csv", tmp_path / "drift.onnx"
    assert posecorr("simulate", "--session", "--poses", "20", "--seed", "2", "--duration", "800", "--effects",
                    "drift=0.002,0,0,900", "-o", str(timed)).returncode == 0
    assert posecorr("fit", str(timed), "--effects", "station,mount,drift", "--method", "none", "--cv", "5", "-o",
                    str(drift)).returncode == 0
    out = posecorr("bench", str(drift), "--n", "20", "--batch", "20", "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert {"c", "onnxruntime", "onnxruntime_iobinding"} <= set(result["single_pose_median_us"])
    # the C runtime's load time, which posecorr-bench measures, and the load it ran under
    assert result["c_load_us"] > 0 and len(result["load_average"]) == 3
    out = posecorr("bench", str(drift), "--n", "20", "--batch", "20")
    assert re.fullmatch(r"load average \d+\.\d\d while it ran; the C runtime loads the file in \d+ us \(median of "
                        r"21, file read included\)", out.stdout.strip().splitlines()[-1]), out.stdout


def test_bench_takes_another_producers_model_as_apply_does(tmp_path) -> None:
    """An unsigned model is refused with the option that loads it, and bench (posecorr-bench
    too) now has it: every back end timed."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "runtime_c" / "tests"))
    import graphs

    g = graphs.G()
    model = tmp_path / "other.onnx"
    model.write_bytes(g.model(g.op("Mul", ["pose", g.f32(np.ones(7, np.float32))]),
                              metadata=graphs.BOUNDED).SerializeToString())
    out = posecorr("bench", str(model), "--n", "20", "--batch", "20")
    assert out.returncode == 2 and "on the command line --allow-unsigned" in out.stderr
    out = posecorr("bench", str(model), "--n", "20", "--batch", "20", "--allow-unsigned", "--json")
    assert out.returncode == 0, out.stderr
    assert all(value is not None for value in json.loads(out.stdout)["single_pose_median_us"].values())


def test_fit_states_a_parity_tolerance_widened_by_far_coordinates(tmp_path) -> None:
    """A tracker frame 900 m from its origin: float32 steps there are 61 um, and the parity
    check allows 64 of them, 3.9 mm. fit says so beside the parity figure (it printed the
    figure alone); at a few metres it keeps to the figure."""
    table = simulate(3, seed=0).table.subset(np.arange(40))
    near = tmp_path / "near.csv"
    write_table(table, near)
    table.meas_p = table.meas_p + 900.0
    far = tmp_path / "far.csv"
    write_table(table, far)
    tol = 64 * float(np.spacing(np.float32(np.abs(table.meas_p).max())))
    for path, widened in ((near, False), (far, True)):
        out = posecorr("fit", str(path), "--effects", "station,mount", "--method", "none", "-o",
                       str(tmp_path / f"{path.stem}.onnx"))
        assert out.returncode == 0, out.stderr
        written = out.stdout.strip().splitlines()[-1]
        assert ("(tolerance " in written) == widened, written
        if widened:
            assert f"(tolerance {tol:.1e} m: 64 float32 steps at the largest coordinate)" in written, written


def test_diagnose_shows_a_candidate_whose_fits_ran_away_as_such(tmp_path) -> None:
    """Exp1 diagnosed with the mount alone (frames unregistered, the station's metres of offset
    left): the quadratic form's fold fits predict the held-out poses ~1e12 m off. The table
    says "ran away" where a candidate's held-out error grows 100-fold, and one line says so
    with the figure; --json keeps the numbers."""
    data = str(Path(__file__).parent / "data" / "realdata" / "20201002_Exp1.csv")
    text = posecorr("diagnose", data, "--effects", "mount")
    result = json.loads(posecorr("diagnose", data, "--effects", "mount", "--json").stdout)
    assert text.returncode == 0, text.stderr
    away = [c for c in result["candidates"] if c["cv_rmse_after"] >= 100 * c["cv_rmse_before"]]
    assert [c["effect"] for c in away] == ["quadratic"], [(c["effect"], c["cv_rmse_after"]) for c in away]
    rows = {line.split()[1]: line for line in text.stdout.splitlines() if re.match(r"\d+ +\w+ +(form|effect) ", line)}
    for c in result["candidates"]:
        assert ("ran away" in rows[c["effect"]]) == (c in away), rows[c["effect"]]
    assert (f"ran away: quadratic's fits predict the held-out poses {away[0]['cv_rmse_after']:.3g} m + rad off "
            f"(against {away[0]['cv_rmse_before']:.4g} before") in text.stdout


def test_fit_auto_on_the_fixed_split_scores_every_rigid_variant(tmp_path) -> None:
    """`--method auto` without --cv on a table of 100 poses or more (the fixed split) ended in
    KeyError 'rigid-lever': auto's candidates hold one rigid variant, and the floor is chosen
    among all of them. Now every variant is fitted and scored on the validation poses, the
    floor is their best, and the model is written."""
    from posecorr.simulate import simulate_session
    from posecorr.train.pipeline import rigid_candidates

    session = simulate_session(4, n=120).table
    data = tmp_path / "s120.csv"
    write_table(session, data)
    run = posecorr("fit", str(data), "--method", "auto", "-o", str(tmp_path / "a.onnx"), "--json", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert set(result["rigid_rmse_total"]) == {c.name for c in rigid_candidates(session)}
    scores = result["rigid_rmse_total"]
    assert result["baseline"]["name"] == min(scores, key=scores.get)
    assert "test" in result and result["n_heldout"] == 18 and (tmp_path / "a.onnx").exists()


def test_fit_says_what_an_option_could_not_do(tmp_path) -> None:
    """--representation with --method none set nothing (no core) and was taken in silence,
    as --subsample beyond the table's rows was; the one is refused, the other said."""
    data = tmp_path / "d.csv"
    write_table(simulate(3, seed=0).table.subset(np.arange(150)), data)
    out = posecorr("fit", str(data), "--method", "none", "--representation", "R", "-o", str(tmp_path / "n.onnx"))
    assert out.returncode == 2 and out.stderr.strip() == (
        "posecorr fit: error: --representation sets the orientation representation of the core after the physics "
        "stage; --method none fits none")
    out = posecorr("fit", str(data), "--method", "pmc", "--subsample", "500", "-o", str(tmp_path / "p.onnx"))
    assert out.returncode == 0, out.stderr
    assert "warning: --subsample 500: " in out.stderr and "has 150 rows; every one is fitted" in out.stderr
    assert out.stdout.startswith("d.csv: 150 poses") or f"{data}: 150 poses" in out.stdout.splitlines()[0]


def test_diagnose_warns_of_an_effect_the_fit_it_advises_would_refuse(tmp_path, capsys) -> None:
    """An effect written with numpy calls: diagnose (numpy) ran it, then advised a fit that
    refused it as untraceable. The warning comes first, with the line that does not trace."""
    from posecorr.cli import main
    from posecorr.effects import EFFECTS, unregister_effect
    from posecorr.simulate import simulate_session

    path = tmp_path / "scalar.py"
    path.write_text("import numpy as np\nfrom posecorr.effects import Effect, Param\n\n\nclass Scalar(Effect):\n"
                    "    name = 'scalar'\n    changes_rotation = False\n"
                    "    params = (Param('a', 1, (0.001,), 0.001, '1'),)\n\n"
                    "    def forward(self, p, R, theta, ctx):\n"
                    "        a = float(np.asarray(theta).reshape(-1)[0])\n        return p * (1 + a), R\n")
    data = tmp_path / "s.csv"
    write_table(simulate_session(1, n=20, spread="full", position_only=False, unremovable=0.0).table, data)
    try:
        assert main(["diagnose", str(data), "--effect-file", str(path), "--effects", "station,mount"]) == 0
    finally:
        if "scalar" in EFFECTS:
            unregister_effect("scalar")
    warning = capsys.readouterr().err.splitlines()[0]
    assert warning.startswith(f"posecorr: warning: effect file {path}: effect 'scalar': its map does not trace into "
                              "the ONNX graph fit exports: "), warning
    assert "(line 11: a = float(np.asarray(theta).reshape(-1)[0]))" in warning
    assert warning.endswith("; fit refuses it until then")


def test_a_model_naming_an_effect_twice_is_refused_naming_the_model(tmp_path) -> None:
    """A model whose metadata names an effect twice (edited, then signed again): the diagnosis
    refitted two copies and failed in numpy's words on the table ("matmul: Input operand 1 has
    a mismatch ..."). It is the model's fault, named before any work."""
    import onnx

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "runtime_c" / "tests"))
    import graphs

    table, model = tmp_path / "session.csv", tmp_path / "model.onnx"
    assert posecorr("simulate", "--session", "--poses", "20", "--seed", "1", "-o", str(table)).returncode == 0
    assert posecorr("fit", str(table), "--effects", "station,mount", "--method", "none", "--cv", "5",
                    "-o", str(model)).returncode == 0
    edited = onnx.load(model)
    next(e for e in edited.metadata_props if e.key == "effects").value = '["mount", "station", "station"]'
    model.write_bytes(graphs.signed(edited))
    out = posecorr("diagnose", str(table), "--model", str(model))
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [
        f"posecorr diagnose: error: {model}: its metadata 'effects' names 'station' more than once, which no fit "
        "writes: the file was edited"], out.stderr


def test_diagnose_prints_its_test_one_condition_to_a_line():
    """The presence test ran to one 900-character line; each condition is a line now, the
    semicolons inside its parentheses kept, and nothing of the --json wording lost."""
    from posecorr.analysis.diagnose import PRESENT_TEST
    from posecorr.cli.diagnose import _test_lines

    test = PRESENT_TEST.format(alpha=0.001, folds=5, gain=0.005, share=0.9)
    head, *items = _test_lines(test)
    assert head == "present where all of these hold:" and all(item.startswith("  - ") for item in items)
    conditions = [item[4:] for item in items]
    assert "; ".join(conditions) == test
    assert len(conditions) == 5 and conditions[1] == "held-out whitened error lower in every one of 5 folds"
    assert all(c.count("(") == c.count(")") for c in conditions)
