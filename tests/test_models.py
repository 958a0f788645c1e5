"""The shipped models in models/: valid ONNX, readable metadata, and their cards' numbers
reproduced from the seeds by applying the file (onnxruntime), not the Python estimator."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from posecorr.controller.onnx_meta import read_info
from posecorr.export.parity import run_onnx
from posecorr.metrics import pose_metrics
from posecorr.train.splits import FixedSplit, split_indices
from tools.models import evaluate, experiment_data

MODELS = Path(__file__).resolve().parent.parent / "models"
# The card's Data line: "N = 3375 poses (...); fixed test rows: 506, `<numpy expression in N>`".
CARD_SPLIT = re.compile(r"^- N = (\d+) poses .*; fixed test rows: (\d+), `([^`]+)`", re.M)
INDEX = MODELS / "index.json"
FILES = sorted(MODELS.glob("*.onnx"))


def _index() -> list[dict]:
    return json.loads(INDEX.read_text())["models"]


def test_index_lists_every_shipped_model():
    assert INDEX.exists(), "models/index.json missing: run `make models`"
    listed = {m["file"] for m in _index()}
    assert listed == {f.name for f in FILES}
    assert len(listed) == 10
    for m in _index():
        assert (MODELS / m["card"]).exists()


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_model_is_valid_and_describes_itself(path):
    model = onnx.load(path)
    onnx.checker.check_model(model, full_check=True)
    info = read_info(path)
    assert info["method"] in ("pmc", "mlp")
    assert info["representation"] in ("eaa", "quat", "R", "zhou", "pos")
    assert path.name.startswith(f"{info['method']}-{info['representation']}")
    for key in ("rmse_pos", "rmse_rot", "rmse_total", "improvement_total"):
        assert key in info["test_metrics"]
    assert info["parity"]["passed"] is True
    assert info["parity"]["max_pos_m"] <= 1e-5 and info["parity"]["max_rot_rad"] <= 1e-5
    assert info["training_data_digest"].startswith("sha256:")
    assert info["inputs"][0]["name"] == "pose" and info["outputs"][0]["name"] == "corrected"


_DATA: dict[tuple[int, int], dict] = {}


def _data(experiment: int, seed: int) -> dict:
    if (experiment, seed) not in _DATA:
        _DATA[experiment, seed] = experiment_data(experiment, seed)
    return _DATA[experiment, seed]


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
@pytest.mark.cpu_floats
def test_card_metrics_reproduced_on_regenerated_test_split(path):
    info = read_info(path)
    data = _data(info["experiment"], info["data_seed"])
    M, R, test = data["measured"], data["reference"], data["test"]
    got = evaluate(run_onnx(path, M[test]), M[test], R[test], data["with_rotation"])
    card = info["test_metrics"]
    assert card["n"] == len(test)
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        if card[key] is None:
            assert got[key] is None
            continue
        assert got[key] == pytest.approx(card[key], rel=0.01), key
    # The markdown card shows the same rmse_total (5 significant digits).
    text = path.with_suffix(".md").read_text()
    row = re.search(r"\| rmse_total \| [^|]+ \| ([0-9.e+-]+) \|", text)
    assert row and float(row.group(1)) == pytest.approx(card["rmse_total"], rel=1e-4)


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
@pytest.mark.cpu_floats
def test_cone_of_training_orientations_is_the_training_rows(path):
    """A shipped core that reads the orientation states its training rows' cone (scipy's
    mean and angles; the mean is the chordal one, so `within` is checked against it, and the
    mean against scipy's to a small fraction of the cone); a position-only one states none."""
    from scipy.spatial.transform import Rotation

    from posecorr import coverage

    info = read_info(path)
    stated = coverage.cone_of(info.get(coverage.KEY))
    if info["representation"] == "pos":
        assert coverage.KEY not in info
        return
    data = _data(info["experiment"], info["data_seed"])
    q = data["measured"][data["train"], 3:7]
    turns = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    mean = Rotation.from_quat(stated["mean"][[1, 2, 3, 0]])
    angles = (mean.inv() * turns).magnitude()
    assert stated["within"] == pytest.approx(angles.max(), abs=1e-6)
    assert (turns.mean().inv() * mean).magnitude() < 0.01 * stated["within"]


@pytest.mark.parametrize("path", [p for p in FILES if read_info(p).get("experiment") == 3], ids=lambda p: p.name)
@pytest.mark.cpu_floats
def test_exp3_model_generalises_to_a_fresh_simulation(path):
    """Same hardware and session effects, new noise draws and order (seed 1): the model's
    rmse_total over the whole fresh table stays within 10 % of its card."""
    info = read_info(path)
    data = _data(3, 1)
    M, R = data["measured"], data["reference"]
    got = evaluate(run_onnx(path, M), M, R, True)["rmse_total"]
    assert got == pytest.approx(info["test_metrics"]["rmse_total"], rel=0.10)


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
@pytest.mark.cpu_floats
def test_card_metrics_reproduced_by_posecorr_apply(path, tmp_path, capsys):
    """The user's route: the test split as a CSV through `posecorr apply` (C runtime)."""
    from posecorr.cli import main
    from posecorr.data import PoseTable, write_table

    info = read_info(path)
    data = _data(info["experiment"], info["data_seed"])
    M, R, test = data["measured"], data["reference"], data["test"]
    table = PoseTable(M[test, :3], M[test, 3:], R[test, :3], R[test, 3:] if data["with_rotation"] else None)
    write_table(table, tmp_path / "test.csv")
    capsys.readouterr()
    assert main(["apply", str(path), str(tmp_path / "test.csv"), "-o", str(tmp_path / "out.csv"), "--json"]) == 0
    corrected = json.loads(capsys.readouterr().out)["corrected"]
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        if info["test_metrics"][key] is None:
            assert corrected[key] is None
        else:
            assert corrected[key] == pytest.approx(info["test_metrics"][key], rel=0.01), key


