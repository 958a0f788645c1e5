"""The checks every back end makes on a model and on the poses it corrects, in one place.

libposecorr (runtime_c) makes them in C: at load in api.c and onnx.c, at run time in
run.c's pc_check_input and pc_check_output. This module makes the same checks, in the same
order and with the same messages and status codes, for the Python back ends that do not go
through the C runtime (`Corrector(backend="onnxruntime")`, hence `posecorr apply --backend
onnxruntime`). tests/test_checks.py runs every hostile case on both back ends and compares
their messages word for word.

At load (`check_model`), in libposecorr's order: a supported default-domain opset; the
graph's inputs and outputs are the pose contract's (`pose` float32 [N,7], optionally `t`
float32 [N]; `corrected` float32 [N,7]: `check_contract`); its operators are those of
export/operators.txt in the default domain; every weight tensor has a shape, element type
and size libposecorr takes (`check_tensor`); every value is produced once and before it is
read (`check_references`); no float tensor of the graph (an initialiser, a Constant's value)
holds NaN or infinity; the metadata's bounds (`input_bounds`, metres, and `time_bounds`,
seconds) are finite float32 numbers, lower ones not above upper ones.

Before those, the file's digest (metadata `model_digest`, `digest`): a file whose bytes do
not give it is refused (INTEGRITY), one without it unless the caller allows unsigned files;
a model without `input_bounds` or `correction_reach` is refused unless the caller allows
unbounded ones (CONTRACT).

Per call (`check_input`, `check_output`), the same for every model whoever wrote it:
finite times inside `time_bounds` (models that take time; no t is t = 0), finite poses,
unit quaternions, positions inside `input_bounds`, and out, finite poses with unit
quaternions and a correction within `correction_reach`. A pose's refusal reads "pose I:
CLAUSE" (posecorr.h's pc_run), I its index in the call and CLAUSE naming a column by the
contract's names (`COLUMNS`, t the time).

A caller's value wider than float32 (float64) may be finite and beyond float32's range: cast
for the model it is infinite, and refused as not finite. `check_wide_input` names it as the
caller gave it: outside the model's bounds in run.c's words, or, for a model without bounds,
as not fitting in float32.
"""
from __future__ import annotations

import importlib.util
import json
import math
import re
from contextlib import contextmanager
from dataclasses import dataclass, replace
from enum import IntEnum
from functools import lru_cache, partial
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from . import digest, onnx_meta

__all__ = ["PoseCorrError", "Status", "Limits", "check_model", "check_input", "check_output",
           "check_wide_input", "failure", "decimal"]


class PoseCorrError(ValueError):
    """A model failed to load or a pose could not be corrected; `status` is the C code."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status

    def __reduce__(self):
        return type(self), (str(self), self.status)  # crosses a process pool intact


class Status(IntEnum):
    """libposecorr's pc_status (runtime_c/posecorr.h), value for value."""

    OK = 0
    ARGUMENT = 1
    IO = 2
    MEMORY = 3
    TRUNCATED = 4
    MALFORMED = 5
    UNSUPPORTED = 6
    CONTRACT = 7
    GRAPH = 8
    SHAPE = 9
    NONFINITE = 10
    RUNTIME = 11
    RANGE = 12
    QUATERNION = 13
    INTEGRITY = 14


# pc_status_name (runtime_c/status.c) of the codes raised here.
STATUS_NAMES = {
    Status.MALFORMED: "malformed model",
    Status.UNSUPPORTED: "unsupported feature",
    Status.NONFINITE: "non-finite input",
    Status.RUNTIME: "runtime error",
    Status.RANGE: "pose outside the fitted range",
    Status.QUATERNION: "quaternion not unit",
    Status.INTEGRITY: "model file changed or unsigned",
}

