"""The orientations a model was fitted on, as its file states them, and `apply`'s count of
the poses turned beyond them (posecorr.coverage), against scipy's Rotation: its mean (the
same chordal mean, computed its own way) and its angles."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr import coverage
from posecorr.cli import main
from posecorr.controller.onnx_meta import read_info

EXP2 = Path(__file__).parent / "data" / "realdata" / "20200717_Exp2.csv"
QUAT = ("meas_qw", "meas_qx", "meas_qy", "meas_qz")


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def _turned(source: Path, target: Path, degrees: float) -> Rotation:
    """`source` with each measured orientation turned by `degrees` about its own x axis;
    returns the turned orientations."""
    rows = _rows(source)
    turned = Rotation.from_quat([[float(r[c]) for c in QUAT] for r in rows], scalar_first=True) \
        * Rotation.from_euler("x", degrees, degrees=True)
    for row, q in zip(rows, turned.as_quat(scalar_first=True)):
        row.update({c: repr(float(v)) for c, v in zip(QUAT, q)})
    with target.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return turned


@pytest.fixture(scope="module")
def pmc(tmp_path_factory) -> tuple[Path, Path]:
    """`fit`'s default (physics + PMC on zhou) on Exp2's nine poses at one orientation."""
    where = tmp_path_factory.mktemp("coverage")
    data, model = where / "exp2.csv", where / "pmc.onnx"
    data.write_bytes(EXP2.read_bytes())
    assert main(["fit", str(data), "--effects", "station,mount", "--method", "pmc", "-o", str(model)]) == 0
    return data, model


def test_the_file_states_the_cone_of_its_training_orientations(pmc, capsys) -> None:
    data, model = pmc
    stated = read_info(model)[coverage.KEY]
    truth = Rotation.from_quat([[float(r[c]) for c in QUAT] for r in _rows(data)], scalar_first=True)
    mean = truth.mean()
    np.testing.assert_allclose((mean.inv() * Rotation.from_quat(stated["mean"], scalar_first=True)).magnitude(), 0,
                               atol=1e-9)
    assert stated["within"] == pytest.approx(np.max((mean.inv() * truth).magnitude()), abs=1e-9)
    assert 0 < stated["within"] < np.deg2rad(0.5)   # the session's nine poses, within half a degree
    assert main(["info", str(model)]) == 0
    assert (f"  fitted on orientations within {np.degrees(stated['within']):.3g} deg of their mean "
            "(apply counts the poses turned beyond)") in capsys.readouterr().out


def test_apply_counts_the_poses_turned_beyond_them(pmc, tmp_path: Path, capsys) -> None:
    """Its own poses: none. Turned by 2 degrees: all nine, by as much as scipy says they lie
    beyond the cone, and the text says so; they are corrected all the same."""
    data, model = pmc
    stated = read_info(model)[coverage.KEY]
    assert main(["apply", str(model), str(data), "-o", str(tmp_path / "own.csv"), "--json"]) == 0
    own = json.loads(capsys.readouterr().out)["beyond_training_orientations"]
    assert own["count"] == 0 and own["rows"] == []

    turned = _turned(data, tmp_path / "turned.csv", 2.0)
    past = (Rotation.from_quat(stated["mean"], scalar_first=True).inv() * turned).magnitude() - stated["within"]
    assert main(["apply", str(model), str(tmp_path / "turned.csv"), "-o", str(tmp_path / "out.csv"), "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    beyond = payload["beyond_training_orientations"]
    assert beyond["count"] == int(np.sum(past > coverage.MARGIN)) == 9
    assert beyond["rows"] == list(range(2, 11))   # the file's lines, after the header
    assert beyond["largest_rad"] == pytest.approx(np.max(past), abs=1e-6)
    assert payload["refused"]["count"] == 0 and payload["n"] == 9

    assert main(["apply", str(model), str(tmp_path / "turned.csv"), "-o", str(tmp_path / "out.csv")]) == 0
    text = capsys.readouterr().out
    assert (f"note: 9 poses (rows 2, 3, 4, 5, 6, 7, 8, 9, 10) lie up to {np.degrees(np.max(past)):.3g} deg beyond "
            f"the orientations pmc.onnx was fitted on (within {np.degrees(stated['within']):.3g} deg") in text, text


def test_a_core_that_does_not_read_the_orientation_states_none(tmp_path: Path, capsys) -> None:
    """The physics stage alone turns with the tracker as physics does: no cone, nothing counted."""
    data, model = tmp_path / "exp2.csv", tmp_path / "physics.onnx"
    data.write_bytes(EXP2.read_bytes())
    assert main(["fit", str(data), "--effects", "station,mount", "--method", "none", "-o", str(model)]) == 0
    capsys.readouterr()
    assert coverage.KEY not in read_info(model)
    _turned(data, tmp_path / "turned.csv", 5.0)
    assert main(["apply", str(model), str(tmp_path / "turned.csv"), "-o", str(tmp_path / "out.csv"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["beyond_training_orientations"] is None


@pytest.mark.parametrize("value", ["[1, 0, 0, 0]", '{"mean": [1, 0, 0], "within": 0.1}',
                                   '{"mean": [1, 0, 0, 0], "within": "0.001"}', '{"mean": [1, 0, 0, 0], "within": true}',
                                   '{"mean": [1, 0, 0, 0], "within": 7}', '{"mean": [1, 0, 0, "0"], "within": 0.1}',
                                   '{"mean": [2, 0, 0, 0], "within": 0.1}', '{"mean": [1, 0, 0, 0], "within": -1}',
                                   '{"mean": [1, 0, 0, 0]}', "not json"])
def test_a_cone_that_is_not_one_is_no_statement(value: str) -> None:
    assert coverage.stated({coverage.KEY: value}) is None
    assert coverage.Beyond({coverage.KEY: value, "representation": "zhou"}).record() is None


def test_a_pose_the_model_refused_is_not_counted_as_turned(pmc, tmp_path: Path, capsys) -> None:
    """`--keep-going` writes a lost pose (zero quaternion) as nan: refused, and no orientation
    to count; the eight others, turned, are."""
    data, model = pmc
    _turned(data, tmp_path / "turned.csv", 2.0)
    rows = _rows(tmp_path / "turned.csv")
    rows[1].update({c: "0" for c in QUAT})
    with (tmp_path / "lost.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    assert main(["apply", str(model), str(tmp_path / "lost.csv"), "-o", str(tmp_path / "out.csv"), "--keep-going",
                 "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["refused"]["count"] == 1 and payload["refused"]["rows"] == [3]
    assert payload["beyond_training_orientations"]["count"] == 8
    assert 3 not in payload["beyond_training_orientations"]["rows"]


def test_one_pose_beyond_is_said_in_the_singular(pmc, tmp_path: Path, capsys) -> None:
    data, model = pmc
    _turned(data, tmp_path / "turned.csv", 5.0)
    rows = _rows(data)
    rows[4] = _rows(tmp_path / "turned.csv")[4]
    with (tmp_path / "one.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    assert main(["apply", str(model), str(tmp_path / "one.csv"), "-o", str(tmp_path / "out.csv")]) == 0
    text = capsys.readouterr().out
    assert "note: 1 pose (row 6) lies " in text and "deg beyond the orientations pmc.onnx" in text, text
    assert "a fit on poses that turn as this one does would know)\n" in text, text


def test_one_pose_applied_is_said_in_the_singular(pmc, tmp_path: Path, capsys) -> None:
    data, model = pmc
    rows = _rows(data)[:1]
    with (tmp_path / "first.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    assert main(["apply", str(model), str(tmp_path / "first.csv"), "-o", str(tmp_path / "out.csv")]) == 0
    assert capsys.readouterr().out.startswith(f"1 pose corrected with {model} "), "the head line's count"
