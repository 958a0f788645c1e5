"""Where the base station stood (`--station-pose`): sweep, range scale and incidence bend about
it, and unregistered frames do not say where it is. Checked against the simulator's own
station, placed away from the paper's, and against scipy's Rotation."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr.analysis.diagnose import diagnose
from posecorr.data import read_table, write_table
from posecorr.geometry import parse_station_pose, station_pose
from posecorr.simulate import simulate_session
from posecorr.train.pipeline import CorrectionPipeline, cross_validate
from posecorr.train.splits import LeaveOneOut

# A station 1.5 m to the side of the paper's and 1 m above the cell, its -z on the cell's centre.
STATION = "1.5,-1.0,1.5,0.696191,0.379671,0.291693,0.534868"
SWEEP = {"sweep": np.array([1e-3, -1e-3, 0.02, -0.02])}


@pytest.fixture(scope="module")
def session():
    """50 robot-carried poses, a sweep about STATION, frames unregistered."""
    return simulate_session(3, extra=SWEEP, station_pose=STATION, n=50, robot="ur5e")


def test_the_option_reads_both_frames_and_refuses_in_one_line():
    paper = parse_station_pose("paper")
    assert paper.text is None and np.array_equal(paper.t, station_pose()[1])
    stated = parse_station_pose(" tracker:1,2,3,0,0,0,1 ")
    assert stated.in_tracker_frame and stated.text == "tracker:1,2,3,0,0,0,1"
    assert np.allclose(stated.R, Rotation.from_quat([0, 0, 1, 0]).as_matrix())   # scipy: scalar last
    R, t = np.diag([1.0, -1.0, -1.0]), np.array([0.1, 0.2, 0.3])
    R_S, t_S = stated.in_reference((R, t))
    assert np.allclose(R_S, R @ stated.R) and np.allclose(t_S, R @ [1, 2, 3] + t)
    for bad, why in [("tracker:paper", "expected paper"), ("1,2", "expected paper"), ("1,2,3,1,1,0,0", "norm 1.41"),
                     ("nan,0,0", "expected paper")]:
        with pytest.raises(ValueError, match=why):
            parse_station_pose(bad)


def test_the_simulators_tracker_frame_station_is_its_reference_station_moved_by_the_registration(session):
    text = session.station_in_tracker_frame()
    stated = parse_station_pose(text)
    w, v = session.effects["station"][:3], session.effects["station"][3:]
    W, c = Rotation.from_rotvec(w).as_matrix(), session.context.c
    reference = parse_station_pose(STATION)
    assert np.allclose(stated.t, c + W @ (reference.t - c) + v, atol=1e-6)
    assert np.allclose(stated.R, W @ reference.R, atol=1e-5)


def _loo_pos(table, effects):
    cv = cross_validate(lambda: CorrectionPipeline(effects), table, LeaveOneOut())
    return cv.metrics["rmse_pos"]


def test_stated_in_the_trackers_frame_the_sweep_is_found_and_fitted(session):
    table = session.table
    nominal = diagnose(table, ["station", "mount"])
    table.station_pose = session.station_in_tracker_frame()
    stated = diagnose(table, ["station", "mount"])
    present = {c["effect"] for c in stated["candidates"] if c["present"]}
    assert present == {"sweep"} and stated["proposal"] is None
    assert any("taken about the stated base station" in note for note in stated["notes"])
    # about the paper's station the sweep bends the wrong way: it takes half as much off
    after = {name: {c["effect"]: c["cv_rmse_after"] for c in result["candidates"]}["sweep"]
             for name, result in (("nominal", nominal), ("stated", stated))}
    assert after["stated"] < 0.6 * after["nominal"]
    # the held-out error falls to the noise floor only about the right station
    about_stated = _loo_pos(table, ("station", "mount", "sweep"))
    table.station_pose = None
    about_paper = _loo_pos(table, ("station", "mount", "sweep"))
    floor = session.noise_floor["rmse_pos"]
    assert about_stated < 1.2 * floor < 2 * floor < about_paper


def test_fit_states_the_station_and_report_rebuilds_its_held_out_figures(session, tmp_path, capsys):
    from posecorr.cli import main
    from posecorr.controller.onnx_meta import read_info

    data, model = tmp_path / "session.csv", tmp_path / "m.onnx"
    table = session.table
    table.station_pose = None
    write_table(table, data)
    where = session.station_in_tracker_frame()
    capsys.readouterr()
    assert main(["fit", str(data), "--effects", "station,mount,sweep", "--method", "none", "--cv", "loo",
                 "--station-pose", where, "-o", str(model), "--json"]) == 0
    fitted = json.loads(capsys.readouterr().out)
    placed = read_info(model)["station_pose"]
    assert placed["stated"] == where
    # the rigid fit places the station within millimetres of where the simulator put it
    truth = parse_station_pose(STATION)
    assert np.linalg.norm(np.array(placed["reference"][:3]) - truth.t) < 0.02
    assert (Rotation.from_quat(placed["reference"][3:], scalar_first=True).inv() \
        * Rotation.from_matrix(truth.R)).magnitude() < 0.02
    ledger = [json.loads(line) for line in (tmp_path / "session.csv.ledger.jsonl").read_text().splitlines()]
    assert ledger[-1]["station_pose"] == where
    # report takes the model's station: the held-out figures it rebuilds are the fit's
    assert main(["report", str(data), "--model", str(model), "-o", str(tmp_path / "r.html"), "--no-diagnosis",
                 "--json"]) == 0
    after = json.loads(capsys.readouterr().out)["after"]
    assert after["held_out"] and after["rmse_pos"] == pytest.approx(fitted["cv"]["rmse_pos"], rel=1e-9)
    page = (tmp_path / "r.html").read_text()
    x, y, z = placed["reference"][:3]
    assert f"--station-pose {where}; placed at ({x:.3f}, {y:.3f}, {z:.3f}) m in the reference frame" in page
    assert read_table(data).station_pose is None   # the table file itself is unchanged


@pytest.mark.parametrize("args, words", [
    (["--station-pose", "1,2"], "expected paper"),
    (["--station-pose", "tracker:paper"], "expected paper"),
])
def test_a_bad_station_pose_ends_in_one_line(tmp_path, capsys, args, words):
    from posecorr.cli import main

    data = tmp_path / "s.csv"
    write_table(simulate_session(1, n=12).table, data)
    assert main(["diagnose", str(data), "--effects", "station,mount", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and err[0].count("--station-pose") == 1


def test_simulate_places_the_station_in_the_reference_frame_only(tmp_path, capsys):
    from posecorr.cli import main

    assert main(["simulate", "--session", "--poses", "12", "--station-pose", "tracker:0,0,0",
                 "-o", str(tmp_path / "s.csv")]) == 2
    assert "simulate places the station in the reference frame" in capsys.readouterr().err


@pytest.mark.parametrize("value, words", [
    ('{"stated": 5}', "metadata station_pose"),
    ('"paper"', "metadata station_pose"),
    ('{"stated": "tracker:paper"}', "metadata station_pose: --station-pose 'tracker:paper': expected paper"),
])
def test_a_models_bad_station_pose_ends_in_one_line_naming_it(tmp_path, capsys, value, words):
    """The station a model states is read before any work; a value fit never writes is refused."""
    import onnx

    from posecorr.cli import main
    from posecorr.controller import digest

    data, model = tmp_path / "s.csv", tmp_path / "m.onnx"
    write_table(simulate_session(1, n=12).table, data)
    assert main(["fit", str(data), "--effects", "station,mount", "--method", "none", "--cv", "3",
                 "-o", str(model)]) == 0
    m = onnx.load(model)
    kept = [(e.key, e.value) for e in m.metadata_props if e.key != digest.KEY]
    del m.metadata_props[:]
    for key, text in kept + [("station_pose", value), (digest.KEY, digest.PLACEHOLDER)]:
        entry = m.metadata_props.add()
        entry.key, entry.value = key, text
    model.write_bytes(digest.sign(m.SerializeToString()))
    capsys.readouterr()
    for argv in (["report", str(data), "--model", str(model), "-o", str(tmp_path / "r.html"), "--no-diagnosis"],
                 ["diagnose", str(data), "--model", str(model)]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(model) in err[0] and words in err[0], err
    assert not (tmp_path / "r.html").exists()