# Default-domain opsets libposecorr loads (PC_OPSET_MIN, PC_OPSET_MAX in posecorr.h).
OPSETS = (13, 28)
# run.c's tolerances: an output |q|^2 within 2.002e-3 of 1, the input's rule with float slack
# (after a few dozen float32 operations it is within 1e-5; a position-only model passes the
# input's quaternion through); an input norm within 1e-3 of 1, the pose tables' rule
# (posecorr.data.QUAT_NORM_TOLERANCE), compared on |q|^2 in float64 as (1 -+ 1e-3)^2. The
# model normalises its input, so a few lost bits change nothing, while a zero or norm-3
# vector is a glitch that normalising would turn into a made-up rotation.
OUTPUT_UNIT_TOLERANCE = np.float32(2.002e-3)
INPUT_NORM2_RANGE = (0.998001, 1.002001)
FLOAT32_MAX = float(np.finfo(np.float32).max)
FLOAT64_MAX = float(np.finfo(np.float64).max)
# What a time model without time_bounds takes of a caller's wider t (check_wide_input).
_FLOAT32_SPAN = (np.float32(-FLOAT32_MAX), np.float32(FLOAT32_MAX))
BOX_EXPECTED = "[[x_lo, y_lo, z_lo], [x_hi, y_hi, z_hi]] in metres"
SPAN_EXPECTED = "[t_lo, t_hi] in seconds"
REACH_KEY = "correction_reach"
# How a load refusal names the caller's way out (posecorr.h's PC_LOAD_ALLOW_* flags).
ALLOW_UNBOUNDED = "load with PC_LOAD_ALLOW_UNBOUNDED, on the command line --allow-unbounded"
ALLOW_UNSIGNED = "load with PC_LOAD_ALLOW_UNSIGNED, on the command line --allow-unsigned"
# The contract's optional second input: float32 [N], s since the session's start.
TIME_INPUT = "t"
# The columns of a pose in and out (posecorr.h; run.c's pc_column_names), as the messages name them.
COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")
QUATERNION = "the quaternion qw, qx, qy, qz"


def failure(status: Status, message: str) -> PoseCorrError:
    """The error a run-time check raises: its status name first, as the C back end's."""
    return PoseCorrError(f"{STATUS_NAMES[status]}: {message}", int(status))


def decimal(value: float, places: int = 3) -> str:
    """`value` with `places` decimals (mm, ms), from 1e9 on as a mantissa and a power of ten
    (3.000e30), inf and nan as such, as run.c's pc_decimal writes it: the same steps in the
    same doubles."""
    a = abs(float(value))
    power = ""
    if not a <= FLOAT64_MAX:   # a reach or distance may be infinite, or nan
        return "nan" if a != a else "-inf" if value < 0 else "inf"
    if a >= 1e9:
        decade, exponent = 1e9, 9
        while a >= decade * 10.0:
            decade *= 10.0
            exponent += 1
        a /= decade
    scale = 10.0 ** places
    units = int(a * scale + 0.5)
    if abs(float(value)) >= 1e9:
        if units >= 10 * int(scale):  # 9.9996e12 rounds to 1.000e13
            units //= 10
            exponent += 1
        power = f"e{exponent}"
    return f"{'-' if value < 0 and units else ''}{units // int(scale)}.{units % int(scale):0{places}d}{power}"


def _outside(pose: int, name: str, value: float, lo: float, hi: float) -> str:
    """run.c's pc_outside: a position (metres, input_bounds) or the time t (seconds, time_bounds).
    A bound at float32's limit is no model's (`check_wide_input`): beyond it is beyond float32."""
    unit, span, key = ("s", "span", "time_bounds") if name == TIME_INPUT else ("m", "range", "input_bounds")
    if abs(float(lo if value < lo else hi)) == FLOAT32_MAX:
        return (f"pose {pose}: {name} = {float(value):.7g} {unit} does not fit in float32, the numbers the model "
                f"computes in (their largest is {FLOAT32_MAX:.7g})")
    return (f"pose {pose}: {name} = {decimal(value)} {unit} is outside the {span} the model was fitted on, "
            f"{decimal(lo)} to {decimal(hi)} {unit} (metadata {key})")


