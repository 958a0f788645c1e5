"""Estimator -> .onnx: trace `forward` on symbolic tensors, check, verify parity, save.

The exporter knows nothing about what `forward` does (encodings, scaling, PMC, MLP,
physical-effect stages): whatever `_xp` calls it makes become nodes. It only fixes the
contract of docs/design.md: input `pose` float32 [N, 7], output `corrected` float32 [N, 7],
opset 17, operators from `export/operators.txt` only.
"""
from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any, Callable

import numpy as np

from posecorr import coverage
from posecorr.controller import digest

from .aligned import serialize_aligned
from .metadata import UNITS, data_digest, encode_metadata
from .parity import Parity, check_parity
from .symbolic import FLOAT, OPSET, ExportError, Graph, Sym

INPUT_NAME = "pose"
TIME_NAME = "t"
OUTPUT_NAME = "corrected"
BATCH_DIM = "N"
# IR version 8 is the one that introduced opset 17; older readers accept it.
IR_VERSION = 8
OPERATORS_FILE = Path(__file__).resolve().parent / "operators.txt"


class OperatorNotSupported(ExportError):
    """A node whose operator runtime_c does not implement."""

    def __init__(self, op_type: str, node_name: str, domain: str = "") -> None:
        where = f" (domain {domain!r})" if domain else ""
        super().__init__(f"operator '{op_type}'{where} in node '{node_name}' is not in export/operators.txt")
        self.op_type, self.node_name = op_type, node_name


class ParityError(ExportError):
    """The float32 graph disagrees with the float64 estimator beyond tolerance."""


def load_operator_list(path: str | Path | None = None) -> frozenset[str]:
    """The operators (default domain, opset 17) that the exporter may emit and runtime_c
    implements: one name per line of export/operators.txt, '#' starts a comment."""
    text = Path(path or OPERATORS_FILE).read_text(encoding="utf-8")
    names = {line.split("#", 1)[0].strip() for line in text.splitlines()}
    return frozenset(n for n in names if n)


def check_operators(model: Any, allowed: frozenset[str] | None = None) -> None:
    """Raise OperatorNotSupported for the first node (graph order) whose operator is not
    allowed; nodes of any non-default domain are refused too."""
    allowed = load_operator_list() if allowed is None else allowed
    for node in model.graph.node:
        if node.domain not in ("", "ai.onnx") or node.op_type not in allowed:
            raise OperatorNotSupported(node.op_type, node.name, node.domain)


def _tensor_proto(name: str, value: np.ndarray) -> Any:
    from onnx import numpy_helper

    return numpy_helper.from_array(value, name)


def _traced_output(g: Graph, forward: Callable[..., Any], time_input: bool) -> Sym:
    """Trace `forward` on the graph's inputs; its result must be a pose-dependent float [N, 7]."""
    pose = g.input(INPUT_NAME, (-1, 7))
    out = g.lift(forward(pose, g.input(TIME_NAME, (-1,))) if time_input else forward(pose))
    if out.is_const:
        raise ExportError("forward() returned a constant: the output does not depend on the pose")
    if out.elem != FLOAT or out.ndim != 2 or out.shape[1] != 7 or out.shape[0] not in (-1, 1):
        raise ExportError(f"forward() must return a float [N, 7] tensor, got shape {out.shape}")
    if out.shape[0] == 1:
        raise ExportError("forward() lost the batch dimension (output shape [1, 7])")
    return out


def _rename_output(g: Graph, final: str) -> None:
    """Give the output tensor the contract's name, in its producer and its consumers."""
    for node in g.nodes:
        node.inputs = [OUTPUT_NAME if n == final else n for n in node.inputs]
        node.outputs = [OUTPUT_NAME if n == final else n for n in node.outputs]


def _needed_names(g: Graph) -> set[str]:
    """The tensor names the output depends on (forward may compute things it does not use)."""
    producer = {o: node for node in g.nodes for o in node.outputs}
    needed: set[str] = set()
    stack = [OUTPUT_NAME]
    while stack:
        name = stack.pop()
        if name in needed:
            continue
        needed.add(name)
        node = producer.get(name)
        if node is not None:
            stack.extend(i for i in node.inputs if i)
    return needed