def _recipe_rows(recipe: str, n: int) -> np.ndarray:
    """The rows a card's recipe names, evaluated as written with numpy and N alone."""
    return np.asarray(eval(recipe, {"__builtins__": {"round": round}, "numpy": np, "N": n}))


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
@pytest.mark.cpu_floats
def test_card_test_rows_are_the_rows_the_code_tests_on(path):
    """What the card says about its split, evaluated as written, names the rows the code
    tests on (`FixedSplit`, `tools.models`); the stored raw test error is the raw error of
    those rows of the regenerated data (another draw of 15 % gives another error)."""
    card = CARD_SPLIT.search(path.with_suffix(".md").read_text())
    assert card, f"{path.with_suffix('.md')}: no line '- N = ... poses ...; fixed test rows: ..., `recipe`'"
    n, n_test, recipe = int(card.group(1)), int(card.group(2)), card.group(3)
    info = read_info(path)
    assert recipe in info["split"], (recipe, info["split"])
    rows = _recipe_rows(recipe, n)
    data = _data(info["experiment"], info["data_seed"])
    assert len(data["measured"]) == n and len(rows) == n_test == info["test_metrics"]["n"]
    np.testing.assert_array_equal(rows, data["test"])
    np.testing.assert_array_equal(rows, FixedSplit().indices(n, data["split_seed"])[2])
    raw = pose_metrics(data["reference"][rows], data["measured"][rows], data["with_rotation"])
    assert raw["rmse_total"] == pytest.approx(info["test_metrics"]["raw"]["rmse_total"], rel=1e-9)


@pytest.mark.parametrize("n, seed", [(7, 0), (100, 3), (1331, 0), (3375, 0), (3375, 12)])
def test_split_recipe_is_the_draw(n, seed):
    """`FixedSplit.test_recipe`, evaluated, is `split_indices`' test set for any N and seed
    (a different seed draws other rows)."""
    rows = _recipe_rows(FixedSplit().test_recipe(seed), n)
    np.testing.assert_array_equal(rows, split_indices(n, seed)[2])
    if n >= 100:
        assert not np.array_equal(rows, _recipe_rows(FixedSplit().test_recipe(seed + 1), n))


PMC_FILES = [path for path in FILES if path.name.startswith("pmc-")]


def _wiring_names(graph) -> dict[str, str]:
    """The place of each tensor a node of `graph` makes inside it, by its name: the exporter
    names those by the Python frame that made each node (a list comprehension's own frame on
    3.11, its function's where 3.12 inlined comprehensions). The graph's input, output and
    initializer names are the same on every Python and are compared as they are."""
    outputs = {v.name for v in graph.output}
    inner = [t for n in graph.node for t in n.output if t not in outputs]
    return {name: f"#{place}" for place, name in enumerate(inner)}


def test_shipped_pmc_models_are_what_the_exporter_writes_today(tmp_path):
    """Each shipped PMC refitted from its seeds (`python -m tools.models --only`, a second in
    all) gives the shipped graph: the same nodes, and weights equal to float32 rounding (the
    fit's float64 sums differ across CPUs). The position-only decoder came to normalise its
    quaternion while the shipped pos models kept the old graph; the C runtime's compiled
    programs, written from models/, then missed every fresh pos export's decoder. The
    networks take minutes to train; their encoders and decoders are the PMCs'."""
    from onnx import numpy_helper

    from tools.models import main

    assert main(["--only", ",".join(path.stem for path in PMC_FILES), "-o", str(tmp_path)]) == 0
    for path in PMC_FILES:
        shipped, fresh = onnx.load(path).graph, onnx.load(tmp_path / path.name).graph
        names = [_wiring_names(g) for g in (shipped, fresh)]
        nodes = [[(n.op_type, [k.get(t, t) for t in n.input], [k.get(t, t) for t in n.output]) for n in g.node]
                 for g, k in zip((shipped, fresh), names)]
        assert nodes[0] == nodes[1], f"{path.name}: the exporter writes another graph; run `make models`"
        weights = [{w.name: numpy_helper.to_array(w) for w in g.initializer} for g in (shipped, fresh)]
        assert weights[0].keys() == weights[1].keys(), path.name
        for name, value in weights[0].items():
            np.testing.assert_allclose(weights[1][name], value, rtol=1e-5, atol=1e-6 * np.abs(value).max(initial=1.0),
                                       err_msg=f"{path.name}: {name}")