def _refuse_constant(name: str) -> Any:
    raise ValueError(name)


# How deep api.c's pc_parse_numbers reads nested arrays (PC_JSON_DEPTH).
JSON_DEPTH = 32


def _numbers(value: Any, depth: int = 0) -> list[float] | None:
    """The numbers of a JSON array nested at most JSON_DEPTH deep (api.c's
    pc_parse_numbers), None when it holds anything else."""
    if isinstance(value, float):   # integers too: read with parse_int=float, 400 digits are inf as in C
        return [value]
    if isinstance(value, list) and depth < JSON_DEPTH:
        out: list[float] = []
        for v in value:
            got = _numbers(v, depth + 1)
            if got is None:
                return None
            out += got
        return out
    return None


def _quoted(text: str) -> str:
    """A metadata value as api.c quotes it ('%.*s' of at most 60 bytes): its first 60 bytes
    of UTF-8, up to a NUL, read back as the shim reads the C message."""
    return text.encode("utf-8", "surrogatepass")[:60].split(b"\0", 1)[0].decode(errors="replace")


def _read_bounds(key: str, value: str, count: int, expected: str) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) float32 of a bounds value, refused as api.c's pc_read_bounds refuses it."""
    text = value  # read whole, of any length, as the C parser reads it
    try:  # NaN and Infinity are not numbers, as in the C parser
        v = _numbers(json.loads(text, parse_constant=_refuse_constant, parse_int=float))
    except (ValueError, RecursionError):
        v = None
    if v is None or len(v) != 2 * count:
        raise PoseCorrError(f"metadata {key} is '{_quoted(text)}', expected {expected}", int(Status.MALFORMED))
    for k in range(count):
        if not (abs(v[k]) <= FLOAT32_MAX and abs(v[k + count]) <= FLOAT32_MAX):
            raise PoseCorrError(f"metadata {key}: a bound is not a finite float32 in column {k} "
                                f"(expected {expected})", int(Status.MALFORMED))
    lo, hi = np.float32(v[:count]), np.float32(v[count:])
    for k in range(count):
        if not lo[k] <= hi[k]:
            raise PoseCorrError(f"metadata {key}: lower bound above upper bound in column {k}",
                                int(Status.MALFORMED))
    return lo, hi


def _read_reach(value: str) -> tuple[np.float32, np.float32]:
    """(reach_pos2, reach_cos2) of correction_reach "[metres, radians]" as api.c's
    pc_read_reach keeps them: the squared distance and cos^2 of half the angle (float32)."""
    text = value  # read whole, of any length, as the C parser reads it
    try:
        v = _numbers(json.loads(text, parse_constant=_refuse_constant, parse_int=float))
    except (ValueError, RecursionError):
        v = None
    if v is None or len(v) != 2 or not all(0.0 <= x <= FLOAT32_MAX for x in v):
        raise PoseCorrError(f"metadata {REACH_KEY} is '{_quoted(text)}', expected [metres, radians]: "
                            "two finite numbers, not negative", int(Status.MALFORMED))
    pos, rot = np.float32(v[0]), np.float32(v[1])
    cos2 = 0.0 if v[1] >= math.pi else math.cos(0.5 * float(rot)) * math.cos(0.5 * float(rot))
    return pos * pos, np.float32(cos2)


_UNBOUNDED_BOX = (np.full(3, -np.inf, np.float32), np.full(3, np.inf, np.float32))