def _pruned(g: Graph, time_input: bool) -> tuple[list[Any], list[Any]]:
    """The nodes and initializer protos the output needs; refused if it ignores an input."""
    needed = _needed_names(g)
    nodes = [n for n in g.nodes if n.outputs[0] in needed]
    initializers = [_tensor_proto(k, v) for k, v in g.initializers.items() if k in needed]
    if INPUT_NAME not in needed:
        raise ExportError("the output does not depend on the input pose")
    if time_input and TIME_NAME not in needed:
        raise ExportError("the model takes a time input but its output does not depend on it")
    return nodes, initializers


def _graph_proto(nodes: list[Any], initializers: list[Any], graph_name: str, time_input: bool) -> Any:
    """The onnx.GraphProto of the contract's inputs and output, with their doc strings."""
    from onnx import TensorProto, helper

    node_protos = [helper.make_node(n.op_type, n.inputs, n.outputs, name=n.name, **n.attrs) for n in nodes]
    dims = [BATCH_DIM, 7]
    inputs = [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, dims)]
    if time_input:
        inputs.append(helper.make_tensor_value_info(TIME_NAME, TensorProto.FLOAT, [BATCH_DIM]))
    graph = helper.make_graph(
        node_protos, graph_name, inputs,
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, dims)],
        initializer=initializers)
    graph.input[0].doc_string = "measured pose: x, y, z (m), qw, qx, qy, qz"
    if time_input:
        graph.input[1].doc_string = "time of each pose, s since the session's start"
    graph.output[0].doc_string = "corrected pose: x, y, z (m), qw, qx, qy, qz with qw >= 0"
    return graph


def build_model(forward: Callable[..., Any], *, graph_name: str = "posecorr",
                doc: str = "", check: bool = True, time_input: bool = False) -> Any:
    """Trace `forward(pose) -> corrected` into an onnx.ModelProto (no metadata yet).

    time_input: the graph also takes `t` float32 [N] (seconds since the session's start),
    traced as `forward(pose, t)`: the contract's optional second input, for models with a
    time-dependent effect.

    Unused nodes and initializers are dropped; the operator list, onnx.checker (full
    check) and strict shape inference are applied when `check` is true.
    """
    from onnx import helper

    from posecorr import __version__

    g = Graph()
    out = _traced_output(g, forward, time_input)
    if out.name == INPUT_NAME:
        # Renaming the output to the contract's name must not rename the input pose. Emitted
        # here, not in a helper: a node's name records the function that emits it.
        out = g.emit("Identity", [out], out.shape)
    _rename_output(g, out.name)
    nodes, initializers = _pruned(g, time_input)
    model = helper.make_model(_graph_proto(nodes, initializers, graph_name, time_input),
                              opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="posecorr", doc_string=doc)
    model.ir_version = IR_VERSION
    model.producer_version = __version__
    if check:
        check_model(model)
    return model


def check_model(model: Any) -> None:
    """Operator list, onnx.checker (full) and strict shape inference; the inferred output
    must be float [N, 7]."""
    import onnx

    check_operators(model)
    onnx.checker.check_model(model, full_check=True)
    inferred = onnx.shape_inference.infer_shapes(model, check_type=True, strict_mode=True, data_prop=True)
    out_type = inferred.graph.output[0].type.tensor_type
    if out_type.elem_type != onnx.TensorProto.FLOAT:
        raise ExportError("the output is not float32")


# How far outside the training data a model still corrects (the runtimes refuse a pose or
# time beyond with PC_ERR_RANGE): half the training extent per axis, and at least 0.1 m for
# a position, 60 s for a time (a session's clock and the tracker's stamps may disagree by
# seconds). Times are seconds since the session's start, so the span reaches back no further
# than 60 s before it: earlier is no time of the session, and there a time model
# extrapolates without limit (drift's 1 - exp(-t / tau) overflows float32 hours before the
# start when tau is a minute).
BOUNDS_MARGIN_FRACTION = 0.5
BOUNDS_MARGIN_MIN = 0.1
TIME_MARGIN_MIN = 60.0


