"""Regenerate the shipped models in models/: `python -m tools.models` (`make models`).

Data: the simulator's default Experiment III (seed 0, 3375 poses, position + orientation)
and Experiment I (seed 0, 1331 poses, position only), `posecorr.simulate.simulate`.

Split (`test_split`): the paper keeps a fixed 15 % test set and never trains on it; it is
the protocol's (`posecorr.train.splits.FixedSplit`, seed SPLIT_SEED), the same one
`posecorr fit` and `posecorr demo` test on; everything else is training data (the MLP
trainers make their own validation split inside it when they use one).

Models (each a `posecorr.train.spec.ModelSpec`, named by its `file_name`: `pmc-<rep>.onnx`,
`mlp-<rep>-<act>-<arch>-<trainer>.onnx`):
- Exp III: PMC for eaa, quat, R, zhou, and per representation an MLP with the activation
  and trainer of the lowest min RMSE_total in the paper's table 4 (eaa radbas 16/2, quat
  tansig 8/2, R logsig 16/2, zhou tansig 16/2; trainer 2 = BR). zhou keeps the paper's
  architecture 16 (20-20-20-20: the network of the latency benchmark); the others use
  architecture 8 (20-20) to keep `make models` within minutes.
- Exp I: position-only PMC and the paper's best network of table 2, tansig 15/1
  (15-15-15-15, LM).
The networks are trained with at most `MLP_EPOCHS` epochs (the paper: 1000), so that
regeneration takes minutes; the cards say so. Everything is deterministic from the seeds.

Each model gets a markdown card (`<name>.md`) with data, method, test metrics, parity,
operator counts, file size, the box of poses it corrects (`input_bounds`) and the
regeneration command; `models/index.json` lists them.

`python -m tools.models --metadata-only` rewrites, without refitting, what the code states
about the models already in models/: the split's recipe (`split`), the box of poses
(`input_bounds`, kept where recorded), the cone of training orientations of a core that reads
the orientation (`training_orientations`, kept where recorded), the correction reach
(`correction_reach`, the model's graph on the training poses and drawn ones, as `to_onnx`
records it) and the digest
(`model_digest`), and each card from the file and the regenerated data. The data is
regenerated from its seeds and checked to be the model's; the file is rewritten with
`serialize_aligned` and signed, its graph and weights byte for byte the same (checked).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from posecorr.train.spec import ModelSpec
from posecorr.train.splits import TEST_FRACTION, FixedSplit

SPLIT_SEED = 0
DATA_SEED = 0
MLP_EPOCHS = 100
MODELS_DIR = Path(__file__).resolve().parent.parent / "models"


@dataclass(frozen=True)
class Spec:
    """One shipped model: the experiment it is fitted on, its core and the label of the paper's
    best network of its representation (the table's "tansig 16/2"; the core may be smaller)."""

    experiment: int
    model: ModelSpec
    paper_label: str = ""

    @property
    def name(self) -> str:
        """The model's file name without ".onnx": the spec's, with "-exp1" for an orientation
        model fitted on Experiment I."""
        return self.model.stem + ("-exp1" if self.experiment == 1 and self.model.with_rotation else "")


SPECS: tuple[Spec, ...] = (
    Spec(3, ModelSpec("pmc", "eaa")), Spec(3, ModelSpec("pmc", "quat")), Spec(3, ModelSpec("pmc", "R")),
    Spec(3, ModelSpec("pmc", "zhou")),
    Spec(3, ModelSpec("mlp", "eaa", (20, 20), "radbas", "br"), "radbas 16/2"),
    Spec(3, ModelSpec("mlp", "quat", (20, 20), "tansig", "br"), "tansig 8/2"),
    Spec(3, ModelSpec("mlp", "R", (20, 20), "logsig", "br"), "logsig 16/2"),
    Spec(3, ModelSpec("mlp", "zhou"), "tansig 16/2"),            # the spec's defaults: the paper's 16/2
    Spec(1, ModelSpec("pmc", "pos")),
    Spec(1, ModelSpec("mlp", "pos", (15, 15, 15, 15), "tansig", "lm"), "tansig 15/1"),
)


def test_split(n: int, seed: int = SPLIT_SEED, fraction: float = TEST_FRACTION) -> tuple[np.ndarray, np.ndarray]:
    """(train_index, test_index): the protocol's fixed, seeded test set (`FixedSplit`);
    the rest (its training and validation rows) is training data here."""
    train, val, test = FixedSplit(test_fraction=fraction).indices(n, seed)
    return np.sort(np.concatenate([train, val])), test


def split_text(seed: int = SPLIT_SEED) -> str:
    """The `split` metadata of a shipped model: the test rows' recipe, from `FixedSplit`."""
    return f"test rows {FixedSplit().test_recipe(seed)}, the others train"


def experiment_data(experiment: int, seed: int = DATA_SEED, split_seed: int = SPLIT_SEED) -> dict[str, Any]:
    """Simulated table split into train / test: {"measured", "reference", "train", "test",
    "with_rotation", "raw", "noise_floor", "seed", "split_seed"}."""
    from posecorr.simulate import simulate

    result = simulate(experiment, seed=seed)
    table = result.table
    measured, reference = np.asarray(table.measured, float), np.asarray(table.reference, float)
    train, test = test_split(len(measured), split_seed)
    return {"measured": measured, "reference": reference, "train": train, "test": test,
            "with_rotation": bool(table.has_orientation), "raw": result.raw,
            "noise_floor": result.noise_floor, "seed": seed, "split_seed": split_seed}


def evaluate(corrected: np.ndarray, measured: np.ndarray, reference: np.ndarray,
             with_rotation: bool) -> dict[str, float | None]:
    """rmse_pos (m), rmse_rot (rad), rmse_total and the improvements over the raw data."""
    from posecorr.metrics import improvement, pose_metrics

    raw = pose_metrics(reference, measured, with_rotation)
    corr = pose_metrics(reference, corrected, with_rotation)
    return {**corr, **improvement(raw, corr), "raw_rmse_total": raw["rmse_total"]}


def make_estimator(spec: Spec, epochs: int = MLP_EPOCHS) -> Any:
    from dataclasses import replace

    return replace(spec.model, epochs=epochs).make(seed=0)


def _fmt(v: Any, digits: int = 5) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def model_card(spec: Spec, report: dict[str, Any], data: dict[str, Any], epochs: int) -> str:
    """The markdown card of one exported model."""
    meta = report["metadata"]
    exp_name = {1: "I", 2: "II", 3: "III"}[spec.experiment]
    lines = [
        f"# {spec.name}", "",
        f"Correction model for the HTC VIVE tracker, fitted on the simulated Experiment {exp_name} "
        f"(posecorr `simulate(experiment={spec.experiment}, seed={data['seed']})`, default effect mix).", "",
        *_card_data(meta, data),
        *_card_method(spec, meta, epochs),
        *_card_metrics(meta["test_metrics"]),
        *_card_export(spec, report, epochs),
    ]
    return "\n".join(lines)


def _card_data(meta: dict[str, Any], data: dict[str, Any]) -> list[str]:
    """The card's data section: the table, its fixed split, digest and raw error."""
    n, n_test = len(data["measured"]), len(data["test"])
    return [
        "## Data", "",
        f"- N = {n} poses ({'position and orientation' if data['with_rotation'] else 'position only'}); "
        f"fixed test rows: {n_test}, `{FixedSplit().test_recipe(data['split_seed'])}` "
        f"(`posecorr.train.splits.FixedSplit`, seed {data['split_seed']}); training rows: the other {n - n_test}.",
        f"- training-data digest: `{meta.get('training_data_digest')}` (`posecorr.export.metadata.data_digest` "
        "of the training rows' measured and reference poses, float64).",
        f"- raw data (whole table): rmse_pos {_fmt(data['raw']['rmse_pos'])} m, rmse_rot "
        f"{_fmt(data['raw']['rmse_rot'])} rad, rmse_total {_fmt(data['raw']['rmse_total'])}; "
        f"simulator noise floor rmse_total {_fmt(data['noise_floor']['rmse_total'])}.", "",
    ]


def _card_method(spec: Spec, meta: dict[str, Any], epochs: int) -> list[str]:
    """The card's method section: the polynomial map or the network and its training."""
    model = spec.model
    if not model.is_network:
        return ["## Method", "",
                f"- PMC (paper 2.3): full quadratic least-squares map of the {model.representation} "
                f"input vector, {meta.get('architecture')}."]
    table = 2 if spec.experiment == 1 else 4
    best = (f"the best of its representation in the paper's table {table}" if model.label == spec.paper_label else
            f"the best of its representation in the paper's table {table} is `{spec.paper_label}`, the same "
            "activation and trainer on a larger network, left out to keep `make models` within minutes")
    return ["## Method", "",
            f"- MLP (paper 2.4): {model.representation} representation, hidden layers "
            f"{'-'.join(map(str, model.hidden))}, activation {model.activation}, trainer {model.trainer} "
            f"(paper label `{model.label}`: {best}); at most {epochs} epochs "
            f"(paper: 1000), stopped after {meta.get('epochs')} ({meta.get('stop_reason')})."]


def _card_metrics(test: dict[str, Any]) -> list[str]:
    """The card's table of test metrics, raw against corrected."""
    lines = [
        "",
        "## Test metrics (fixed test split)", "",
        "| metric | raw | corrected | improvement |", "|---|---|---|---|",
    ]
    raw_test = test.get("raw", {})
    for key, imp in (("rmse_pos", "improvement_pos"), ("rmse_rot", "improvement_rot"),
                     ("rmse_total", "improvement_total")):
        unit = {"rmse_pos": " m", "rmse_rot": " rad", "rmse_total": ""}[key]
        lines.append(f"| {key}{unit} | {_fmt(raw_test.get(key))} | {_fmt(test.get(key))} | {_fmt(test.get(imp), 4)} |")
    return lines


def _card_export(spec: Spec, report: dict[str, Any], epochs: int) -> list[str]:
    """The card's export and regenerate sections: the file, its parity, interface and reach."""
    meta, parity = report["metadata"], report["parity"]
    return [
        "", "## Export", "",
        f"- file size {report['file_size']} bytes, {report['n_nodes']} nodes, opset {meta['opset']}; operators: "
        + ", ".join(f"{k} {v}" for k, v in report["op_counts"].items()) + ".",
        f"- parity (onnxruntime float32 vs float64 `predict`): max position error "
        f"{parity['max_pos_m']:.2e} m, max rotation error {parity['max_rot_rad']:.2e} rad "
        f"(training poses: {parity['train']['max_pos_m']:.2e} m / {parity['train']['max_rot_rad']:.2e} rad; "
        f"{parity['random_poses']}: {parity['random']['max_pos_m']:.2e} m / "
        f"{parity['random']['max_rot_rad']:.2e} rad); tolerance 1e-5 m / 1e-5 rad: "
        f"{'passed' if parity['passed'] else 'FAILED'}.",
        "- input `pose` float32 [N, 7] (x, y, z in m, qw, qx, qy, qz); output `corrected` float32 [N, 7]"
        + (" (qw >= 0)." if spec.model.with_rotation else " (orientation passed through)."),
        bounds_line(meta["input_bounds"]),
        *cone_lines(meta),
        reach_line(meta["correction_reach"]),
        "", "## Regenerate", "",
        "```", "make models        # or: python -m tools.models" + (
            "" if epochs == MLP_EPOCHS else f" --epochs {epochs}"), "```", "",
        "`posecorr info models/" + spec.name + ".onnx` prints the metadata stored in the file.", "",
    ]


def bounds_line(box: list[list[float]]) -> str:
    """The card's line on the box of positions the model corrects."""
    axes = ", ".join(f"{axis} {a:.3f}..{b:.3f}" for axis, a, b in zip("xyz", *box))
    return (f"- input_bounds: {axes} m (the training positions' box widened by half its extent, "
            "at least 0.1 m); a pose outside is refused (PC_ERR_RANGE), on every back end.")


def cone_lines(meta: dict[str, Any]) -> list[str]:
    """The card's line on the orientations the model was fitted on, where it states them."""
    from posecorr import coverage

    cone = coverage.cone_of(meta.get(coverage.KEY))
    if cone is None:
        return []
    mean = ", ".join(f"{v:.4f}" for v in cone["mean"])
    return [f"- training_orientations: within {np.rad2deg(cone['within']):.1f} deg of the mean (qw, qx, qy, qz) "
            f"{mean}; `posecorr apply` and the ROS 2 node count the poses more than "
            f"{np.rad2deg(coverage.MARGIN):.1f} deg beyond, and still correct them."]


def reach_line(reach: list[float]) -> str:
    """The card's line on how far the model's corrections reach."""
    return (f"- correction_reach: {reach[0]:.4f} m, {reach[1]:.4f} rad (twice the largest correction on "
            "the training poses and 10,000 poses drawn over the input box and all orientations, plus "
            "0.01 m and 0.01 rad); a pose corrected farther is refused "
            "(PC_ERR_RUNTIME), on every back end. The file carries its CRC-32C (`model_digest`).")


def build(spec: Spec, data: dict[str, Any], out_dir: Path, epochs: int = MLP_EPOCHS) -> dict[str, Any]:
    """Fit, evaluate on the test split, export with parity check, write the card."""
    from posecorr.export import Parity, to_onnx
    from posecorr.export.parity import run_onnx

    M, R, tr, te = data["measured"], data["reference"], data["train"], data["test"]
    est = make_estimator(spec, epochs)
    est.fit(M[tr], R[tr])
    with_rot = data["with_rotation"]
    test_metrics = evaluate(est.predict(M[te]), M[te], R[te], with_rot)
    from posecorr.metrics import pose_metrics

    test_metrics["raw"] = pose_metrics(R[te], M[te], with_rot)
    test_metrics["n"] = int(len(te))
    path = out_dir / f"{spec.name}.onnx"
    report = to_onnx(est, path, measured=M[tr], reference=R[tr], parity=Parity.RAISE,
                     test_metrics=test_metrics, experiment=spec.experiment, data_seed=data["seed"],
                     split=split_text(data["split_seed"]),
                     paper_label=spec.paper_label or None, max_epochs=epochs if spec.model.is_network else None)
    # The card's numbers must be what the exported graph does, not only the float64 model.
    onnx_metrics = evaluate(run_onnx(path, M[te]), M[te], R[te], with_rot)
    report["onnx_test_metrics"] = onnx_metrics
    (out_dir / f"{spec.name}.md").write_text(model_card(spec, report, data, epochs), encoding="utf-8")
    return report


def _graph_bytes(model: Any) -> bytes:
    """The graph and its weights, without the initializers' alignment padding (`doc_string`,
    which `serialize_aligned` sizes to the metadata in front of it)."""
    graph = type(model.graph)()
    graph.CopyFrom(model.graph)
    for tensor in graph.initializer:
        tensor.ClearField("doc_string")
    return graph.SerializeToString()


def rewrite_metadata(out_dir: Path = MODELS_DIR) -> list[dict[str, Any]]:
    """Rewrites, without refitting, the metadata the code states (module doc) in the shipped
    models in `out_dir` and their cards; returns {"file", "split", "correction_reach",
    "file_size"} per model. The data is regenerated from its seeds; the stored raw test
    metrics must come out again (to 1e-9) as the proof that it is the data the model was
    fitted on (the digest of the training data is of the exact bits, which the simulator's
    last digits may change from one machine's BLAS to another's)."""
    import onnx

    from posecorr.controller import digest
    from posecorr.controller.onnx_meta import read_info
    from posecorr.export.aligned import serialize_aligned
    from posecorr.export.metadata import encode_value
    from posecorr.metrics import pose_metrics
    from posecorr.safeio import write_bytes

    done = []
    data_cache: dict[int, dict[str, Any]] = {}
    index_path = out_dir / "index.json"
    index = json.loads(index_path.read_text(encoding="utf-8"))
    for spec in SPECS:
        path = out_dir / f"{spec.name}.onnx"
        data = data_cache.setdefault(spec.experiment, experiment_data(spec.experiment))
        M, R, te = data["measured"], data["reference"], data["test"]
        model = onnx.load(str(path))
        meta = {p.key: p.value for p in model.metadata_props}
        stored = json.loads(meta["test_metrics"])["raw"]["rmse_total"]
        again = pose_metrics(R[te], M[te], data["with_rotation"])["rmse_total"]
        if abs(stored - again) > 1e-9 * abs(stored):
            raise SystemExit(f"{path}: the regenerated data is not the data of this model "
                             f"(raw test rmse_total {again!r}, stored {stored!r}); refit with `make models`")
        graph = _graph_bytes(model)
        reach = _state(meta, path, data)
        meta[digest.KEY] = digest.PLACEHOLDER
        del model.metadata_props[:]
        for key in sorted(meta):
            entry = model.metadata_props.add()
            entry.key, entry.value = key, meta[key]
        blob = digest.sign(serialize_aligned(model))
        if _graph_bytes(onnx.load_from_string(blob)) != graph:
            raise SystemExit(f"{path}: rewriting the metadata changed the graph; nothing written")
        write_bytes(path, blob)
        info = read_info(path)
        report = {"metadata": info, "parity": info["parity"], "file_size": info["file_size"],
                  "n_nodes": info["node_count"], "op_counts": info["op_counts"]}
        epochs = info.get("max_epochs") or MLP_EPOCHS
        write_bytes(out_dir / f"{spec.name}.md", model_card(spec, report, data, epochs).encode("utf-8"))
        for entry in index["models"]:
            if entry["file"] == path.name:
                entry["file_size"] = len(blob)
        done.append({"file": path.name, "split": meta["split"], "correction_reach": reach, "file_size": len(blob)})
        print(f"{path}: split {meta['split']}, correction_reach {encode_value(reach)}, {len(blob)} bytes", flush=True)
    write_bytes(index_path, (json.dumps(index, indent=1) + "\n").encode("utf-8"))
    return done


def _state(meta: dict[str, str], path: Path, data: dict[str, Any]) -> list[float]:
    """Sets in `meta` (a model's metadata, as stored) what the code states about the model at
    `path` fitted on `data`'s training rows; returns its correction reach."""
    from posecorr import coverage
    from posecorr.export.metadata import encode_value
    from posecorr.export.onnx_export import input_bounds, model_reach

    M, tr = data["measured"], data["train"]
    meta["split"] = split_text(data["split_seed"])
    # a box already recorded stays as it is (its last digits may differ on this BLAS)
    box = json.loads(meta["input_bounds"]) if "input_bounds" in meta else input_bounds(M[tr])
    reach, _ = model_reach(path, M[tr], box)
    meta["input_bounds"] = meta.get("input_bounds") or encode_value(box)
    meta["correction_reach"] = encode_value(reach)
    # the cone is stated as an export states it, and like the box kept where recorded
    if coverage.reads_orientation(meta.get("representation")) and coverage.KEY not in meta:
        meta[coverage.KEY] = encode_value(coverage.cone(M[tr][:, 3:7]))
    return reach


def demo_physics_pmc(path: Path) -> int:
    """Fits and exports the demo's physics + PMC (zhou) pipeline (`posecorr demo`'s, on its fixed
    split's training and validation rows); returns its node count. `make programs` compiles its
    programs, the benchmarks time it, the 32 KB firmware carries it."""
    from posecorr.demo import physics_pmc
    from posecorr.simulate import simulate
    from posecorr.train.protocol import split_indices

    data = simulate(3, seed=0).table
    train, val, _ = split_indices(data.n, 0)
    rows = np.sort(np.concatenate([train, val]))
    model = physics_pmc().fit(data.measured[rows], data.reference[rows])
    return model.to_onnx(path, measured=data.measured[rows], reference=data.reference[rows])["n_nodes"]


def unshipped_mlp(representation: str, hidden: tuple[int, ...], path: Path, activation: str | None = None,
                  rows: int = 120) -> Path:
    """A table-1 MLP nobody shipped: fitted two epochs (Levenberg-Marquardt, random_state 1) on
    `rows` rows of the simulated Experiment III and exported to `path` by the project's
    exporter. Near-random weights of the right architecture: what an instruction count, a
    timing or a bit-for-bit comparison of two back ends needs."""
    from posecorr.export import to_onnx
    from posecorr.simulate import simulate
    from posecorr.train.mlp import MLP

    table = simulate(3, seed=0).table
    idx = np.linspace(0, len(table.measured) - 1, rows).astype(int)
    m, r = table.measured[idx], table.reference[idx]
    chosen = {} if activation is None else {"activation": activation}
    est = MLP(representation=representation, hidden=tuple(hidden), trainer="lm", epochs=2, random_state=1,
              **chosen).fit(m, r)
    # two epochs leave a float32 graph that may miss the float64 estimator by more than the
    # exporter's parity tolerance: recorded, not refused (the weights do not change the work)
    to_onnx(est, path, measured=m, reference=r, parity="warn")
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.models", description=__doc__.split("\n")[0])
    parser.add_argument("-o", "--out", type=Path, default=MODELS_DIR, help="output directory (default: models/)")
    parser.add_argument("--epochs", type=int, default=MLP_EPOCHS, help="max MLP epochs")
    parser.add_argument("--only", default="", help="comma-separated model names to build (default: all)")
    parser.add_argument("--demo-physics-pmc", type=Path, metavar="OUT.onnx",
                        help="fit and export only the demo's physics + PMC model, to OUT.onnx")
    parser.add_argument("--metadata-only", action="store_true",
                        help="rewrite the existing models' stated metadata (split, bounds, reach, digest) and "
                             "their cards without refitting")
    args = parser.parse_args(argv)
    if args.demo_physics_pmc is not None:
        demo_physics_pmc(args.demo_physics_pmc)
        return 0
    if args.metadata_only:
        rewrite_metadata(args.out)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    wanted = {w.strip() for w in args.only.split(",") if w.strip()}
    data_cache: dict[int, dict[str, Any]] = {}
    index = []
    for spec in SPECS:
        if wanted and spec.name not in wanted:
            continue
        data = data_cache.setdefault(spec.experiment, experiment_data(spec.experiment))
        t0 = time.perf_counter()
        report = build(spec, data, args.out, args.epochs)
        test = report["metadata"]["test_metrics"]
        print(f"{spec.name:40s} test rmse_pos {test['rmse_pos']:.5f} m  rmse_rot {_fmt(test['rmse_rot'])} rad  "
              f"rmse_total {test['rmse_total']:.5f}  parity {report['parity']['max_pos_m']:.1e} m "
              f"{report['parity']['max_rot_rad']:.1e} rad  {report['n_nodes']} nodes  "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
        model = spec.model
        index.append({"file": f"{spec.name}.onnx", "card": f"{spec.name}.md", "experiment": spec.experiment,
                      "method": model.method, "representation": model.representation,
                      "activation": model.activation, "hidden": list(model.hidden), "trainer": model.trainer,
                      "test_metrics": {k: test[k] for k in ("rmse_pos", "rmse_rot", "rmse_total")},
                      "parity": {k: report["parity"][k] for k in ("max_pos_m", "max_rot_rad", "passed")},
                      "n_nodes": report["n_nodes"], "file_size": report["file_size"]})
    index_path = args.out / "index.json"
    if wanted and index_path.exists():
        # --only rebuilds some models: the others keep their entries, in the specs' order
        rebuilt = {entry["file"]: entry for entry in index}
        kept = json.loads(index_path.read_text(encoding="utf-8"))["models"]
        index = [rebuilt.pop(entry["file"], entry) for entry in kept] + list(rebuilt.values())
    index_path.write_text(json.dumps({"models": index, "data_seed": DATA_SEED, "split_seed": SPLIT_SEED,
                                      "max_epochs": args.epochs}, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