@dataclass(frozen=True)
class Limits:
    """What a model's metadata asks of the poses it corrects (api.c's pc_read_checks)."""

    box: tuple[np.ndarray, np.ndarray] = _UNBOUNDED_BOX   # float32 (3,) lo, hi: input_bounds
    span: tuple[np.float32, np.float32] | None = None    # time_bounds, models that take time
    reach_pos2: np.float32 = np.float32(np.inf)          # correction_reach, as run.c compares it
    reach_cos2: np.float32 = np.float32(0.0)

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, str], takes_time: bool,
                      allow_unbounded: bool = False, repeated: Sequence[str] = ()) -> "Limits":
        """Raises PoseCorrError: status MALFORMED for bounds that are not finite float32
        numbers or are inverted, or given twice (`repeated`: the file's keys given again),
        CONTRACT for a model without input_bounds or correction_reach unless
        `allow_unbounded`."""
        for key in repeated:
            if key in ("input_bounds", "time_bounds", REACH_KEY):
                raise PoseCorrError(f"metadata {key} appears twice", int(Status.MALFORMED))
        for key, what in (("input_bounds", "which positions it was fitted on"),
                          (REACH_KEY, "how far its corrections reach")):
            if key not in metadata and not allow_unbounded:
                raise PoseCorrError(f"no metadata {key}: the model does not say {what} (to run it "
                                    f"anyway, {ALLOW_UNBOUNDED})", int(Status.CONTRACT))
        box, span = _UNBOUNDED_BOX, None
        if "input_bounds" in metadata:
            box = _read_bounds("input_bounds", metadata["input_bounds"], 3, BOX_EXPECTED)
        if "time_bounds" in metadata:
            lo, hi = _read_bounds("time_bounds", metadata["time_bounds"], 1, SPAN_EXPECTED)
            span = (lo[0], hi[0]) if takes_time else None  # a model without t ignores time
        if REACH_KEY in metadata:
            return cls(box, span, *_read_reach(metadata[REACH_KEY]))
        return cls(box, span)


def check_digest(data: bytes, where: str, allow_unsigned: bool = False) -> None:
    """api.c's pc_check_digest: the file's bytes give its model_digest (docs/design.md,
    "Integrity"); a file without one only when `allow_unsigned`."""
    try:
        span = digest.digest_span(data)
    except onnx_meta._Malformed:
        return  # not a model: read_model says where
    except ValueError as exc:
        raise PoseCorrError(f"{where}: {exc}", int(Status.INTEGRITY)) from None
    if span is None:
        if allow_unsigned:
            return
        raise PoseCorrError(f"{where}: no metadata {digest.KEY}: the file carries no digest of its "
                            f"bytes (to run it anyway, {ALLOW_UNSIGNED})", int(Status.INTEGRITY))
    stored = data[span[0]:span[1]]
    if not re.fullmatch(rb"crc32c:[0-9a-f]{8}", stored):
        text = stored[:40].decode("utf-8", errors="replace")
        raise PoseCorrError(f"{where}: metadata {digest.KEY} is '{text}', expected crc32c: and 8 "
                            "lowercase hexadecimal digits", int(Status.INTEGRITY))
    got = digest.file_digest(data, span)
    if got.encode() != stored:
        raise PoseCorrError(f"{where}: the file's bytes give {got} where its metadata {digest.KEY} says "
                            f"{stored.decode()}: the model was changed or damaged after export",
                            int(Status.INTEGRITY))


@lru_cache(maxsize=1)
def operator_list() -> frozenset[str]:
    """export/operators.txt (package data of posecorr.export), read without importing
    posecorr.export (which needs onnx)."""
    spec = importlib.util.find_spec("posecorr.export")
    if spec is None or not spec.submodule_search_locations:
        raise PoseCorrError("posecorr.export/operators.txt not found: reinstall posecorr")
    text = (Path(list(spec.submodule_search_locations)[0]) / "operators.txt").read_text(encoding="utf-8")
    return frozenset(n for n in (line.split("#", 1)[0].strip() for line in text.splitlines()) if n)