def widened_box(values: np.ndarray, margin_min: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) per column of `values` (N, k): their box widened by BOUNDS_MARGIN_FRACTION of
    its extent, at least `margin_min`."""
    lo, hi = values.min(axis=0), values.max(axis=0)
    margin = np.maximum(BOUNDS_MARGIN_FRACTION * (hi - lo), margin_min)
    return lo - margin, hi + margin


def input_bounds(measured: np.ndarray) -> list[list[float]]:
    """[[x_lo, y_lo, z_lo], [x_hi, y_hi, z_hi]] (m): the training positions' box, widened."""
    lo, hi = widened_box(np.asarray(measured, float)[:, :3], BOUNDS_MARGIN_MIN)
    return [lo.tolist(), hi.tolist()]


def time_bounds(t: np.ndarray) -> list[float]:
    """[t_lo, t_hi] (s): the span of the training times, widened, from no earlier than
    TIME_MARGIN_MIN before the session's start (t = 0) or the first time."""
    t = np.asarray(t, float).reshape(-1, 1)
    lo, hi = widened_box(t, TIME_MARGIN_MIN)
    start = min(float(t.min()), 0.0) - TIME_MARGIN_MIN
    return [max(float(lo[0]), start), float(hi[0])]


# How far a model's corrections may reach (the runtimes refuse a pose corrected farther, with
# PC_ERR_RUNTIME; docs/design.md, "The ONNX contract"): twice the largest correction the
# graph makes on the training poses and on REACH_POSES poses drawn over everything the
# runtimes accept (positions uniform in input_bounds, times in time_bounds, orientations
# uniform over all rotations), plus 0.01 m and 0.01 rad. The drawn poses are there because
# the input checks accept any orientation inside the box, and a model answers one it never
# saw with a larger correction than any in its training data. Twice, as a margin for what
# the draw missed; the floors keep a model that corrects almost nothing usable, and keep
# cos^2 of half the angle (compared in float32) clear of rounding.
REACH_FACTOR = 2.0
REACH_MIN_POS = 0.01
REACH_MIN_ROT = 0.01
REACH_POSES = 10_000
REACH_SEED = 0


def largest_correction(measured: np.ndarray, corrected: np.ndarray) -> list[float]:
    """[metres, radians]: the largest correction of position and of rotation from `measured`
    to `corrected` ((N, 7) poses)."""
    from .parity import quat_angle

    m, c = np.asarray(measured, float), np.asarray(corrected, float)
    return [float(np.max(np.linalg.norm(c[:, :3] - m[:, :3], axis=1))), float(np.max(quat_angle(m[:, 3:7], c[:, 3:7])))]


def with_margin(largest: list[float]) -> list[float]:
    """The correction_reach of a largest correction [metres, radians] (the graph's own float32
    answers): widened by the margin above, the rotation at most pi, where every rotation is
    allowed."""
    pos, rot = largest
    return [REACH_FACTOR * pos + REACH_MIN_POS, min(np.pi, REACH_FACTOR * rot + REACH_MIN_ROT)]


def accepted_poses(box: Any, n: int = REACH_POSES, seed: int = REACH_SEED) -> np.ndarray:
    """(n, 7) poses the runtimes accept: positions uniform in `box` ([[lo], [hi]]),
    orientations uniform over all rotations."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(box, float)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([lo + (hi - lo) * rng.random((n, 3)), q], axis=1)


def model_reach(model: Any, measured: np.ndarray, box: Any, t: Any = None, span: Any = None
                ) -> tuple[list[float], dict[str, list[float]]]:
    """correction_reach of `model` (ModelProto, bytes or path) on the training poses
    `measured` (times `t`) and on accepted_poses in `box` (times uniform in `span`), and
    {"training", "accepted"}: the largest correction on the training poses and on all those
    poses, without the reach's margin (how far beyond its training poses the model goes)."""
    from .parity import run_onnx

    drawn = accepted_poses(box)
    poses = np.concatenate([np.asarray(measured, float), drawn])
    times = None
    if t is not None:
        rng = np.random.default_rng(REACH_SEED + 1)
        times = np.concatenate([np.asarray(t, float), rng.uniform(span[0], span[1], len(drawn))])
    corrected = run_onnx(model, poses, times)
    n_training = len(poses) - len(drawn)
    _refuse_non_finite(poses, times, corrected, n_training)
    accepted = largest_correction(poses, corrected)
    return with_margin(accepted), {"training": largest_correction(poses[:n_training], corrected[:n_training]),
                                   "accepted": accepted}


def _refuse_non_finite(poses: np.ndarray, times: np.ndarray | None, corrected: np.ndarray,
                       n_training: int) -> None:
    """A model that answers a pose the runtimes accept with a non-finite pose has no reach:
    refused, naming the first such pose."""
    bad = np.flatnonzero(~np.isfinite(corrected).all(axis=1))
    if not bad.size:
        return
    i = int(bad[0])
    which = (f"training pose {i}" if i < n_training
             else f"pose {i - n_training} drawn inside input_bounds{'' if times is None else ' and time_bounds'}")
    at = "" if times is None else f" at t = {times[i]:.6g} s"
    raise ExportError(f"the model's correction of {which} ({', '.join(f'{v:.6g}' for v in poses[i])}){at} "
                      f"is not finite ({bad.size} of {len(poses)} poses): it cannot be given a correction_reach")


def _reach_metadata(info: dict[str, Any], model: Any, measured: Any, t: Any, time_input: bool
                    ) -> dict[str, list[float]] | None:
    """Every export carries how far its corrections reach (model_reach), or the reach it was
    given; returns model_reach's largest corrections (None for a given reach)."""
    if "correction_reach" in info:
        return None
    if measured is None:
        raise ExportError("the model's correction_reach needs the training poses: pass measured=... "
                          "(or correction_reach=[metres, radians])")
    if time_input and t is None:
        raise ExportError("the model's correction_reach needs the training times: pass t=...")
    info["correction_reach"], largest = model_reach(model, measured, info["input_bounds"],
                                                    t if time_input else None, info.get("time_bounds"))
    return largest


def _bounds_metadata(info: dict[str, Any], measured: Any, t: Any, time_input: bool) -> None:
    """Every export carries the box its poses are checked against (input_bounds) and, with
    a time input, the span of its times (time_bounds): from the training data, or given."""
    if "input_bounds" not in info:
        if measured is None:
            raise ExportError("the model's input_bounds need the training positions: pass "
                              "measured=... (or input_bounds=[[x_lo, y_lo, z_lo], [x_hi, y_hi, z_hi]])")
        info["input_bounds"] = input_bounds(measured)
    if time_input and "time_bounds" not in info:
        if t is None:
            raise ExportError("the model's time_bounds need the training times: pass t=... "
                              "(or time_bounds=[t_lo, t_hi])")
        info["time_bounds"] = time_bounds(t)


def _check_bounds(meta: dict[str, str], time_input: bool) -> None:
    """The bounds and the reach as the runtimes will read them: finite float32 numbers, not
    inverted, not negative."""
    from posecorr.controller.checks import Limits, PoseCorrError

    try:
        Limits.from_metadata(meta, time_input)
    except PoseCorrError as exc:
        raise ExportError(f"{exc} (from the training data or given)") from None


def op_counts(model: Any) -> dict[str, int]:
    return dict(sorted(Counter(n.op_type for n in model.graph.node).items()))


def _training_arrays(estimator: Any, measured: Any, reference: Any) -> tuple[Any, Any]:
    """The training data for parity and the digest: explicit arguments first, then the
    attributes a fitted estimator may keep."""
    if measured is None:
        for attr in ("training_measured_", "measured_", "X_train_"):
            measured = getattr(estimator, attr, None)
            if measured is not None:
                break
    if reference is None:
        for attr in ("training_reference_", "reference_", "y_train_"):
            reference = getattr(estimator, attr, None)
            if reference is not None:
                break
    if measured is not None and reference is not None and len(measured) != len(reference):
        # the digest and the parity check are of the pairs: poses that are not pairs are neither
        raise ValueError(f"reference has {len(reference)} rows, expected {len(measured)} like measured")
    return measured, reference