def _float_values(tensor: dict[str, Any]) -> np.ndarray:
    if tensor["raw"] is not None:
        return np.frombuffer(tensor["raw"], dtype="<f4", count=len(tensor["raw"]) // 4)
    return np.frombuffer(tensor["float_data"], dtype="<f4")


def check_model(data: bytes, where: str, allow_unbounded: bool = False,
                allow_unsigned: bool = False) -> tuple[dict[str, str], Limits]:
    """The load-time checks of libposecorr on a model's bytes: (metadata as strings, the
    run-time limits). Raises PoseCorrError naming `where` and what was expected."""
    if not data:   # before the digest, as api.c: an empty file is no unsigned model
        raise PoseCorrError(f"{where}: {onnx_meta.EMPTY}", int(Status.TRUNCATED))
    check_digest(data, where, allow_unsigned)
    model = _structure(where, onnx_meta.read_model, data, "not a valid ONNX model ({})")
    opset = model["opset_import"].get("ai.onnx", -1)   # none: libposecorr's -1, refused
    if not OPSETS[0] <= opset <= OPSETS[1]:
        raise PoseCorrError(f"{where}: default-domain opset {opset} is not supported "
                            f"({OPSETS[0]}..{OPSETS[1]})", int(Status.UNSUPPORTED))
    graph = _structure(where, onnx_meta.read_graph, model)
    with _named(where):
        inputs = check_contract(graph)
    allowed = operator_list()

    def check_operator(op: str, domain: str, name: str) -> None:
        if domain not in ("", "ai.onnx"):
            raise PoseCorrError(f"{where}: unsupported operator {op} (domain '{domain}') in node "
                                f"'{name}'", int(Status.UNSUPPORTED))
        if op not in allowed:
            raise PoseCorrError(f"{where}: unsupported operator {op} in node '{name}'",
                                int(Status.UNSUPPORTED))
    graph.update(_structure(where, partial(onnx_meta.read_nodes, each=check_operator), graph))
    with _named(where):
        check_references(graph, inputs)
    # Then libposecorr folds each Constant, reading its value.
    constants = [t for node in graph["constant_nodes"] for t in _structure(where, onnx_meta.constant_tensors, node)]
    with _named(where):
        for tensor in constants:
            check_tensor(tensor)
    for tensor in filter(None, map(onnx_meta.float_tensor, constants + graph["initializer_messages"])):
        bad = np.flatnonzero(~np.isfinite(_float_values(tensor)))
        if bad.size:
            raise PoseCorrError(f"{where}: tensor '{tensor['name']}' holds a non-finite value at "
                                f"element {int(bad[0])} (expected finite weights)", int(Status.MALFORMED))
    takes_time = any(kind == "input" and io["name"] == TIME_INPUT for kind, io in graph["io"])
    with _named(where):
        limits = Limits.from_metadata(model["metadata"], takes_time, allow_unbounded, model["repeated"])
    # Last: libposecorr reads names as bytes and loads such a file; onnxruntime cannot.
    at = onnx_meta.first_not_utf8(model, graph)
    if at is not None:
        raise PoseCorrError(f"{where}: the string at byte {at} is not UTF-8, which onnxruntime cannot load (the C "
                            "back end can)", int(Status.MALFORMED))
    return model["metadata"], limits


@contextmanager
def _named(where: str) -> Iterator[None]:
    """A check's fault with the model's name in front, as every load error reads."""
    try:
        yield
    except PoseCorrError as exc:
        raise PoseCorrError(f"{where}: {exc}", exc.status) from None


def _structure(where: str, read: Any, source: Any, words: str = "{}") -> Any:
    """One stage of `onnx_meta`'s reading, its fault named as libposecorr names it: a top
    level that does not read as a model is "not a valid ONNX model (...)" (`words`), a fault
    inside its graph is named alone."""
    try:
        return read(source)
    except PoseCorrError:   # a check made while reading, already in its words
        raise
    except onnx_meta.TruncatedModel as exc:
        raise PoseCorrError(f"{where}: {exc}", int(Status.TRUNCATED)) from None
    except ValueError as exc:
        raise PoseCorrError(f"{where}: {words.format(exc)}", int(Status.MALFORMED)) from None


def check_contract(graph: dict[str, Any]) -> list[str]:
    """onnx.c's pose contract on a graph's inputs and outputs (`onnx_meta.read_graph`'s
    "io", in the file's order; an input that is an initializer or repeated is skipped, as
    IR < 4 files list initializers among the inputs), in its words and order: the first
    fault raised (CONTRACT); the graph inputs it kept, when the graph keeps the contract."""
    seen = {name for name, _ in graph["initializers"]}
    inputs: list[str] = []
    outputs = 0
    for kind, io in graph["io"]:
        name, elem, shape = io["name"], io["elem"], io["shape"]
        rank = -1 if shape is None else len(shape)
        dims = [d if isinstance(d, int) else -1 for d in shape or ()]
        negative = next((d for d in shape or () if isinstance(d, int) and d < 0), None)
        if negative is not None:   # as -1 it would read as symbolic
            raise PoseCorrError(f"value '{name}' has dimension {negative}, expected a size of 0 or more",
                                int(Status.MALFORMED))
        if kind == "output":
            outputs += 1
            fault = _output_fault(name, elem, rank, dims)
        elif name in seen:
            continue
        else:
            seen.add(name)
            inputs.append(name)
            fault = _input_fault(name, elem, rank, dims)
        if fault:
            raise PoseCorrError(fault, int(Status.CONTRACT))
    if "pose" not in inputs:
        raise PoseCorrError("model has no input 'pose', the contract needs 'pose' float32 [N,7] and optionally 't' "
                            "float32 [N]", int(Status.CONTRACT))
    if outputs != 1:
        raise PoseCorrError(f"model has {outputs} outputs, the contract needs exactly one ('corrected')",
                            int(Status.CONTRACT))
    return inputs


def check_tensor(tensor: bytes) -> None:
    """onnx.c's check of a TensorProto's shape, element type and size before it is held
    (`onnx_meta.tensor_fault`), raised in its words and status."""
    fault = onnx_meta.tensor_fault(tensor)
    if fault is not None:
        raise PoseCorrError(fault[1], int(Status[fault[0]]))


def check_references(graph: dict[str, Any], inputs: list[str]) -> None:
    """graph.c's pc_names_start and pc_scan_refs on a graph (`onnx_meta.read_nodes`'
    "node_io", `inputs` the graph inputs `check_contract` kept), in its words and order:
    every initializer a tensor libposecorr holds (`check_tensor`), every value produced once,
    every node's input produced by a graph input, an initializer or an earlier node (the
    first that is not, reported after the walk, when it is known whether a later node
    produces it), every graph output produced. Raises GRAPH (a tensor's fault: its own
    status)."""
    def fault(message: str) -> PoseCorrError:
        return PoseCorrError(message, int(Status.GRAPH))

    kinds = dict.fromkeys(inputs, "a graph input")
    for (name, _), tensor in zip(graph["initializers"], graph["initializer_messages"]):
        check_tensor(tensor)
        if kinds.get(name) == "an initializer":
            raise fault(f"initializer '{name}' is defined twice")
        kinds.setdefault(name, "an initializer")   # a graph input of that name stays one
    missing = None
    for (_, _, node), (reads, writes) in zip(graph["nodes"], graph["node_io"]):
        missing = missing or next(((x, node) for x in reads if x and x not in kinds), None)
        for y in filter(None, writes):
            if y in kinds:
                raise fault(f"'{y}' (output of node '{node}') is already {kinds[y]}: every value of a graph is "
                            "produced once")
            kinds[y] = "a node output"
    if missing:
        value, node = missing
        if value in kinds:
            raise fault(f"graph has a cycle or is not topologically sorted: node '{node}' reads '{value}' before "
                        "the node that produces it")
        raise fault(f"input '{value}' of node '{node}' is not produced by any node, initializer or graph input")
    for kind, io in graph["io"]:
        if kind == "output" and io["name"] not in kinds:
            raise fault(f"graph output '{io['name']}' is not produced by any node")


def _input_fault(name: str, elem: int, rank: int, dims: list[int]) -> str | None:
    if name == TIME_INPUT:
        if elem != onnx_meta.FLOAT:
            return f"input 't' has element type {elem}, the contract needs float32"
        if rank != 1:
            return f"input 't' must have shape [N] (rank {rank})"
        return f"input 't' has a fixed batch size {dims[0]}; N must be dynamic" if dims[0] >= 0 else None
    if name != "pose":
        return (f"model input is '{name}', the contract needs 'pose' float32 [N,7] and optionally 't' "
                "float32 [N]")
    if elem != onnx_meta.FLOAT:
        return f"input 'pose' has element type {elem}, the contract needs float32"
    if rank != 2 or dims[1] != len(COLUMNS):
        return f"input 'pose' must have shape [N,7] (rank {rank}, width {dims[1] if rank >= 2 else -1})"
    return f"input 'pose' has a fixed batch size {dims[0]}; N must be dynamic" if dims[0] >= 0 else None


def _output_fault(name: str, elem: int, rank: int, dims: list[int]) -> str | None:
    if name != "corrected":
        return f"model output is '{name}', the contract needs 'corrected' float32 [N,7]"
    if elem != onnx_meta.FLOAT:
        return f"output 'corrected' has element type {elem}, the contract needs float32"
    if rank >= 0 and (rank != 2 or dims[1] != len(COLUMNS)):
        return "output 'corrected' must have shape [N,7]"
    return None


def _first(mask: np.ndarray) -> int | None:
    hit = np.flatnonzero(mask)
    return int(hit[0]) if hit.size else None


def check_input(limits: Limits, poses: np.ndarray, t: np.ndarray | None) -> None:
    """run.c's pc_check_input on float32 poses (N, 7) and times (N,) or None (t = 0) (wider
    ones from `check_wide_input`)."""
    if t is not None or limits.span is not None:
        times = t if t is not None else np.zeros(1, np.float32)
        nonfinite = ~np.isfinite(times)
        outside = np.zeros_like(nonfinite)
        if limits.span is not None:
            lo, hi = limits.span
            outside = ~((times >= lo) & (times <= hi))
        i = _first(nonfinite | outside)
        if i is not None:
            if nonfinite[i]:
                raise failure(Status.NONFINITE, f"pose {i}: t is not finite (expected seconds since the "
                                                "session's start)")
            if t is None:
                raise failure(Status.RANGE, f"pose {i}: no t given, so t = 0 s, outside the span the model was "
                                            f"fitted on, {decimal(lo)} to {decimal(hi)} s (metadata time_bounds): "
                                            "the model takes each pose's time")
            raise failure(Status.RANGE, _outside(i, TIME_INPUT, times[i], lo, hi))
    finite = np.isfinite(poses)
    bad = ~finite.all(axis=1)
    lo3, hi3 = limits.box
    with np.errstate(invalid="ignore"):
        inside = (poses[:, :3] >= lo3) & (poses[:, :3] <= hi3)
    bad |= ~inside.all(axis=1)
    q = poses[:, 3:7].astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        norm2 = q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3]
        unit = (norm2 >= INPUT_NORM2_RANGE[0]) & (norm2 <= INPUT_NORM2_RANGE[1])
    i = _first(bad | ~unit)
    if i is None:
        return
    # run.c's pc_pose_error: the quaternion before the box, so that SteamVR's "no pose" (all
    # zeros, its position too) is named a zero quaternion
    c = _first(~finite[i])
    if c is not None:
        raise failure(Status.NONFINITE, f"pose {i}: {COLUMNS[c]} is not finite (expected a finite number)")
    if not unit[i]:
        raise failure(Status.QUATERNION, f"pose {i}: {QUATERNION} has norm {decimal(math.sqrt(norm2[i]), 6)} "
                                         "(expected a unit quaternion: norm within 0.001 of 1)")
    c = _first(~inside[i])
    raise failure(Status.RANGE, _outside(i, COLUMNS[c], poses[i, c], limits.box[0][c], limits.box[1][c]))