def _initial_info(estimator: Any, metadata: dict[str, Any]) -> dict[str, Any]:
    """The estimator's own export_info() and representation, overridden by `metadata`."""
    info: dict[str, Any] = dict(estimator.export_info()) if hasattr(estimator, "export_info") else {}
    info.setdefault("representation", getattr(estimator, "representation", None))
    info.update(metadata)
    return info


def _parity_report(estimator: Any, model: Any, measured: Any, t: Any, time_input: bool, parity: Parity,
                   **check: Any) -> dict[str, Any]:
    """Run the parity check (`check`: n_random, seed, tol_pos, tol_rot); raise ParityError
    on a failure when `parity` says so."""
    if measured is None:
        raise ExportError("parity check needs the training data: pass measured=... "
                          "(or parity='skip')")
    if time_input and t is None:
        raise ExportError("parity check of a model with a time input needs the training times: pass t=...")
    report = check_parity(estimator, model, np.asarray(measured, float), **check,
                          t=None if not time_input else np.asarray(t, float))
    if "broken_clause" in report and parity is Parity.RAISE:
        raise ParityError(f"the exported graph breaks the output contract: {report['broken_clause']}")
    if not report["passed"] and parity is Parity.RAISE:
        train = report["train"]
        within = (train["max_pos_m"] <= report["tol_pos_m"] and train["max_rot_rad"] <= report["tol_rot_rad"]
                  and "random" in report)
        where = (f" on poses around the training ones ({report['random_poses']}; the training poses agree to "
                 f"{train['max_pos_m']:.2g} m / {train['max_rot_rad']:.2g} rad)" if within else "")
        raise ParityError(
            f"exported graph differs from predict(): max position error "
            f"{report['max_pos_m']:.3g} m (tol {report['tol_pos_m']:.3g}), max rotation error "
            f"{report['max_rot_rad']:.3g} rad (tol {report['tol_rot_rad']:.3g}){where}")
    return report


def _heldout_metrics(model: Any, heldout: tuple, time_input: bool) -> dict[str, Any]:
    """The graph's own metrics (onnxruntime, float32) on poses the model never saw."""
    from posecorr.metrics import metric_block, pose_metrics

    from .parity import run_onnx

    h_measured, h_reference, h_t, with_rotation = heldout
    corrected = np.asarray(run_onnx(model, h_measured, h_t if time_input else None), float)
    raw = pose_metrics(h_reference, h_measured, with_rotation)
    return {"test": metric_block(raw, pose_metrics(h_reference, corrected, with_rotation)),
            "raw": raw, "n_test": int(len(h_measured)),
            "computed_by": "the exported graph (onnxruntime, float32) on held-out poses"}


def _set_metadata(model: Any, info: dict[str, Any], measured: Any, reference: Any, t: Any,
                  time_input: bool) -> dict[str, list[float]] | None:
    """Complete `info` (digest, bounds, reach, defaults) and store it as the model's
    metadata_props, the digest still a placeholder; returns model_reach's largest corrections
    where the reach was measured here."""
    from posecorr import __version__

    if measured is not None and "training_data_digest" not in info:
        info["training_data_digest"] = data_digest(measured, reference, t if time_input else None)
        info.setdefault("training_set_digest", digest.set_digest(measured, reference, t if time_input else None))
    _bounds_metadata(info, measured, t, time_input)
    if measured is not None and coverage.reads_orientation(info.get("representation")):
        info.setdefault(coverage.KEY, coverage.cone(np.asarray(measured, float)[:, 3:7]))
    largest = _reach_metadata(info, model, measured, t, time_input)
    info.setdefault("posecorr_version", __version__)
    info.setdefault("units", UNITS)
    info["opset"] = OPSET
    info.setdefault("effects", [])
    for key in ("method", "architecture", "activation", "trainer", "test_metrics"):
        info.setdefault(key, None)
    info[digest.KEY] = digest.PLACEHOLDER  # filled in once the bytes are known
    meta = encode_metadata(info)
    _check_bounds(meta, time_input)
    del model.metadata_props[:]
    for key, value in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    return largest