def check_wide_input(limits: Limits, poses: np.ndarray, t: np.ndarray | None) -> None:
    """check_input on a caller's poses (N, 7) and times (N,) or None wider than float32, when
    one is finite and beyond float32's range: each value as the model reads it, rounded to
    float32, but that one as given, outside the model's bounds or, where it has none, outside
    float32's range. Returns when there is none: the refusal of the float32 values stands."""
    if not (_beyond_float32(poses).any() or (t is not None and _beyond_float32(t).any())):
        return
    lo, hi = limits.box
    span = limits.span if limits.span is not None or t is None else _FLOAT32_SPAN
    within = replace(limits, box=(np.maximum(lo, -FLOAT32_MAX), np.minimum(hi, FLOAT32_MAX)), span=span)
    check_input(within, _as_read(poses), None if t is None else _as_read(t))


def _beyond_float32(values: np.ndarray) -> np.ndarray:
    return np.isfinite(values) & (np.abs(values) > FLOAT32_MAX)


def _as_read(values: np.ndarray) -> np.ndarray:
    """`values` rounded to float32 as the model reads them, but those beyond float32's range
    as given (the cast would make them infinite)."""
    with np.errstate(over="ignore"):
        read = values.astype(np.float32)
    return np.where(_beyond_float32(values), values, read)