def _write_model(model: Any, path: Path, write: Callable[[Path, bytes], None] | None) -> bytes:
    """Sign the model's bytes and write them to `path`; returns the bytes written."""
    if path.parent and not path.parent.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
    data = digest.sign(serialize_aligned(model))  # weights readable in place (PC_LOAD_IN_PLACE)
    if write is None:
        from posecorr.safeio import write_bytes as write
    write(path, data)  # atomic: a controller polling the file never reads half a model
    return data


def to_onnx(estimator: Any, path: str | Path, *, measured: np.ndarray | None = None,
            reference: np.ndarray | None = None, t: np.ndarray | None = None, parity: Parity | str = Parity.RAISE,
            n_random: int = 10_000, heldout: tuple | None = None,
            seed: int = 0, tol_pos: float = 1e-5, tol_rot: float = 1e-5,
            write: Callable[[Path, bytes], None] | None = None, **metadata: Any) -> dict[str, Any]:
    """Export a fitted corrector to `path` and return what was written.

    estimator: has `forward(pose)` (xp-generic, (N, 7) -> (N, 7)), `predict(measured)`,
      `representation` and optionally `export_info()` (metadata dict).
    measured, reference: the training arrays (N, 7) (m, unit quaternions); used for the
      parity check and the training-data digest. Default: the estimator's own copies.
    t: the training poses' times (s) for a model with a time input (`estimator.needs_time`).
    heldout: (measured, reference, t or None, with_rotation) of poses the model never saw: the
      graph itself (onnxruntime, float32) is run on them and its metrics become the file's
      `test_metrics` ({"test": ..., "raw": ...}) and the return value's "heldout_metrics", so
      what fit prints about the file is what the file does.
    parity: `Parity` (or its value): "raise" (refuse to save a model beyond tol_pos m / tol_rot
      rad), "warn" (record the failure in the metadata) or "skip" (no training data needed).
    write: writes the file's bytes (default: `safeio.write_bytes`, atomic; a command writing
      several files together passes `safeio.Staged.write_bytes`).
    metadata: extra `metadata_props` (test_metrics=..., effects=..., ...); they override
      the estimator's `export_info()`. `input_bounds` (and `time_bounds` for a model with a
      time input) come from the training data unless given here; without either the
      export is refused (ExportError): no model leaves without the box it was fitted in.

    Returns {"path", "metadata", "op_counts", "n_nodes", "file_size", "parity", "heldout_metrics",
    "largest_correction" (model_reach's {"training", "accepted"}, [m, rad]; None for a given reach)}.
    """
    try:
        parity = Parity(parity)
    except ValueError:
        raise ValueError(f"parity must be {', '.join(repr(p.value) for p in Parity)}, got {parity!r}") from None
    info = _initial_info(estimator, metadata)
    time_input = bool(getattr(estimator, "needs_time", False))
    on = f" ({info['representation']})" if info.get("representation") else ""
    model = build_model(estimator.forward, doc=f"posecorr {info.get('method', 'corrector')}{on}", time_input=time_input)
    if time_input:
        info["time_input"] = f"{TIME_NAME}: float32 [N], s since the session's start"

    measured, reference = _training_arrays(estimator, measured, reference)
    if time_input and t is None:
        t = getattr(estimator, "training_t_", None)
    parity_report: dict[str, Any] | None = None
    if parity is not Parity.SKIP:
        parity_report = _parity_report(estimator, model, measured, t, time_input, parity,
                                       n_random=n_random, seed=seed, tol_pos=tol_pos, tol_rot=tol_rot)
        info["parity"] = parity_report
    heldout_metrics = None
    if heldout is not None:
        heldout_metrics = _heldout_metrics(model, heldout, time_input)
        # the graph's own figures replace the caller's test and raw; the rest (fit's rigid floor) stays
        info["test_metrics"] = {**(info.get("test_metrics") or {}), **heldout_metrics}
    largest = _set_metadata(model, info, measured, reference, t, time_input)

    path = Path(path)
    data = _write_model(model, path, write)
    counts = op_counts(model)
    return {"path": str(path), "metadata": info, "op_counts": counts, "n_nodes": sum(counts.values()),
            "file_size": len(data), "parity": parity_report, "heldout_metrics": heldout_metrics,
            "largest_correction": largest}