def _sum4(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum of a[:, k] * b[:, k] over k in order, float32 as run.c adds them."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2] + a[:, 3] * b[:, 3]


def check_output(limits: Limits, poses: np.ndarray, out: np.ndarray) -> None:
    """run.c's pc_check_output on the float32 result (N, 7) of a call for `poses`: finite,
    unit quaternion, a correction within correction_reach (compared as run.c compares it,
    in float32 on squares)."""
    finite = np.isfinite(out)
    bad = ~finite.all(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        q, q_in = out[:, 3:7], poses[:, 3:7]
        n2 = _sum4(q, q)
        not_unit = ~(np.abs(n2 - np.float32(1.0)) <= OUTPUT_UNIT_TOLERANCE)
        d = out[:, :3] - poses[:, :3]
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        dot, n_in2 = _sum4(q, q_in), _sum4(q_in, q_in)
        beyond = ~((d2 <= limits.reach_pos2) & (dot * dot >= limits.reach_cos2 * n_in2 * n2))
    i = _first(bad | not_unit | beyond)
    if i is None:
        return
    c = _first(~finite[i])
    if c is not None:
        raise failure(Status.RUNTIME, f"pose {i}: {COLUMNS[c]} of output 'corrected' is not finite "
                                      "(expected a finite number)")
    if not_unit[i]:
        raise failure(Status.RUNTIME, f"pose {i}: {QUATERNION} of output 'corrected' is not unit "
                                      "(expected |q|^2 within 0.002 of 1)")
    cos = min(1.0, abs(float(dot[i])) / math.sqrt(float(n_in2[i]) * float(n2[i])))
    raise failure(Status.RUNTIME, f"pose {i}: output 'corrected' moves the pose by "
                                  f"{decimal(math.sqrt(float(d2[i])))} m and {decimal(2 * math.acos(cos))} rad, "
                                  f"beyond the model's reach of {decimal(math.sqrt(float(limits.reach_pos2)))} m "
                                  f"and {decimal(2 * math.acos(math.sqrt(float(limits.reach_cos2))))} rad "
                                  f"(metadata {REACH_KEY})")
