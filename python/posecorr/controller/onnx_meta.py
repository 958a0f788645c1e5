"""Read an .onnx file's metadata without the onnx package (controller-side `posecorr info`).

A minimal protobuf wire-format reader (stdlib only) for the few ModelProto fields that
`info` shows: metadata_props, opset imports, producer, the graph's inputs / outputs with
their element types and shapes, node operator counts and initializer sizes; and, for the
load-time checks of the Python back ends (`checks.check_model`: `read_model`, `read_graph`,
`read_nodes`, one per stage of libposecorr's load), the graph's inputs and outputs, its
nodes and the bytes of its float tensors. A fault of the file's structure is named in
libposecorr's words ("model field 7 at byte 0 is not bytes", "no graph").

Field numbers follow onnx.proto (ModelProto: ir_version 1, producer_name 2,
producer_version 3, doc_string 6, graph 7, opset_import 8, metadata_props 14; GraphProto:
node 1, name 2, initializer 5, input 11, output 12; NodeProto: op_type 4, domain 7;
ValueInfoProto: name 1, type 2; TypeProto.tensor_type 1: elem_type 1, shape 2;
TensorShapeProto.dim 1: dim_value 1, dim_param 2; TensorProto: dims 1, data_type 2,
float_data 4, name 8, raw_data 9; NodeProto: name 3, attribute 5; AttributeProto: name 1,
t 5).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from collections import Counter
from typing import Any, Callable, Iterator

ELEM_TYPES = {1: "float32", 2: "uint8", 3: "int8", 4: "uint16", 5: "int16", 6: "int32", 7: "int64",
              8: "string", 9: "bool", 10: "float16", 11: "float64", 12: "uint32", 13: "uint64",
              16: "bfloat16"}


class _Malformed(Exception):
    pass


class _Truncated(_Malformed):
    """Bytes that end inside a field: libposecorr's status TRUNCATED, in its words."""


class TruncatedModel(ValueError):
    """A model file cut short, named as libposecorr names it: "truncated file at byte N (...)"."""


# libposecorr's words for a file of no bytes (api.c), where every reader says them.
EMPTY = "truncated file at byte 0 (empty)"


class _Slice(bytes):
    """A length-delimited field's bytes, with where they start in the file (`base`): an
    error names a byte by its offset in the file, as libposecorr does."""

    base = 0


# libposecorr's protobuf reader (pb.c) and this one name a fault in the same words.
def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    base = getattr(buf, "base", 0)
    start, result, shift = pos, 0, 0
    while pos < len(buf):
        b = buf[pos]
        pos += 1
        if shift == 63 and b & 0x7E:
            raise _Malformed(f"varint overflows 64 bits at byte {base + start}")
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7
        if shift > 63:
            raise _Malformed(f"varint longer than 10 bytes at byte {base + start}")
    raise _Truncated(f"truncated file at byte {base + pos} (inside a varint)")


def _fields(buf: bytes) -> Iterator[tuple[int, int, Any]]:
    """(field number, wire type, value) of one message: value is an int (varint, fixed) or
    the bytes of a length-delimited field (a `_Slice`)."""
    for field, wire, value, _ in _fields_at(buf):
        yield field, wire, value


# The fields libposecorr reads as messages or strings and refuses in other wire types
# (onnx.c), by the message that holds them; a field of the wrong type elsewhere it skips, and
# so does this reader. Its words name the field and the byte its key starts on.
_BYTES_FIELDS = {"model": (7, 8, 14),               # graph, opset_import, metadata_props
                 "graph": (1, 5, 11, 12),           # node, initializer, input, output
                 "node": (1, 2, 3, 4, 5, 7)}        # input, output, name, op_type, attribute, domain


def _message_fields(buf: bytes, kind: str) -> Iterator[tuple[int, int, Any]]:
    """`_fields` of a model, graph or node message, refusing its `_BYTES_FIELDS` in another
    wire type in libposecorr's words."""
    for field, wire, value, at in _fields_at(buf):
        if wire != 2 and field in _BYTES_FIELDS[kind]:
            raise _Malformed(f"{kind} field {field} at byte {at} is not bytes")
        yield field, wire, value


def _fields_at(buf: bytes) -> Iterator[tuple[int, int, Any, int]]:
    """`_fields`, each with the byte of the file its key starts on."""
    base = getattr(buf, "base", 0)
    pos, end = 0, len(buf)
    while pos < end:
        start = pos
        key, pos = _varint(buf, pos)
        field, wire = key >> 3, key & 7
        if field == 0 or field > 0x1FFFFFFF:
            raise _Malformed(f"invalid field number at byte {base + start}")
        if wire == 0:
            value, pos = _varint(buf, pos)
        elif wire in (1, 5):
            width = 8 if wire == 1 else 4
            if end - pos < width:
                raise _Truncated(f"truncated file at byte {base + pos} (inside a {width}-byte field)")
            value, pos = int.from_bytes(buf[pos:pos + width], "little"), pos + width
        elif wire == 2:
            length, pos = _varint(buf, pos)
            if length > end - pos:
                raise _Truncated(f"truncated file at byte {base + pos} (field {field} declares {length} bytes, "
                                 f"{end - pos} left)")
            value = _Slice(buf[pos:pos + length])
            value.base, pos = base + pos, pos + length
        else:
            raise _Malformed(f"unsupported wire type {wire} at byte {base + start}")
        yield field, wire, value, base + start


def _pick(fields: Iterator[tuple[int, int, Any]], defaults: dict[int, Any]) -> dict[int, Any]:
    """{field number: value} of one message's `fields` for the fields `defaults` names (the
    last occurrence wins, as in protobuf), the default where a field is absent. A field in
    another wire type than its default's (an int: varint; bytes or None: length-delimited)
    is skipped, as libposecorr skips it."""
    out = dict(defaults)
    for field, wire, value in fields:
        if field in out and wire == (0 if isinstance(defaults[field], int) else 2):
            out[field] = value
    return out


class _Lossy(str):
    """A string field that is not UTF-8, its undecodable bytes as U+FFFD (as the shim shows
    them in libposecorr's messages, which take names as bytes); `at`: the byte of the file
    where the first of them is. onnxruntime cannot load such a file (`first_not_utf8`)."""

    at = 0


def _str(value: bytes) -> str:
    try:
        return bytes(value).decode("utf-8")
    except UnicodeDecodeError as exc:
        text = _Lossy(bytes(value).decode("utf-8", errors="replace"))
        text.at = getattr(value, "base", 0) + exc.start
        return text


def first_not_utf8(*read: Any) -> int | None:
    """The byte of the file where the first string field of these readings (`read_model`,
    `read_graph`, `read_nodes`, nested as they are) that is not UTF-8 starts to be not; None
    where every one is."""
    found = []
    stack = list(read)
    while stack:
        item = stack.pop()
        if isinstance(item, _Lossy):
            found.append(item.at)
        elif isinstance(item, dict):
            stack += list(item) + list(item.values())
        elif isinstance(item, (list, tuple)):
            stack += item
    return min(found, default=None)


def _signed(v: int) -> int:
    return v - (1 << 64) if v >= 1 << 63 else v


def _value_info(buf: bytes) -> dict[str, Any]:
    """A ValueInfoProto: its name, element type (by name, "dtype", and number, "elem": 0
    without one) and shape (a dim: its value, its name, or None; None without a shape).
    Every field read here is length-delimited but the element type, a varint."""
    out: dict[str, Any] = {"name": "", "dtype": None, "elem": 0, "shape": None}
    for f, wire, v in _fields(buf):
        if f == 1 and wire == 2:
            out["name"] = _str(v)
        elif f == 2 and wire == 2:
            for tensor_type in (tv for tf, twire, tv in _fields(v) if tf == 1 and twire == 2):
                for ttf, ttwire, ttv in _fields(tensor_type):
                    if ttf == 1 and ttwire == 0:
                        out["elem"], out["dtype"] = ttv, ELEM_TYPES.get(ttv, f"type{ttv}")
                    elif ttf == 2 and ttwire == 2:
                        out["shape"] = [_dim(sv) for sf, swire, sv in _fields(ttv) if sf == 1 and swire == 2]
    return out


def _dim(buf: bytes) -> int | str | None:
    """A TensorShapeProto.Dimension: dim_value, dim_param, or None (neither)."""
    dim: int | str | None = None
    for f, wire, v in _fields(buf):
        if f == 1 and wire == 0:
            dim = _signed(v)
        elif f == 2 and wire == 2:
            dim = _str(v)
    return dim


def decode_value(text: str) -> Any:
    """A metadata value: JSON where it parses as JSON, else the string itself."""
    try:
        return json.loads(text)
    except (ValueError, TypeError):
        return text


def starts_like_onnx(head: bytes) -> bool:
    """Whether a file's first bytes open an ONNX ModelProto: its ir_version (field 1, a
    varint of one byte) comes first, as writers serialize fields in order. No text starts so
    (0x08 is a control character): a table is never taken for a model."""
    return len(head) >= 2 and head[0] == 0x08 and 0 < head[1] < 0x80


def read_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Metadata and structure of an ONNX model file.

    Returns the `metadata_props` (JSON values decoded) at the top level, plus "file",
    "file_size" (bytes), "ir_version", "producer", "opset_import" ({domain: version}),
    "inputs" / "outputs" ([{"name", "dtype", "shape"}], dynamic dims by name),
    "op_counts" ({op_type: n}), "node_count", "initializer_count", "parameter_count".
    Raises ValueError naming the file when it is not a readable ONNX model.
    """
    path = os.fspath(path)
    with open(path, "rb") as fh:
        data = fh.read()
    try:
        return _readable(_parse)(data, path)
    except TruncatedModel as exc:
        raise TruncatedModel(f"{path}: {exc}") from None
    except ValueError as exc:
        raise ValueError(f"{path}: not a valid ONNX model ({exc})") from None


def stated_metrics(info: dict[str, Any]) -> tuple[str, dict[str, Any], dict[str, Any] | None] | None:
    """The held-out figures a model file states of itself (its `test_metrics`): (kind,
    figures, raw figures or None); kind "test" (a shipped model's fixed split, or fit's) or
    "cv" (fit's cross-validation). None where it states none in either layout."""
    stated = info.get("test_metrics")
    if not isinstance(stated, dict):
        return None
    raw = stated.get("raw") if isinstance(stated.get("raw"), dict) else None
    if isinstance(stated.get("rmse_pos"), (int, float)):      # tools/models.py: the figures at the top
        return "test", stated, raw
    for kind in ("test", "cv"):                                  # fit: {kind: figures, "raw": figures}
        if isinstance(stated.get(kind), dict) and isinstance(stated[kind].get("rmse_pos"), (int, float)):
            return kind, stated[kind], raw
    return None


def stated_rigid(info: dict[str, Any]) -> dict[str, Any] | None:
    """The best rigid fit's figures on the same poses, scored as the model's held-out ones, as
    `fit` states them (`test_metrics` "rigid": {"name": its variant, "rmse_pos", ...}, "model" in
    files written before); None
    where the model states none (a shipped model, an older file)."""
    stated = info.get("test_metrics")
    rigid = stated.get("rigid") if isinstance(stated, dict) else None
    return rigid if isinstance(rigid, dict) and isinstance(rigid.get("rmse_pos"), (int, float)) else None


def describe_corrector(info: dict[str, Any]) -> str:
    """What a model file corrects with, from its metadata: "mlp 20-20-20-20 (tansig, br) on
    zhou", "pmc quadratic-9in-55terms (lstsq) on zhou", "rigid joint", "physics". The
    representation is named only for a data-driven core (one with an architecture)."""
    def given(key: str) -> str | None:
        value = info.get(key)
        return None if value in (None, "", "None", "none", "linear") else str(value)

    method = given("method") or "unknown method"
    core = given("architecture")
    text = " ".join(v for v in (method, given("rigid_variant") if method == "rigid" else core) if v)
    details = [v for v in (given("activation"), given("trainer")) if v]
    text += f" ({', '.join(details)})" if details else ""
    return text + (f" on {given('representation')}" if core and given("representation") else "")


def _parse(data: bytes, path: str) -> dict[str, Any]:
    if not data:
        raise _Truncated(EMPTY)
    top = _model(data)
    if top["ir_version"] is None:
        raise _Malformed("no ir_version")
    graph = _graph(top["graph"])
    graph.update(_nodes(graph))
    init_names = {name for name, _ in graph["initializers"]}
    ops: Counter[str] = Counter(f"{domain}::{op}" if domain and domain != "ai.onnx" else op
                                for op, domain, _ in graph["nodes"])
    shown = ("name", "dtype", "shape")
    structure = {
        "file": path, "file_size": len(data), "ir_version": top["ir_version"], "producer": top["producer"],
        "opset_import": top["opset_import"],
        # Graph inputs that are initializers (IR < 4 style) are not real inputs.
        "inputs": [{k: v[k] for k in shown} for kind, v in graph["io"]
                   if kind == "input" and v["name"] not in init_names],
        "outputs": [{k: v[k] for k in shown} for kind, v in graph["io"] if kind == "output"],
        "op_counts": dict(sorted(ops.items())), "node_count": len(graph["nodes"]),
        "initializer_count": len(init_names), "parameter_count": sum(size for _, size in graph["initializers"])}
    info = {key: decode_value(value) for key, value in top["metadata"].items()}
    for key, value in structure.items():
        if key in info:
            info[f"metadata_{key}"] = info.pop(key)  # never let metadata hide the file's facts
        info[key] = value
    return info


def _model(data: bytes) -> dict[str, Any]:
    """The ModelProto's top level: "metadata" ({key: value as stored, the last of a key
    given twice}), "repeated" (the keys given again, in the order of their second entry),
    "ir_version" (None without one), "producer", "opset_import" ({domain: version}) and the
    graph's bytes; "no graph" without one, as libposecorr says."""
    meta: dict[str, str] = {}
    repeated: list[str] = []
    opsets: dict[str, int] = {}
    top: dict[str, Any] = {"ir_version": None, "producer": {"name": "", "version": ""}, "graph": None}
    for f, wire, v in _message_fields(data, "model"):
        if f == 1 and wire == 0:
            top["ir_version"] = v
        elif f in (2, 3) and wire == 2:
            top["producer"]["name" if f == 2 else "version"] = _str(v)
        elif f == 7:
            top["graph"] = v
        elif f == 8:
            opset = _pick(_fields(v), {1: b"", 2: -1})      # OperatorSetIdProto: domain, version
            opsets[_str(opset[1]) or "ai.onnx"] = opset[2]
        elif f == 14:
            entry = _pick(_fields(v), {1: b"", 2: b""})     # StringStringEntryProto: key, value
            key = _str(entry[1])
            if key in meta and key not in repeated:
                repeated.append(key)
            meta[key] = _str(entry[2])
    if top["graph"] is None:
        raise _Malformed("no graph")
    return {"metadata": meta, "repeated": repeated, "opset_import": opsets, **top}


def _graph(graph: bytes) -> dict[str, Any]:
    """The GraphProto's own fields, as libposecorr reads them before any node: "io"
    [("input" or "output", `_value_info`)] in the file's order, "initializers" [(name,
    element count)], and the bytes of its "node_messages" and "initializer_messages" (read by
    `_nodes`, after the pose contract, as libposecorr reads them)."""
    io, initializers, node_messages, initializer_messages = [], [], [], []
    for f, _, v in _message_fields(graph, "graph"):
        if f == 1:
            node_messages.append(v)
        elif f == 5:
            initializers.append(_initializer(v))
            initializer_messages.append(v)
        elif f in (11, 12):
            io.append(("input" if f == 11 else "output", _value_info(v)))
    return {"io": io, "initializers": initializers, "node_messages": node_messages,
            "initializer_messages": initializer_messages}


def _nodes(graph: dict[str, Any], each: Callable[[str, str, str], None] | None = None) -> dict[str, Any]:
    """A `_graph`'s "nodes" [(op_type, domain, name)], each node's "node_io" ([its inputs'
    names], [its outputs']) and "constant_nodes" (the bytes of its Constant nodes, whose
    attributes `constant_tensors` reads). `each(op_type, domain, name)` sees each node as it
    is read."""
    nodes, node_io, constants = [], [], []
    for message in graph["node_messages"]:
        strings: dict[int, bytes] = {3: b"", 4: b"", 7: b""}   # name, op_type, domain
        inputs, outputs = [], []
        for f, _, v in _message_fields(message, "node"):        # all of these length-delimited
            if f in (1, 2):
                (inputs if f == 1 else outputs).append(_str(v))
            elif f in strings:
                strings[f] = v
        nodes.append((_str(strings[4]), _str(strings[7]), _str(strings[3])))
        node_io.append((inputs, outputs))
        if each is not None:
            each(*nodes[-1])
        if nodes[-1][0] == "Constant":
            constants.append(message)
    return {"nodes": nodes, "node_io": node_io, "constant_nodes": constants}


FLOAT = 1  # TensorProto.FLOAT
# What onnx.c holds of a tensor: its rank, its element count (PC_MAX_ELEMENTS on a 64-bit
# host), and the element types with their bytes in raw_data (int32 held as int64).
MAX_RANK = 6
MAX_ELEMENTS = 0x7FFFFFFF
RAW_BYTES = {FLOAT: 4, 6: 4, 7: 8, 9: 1}                # float, int32, int64, bool
# The repeated number fields and their elements' wire type: dims, float_data, int32_data,
# int64_data (packed, or one element a field).
_NUMBER_FIELDS = {1: 0, 4: 5, 5: 0, 7: 0}


@dataclasses.dataclass
class _Tensor:
    """One TensorProto as read field by field: what the three readers below take of it.
    `fault` is the first thing onnx.c's onnx_tensor_header refuses in the fields' order
    (libposecorr's status name, its words); the fields after it are read all the same."""

    name: str = ""
    dims: list[int] = dataclasses.field(default_factory=list)
    data_type: int = 0
    raw: bytes | None = None
    counts: dict[int, int] = dataclasses.field(default_factory=lambda: {4: 0, 5: 0, 7: 0})
    float_data: bytearray = dataclasses.field(default_factory=bytearray)   # little-endian float32
    fault: tuple[str, str] | None = None


def _tensor(buf: bytes, read_values: bool = True) -> _Tensor:
    """`read_values`: read the values fields too (the graph's first pass counts parameters
    from the shape alone and leaves a fault inside the values to the tensor's own check, where
    libposecorr meets it)."""
    t = _Tensor()

    def refuse(status: str, words: str) -> None:
        t.fault = t.fault or (status, words)

    for f, wire, v, at in _fields_at(buf):
        if f in _NUMBER_FIELDS and (read_values or f == 1):
            elem = _NUMBER_FIELDS[f]
            if wire == elem:
                values = [v]
                if f == 4:
                    t.float_data += int(v).to_bytes(4, "little")
            elif wire != 2:
                refuse("MALFORMED", f"field {f} at byte {at} has wire type {wire}")
                continue
            elif elem == 5:
                if len(v) % 4:
                    refuse("MALFORMED", f"packed field {f} at byte {at} is not a multiple of 4 bytes")
                values = [0] * (len(v) // 4)
                t.float_data += bytes(v)
            else:
                values, pos = [], 0
                while pos < len(v):
                    value, pos = _varint(v, pos)
                    values.append(value)
            if f != 1:
                t.counts[f] += len(values)
                continue
            if len(t.dims) + len(values) > MAX_RANK:
                refuse("UNSUPPORTED", f"tensor at byte {at} has rank > {MAX_RANK}")
            t.dims += map(_signed, values)
        elif f == 2 and wire == 0:
            t.data_type = _signed(v)
        elif f == 8 and wire == 2:
            t.name = _str(v)
        elif f == 9 and wire == 2:
            t.raw = bytes(v)
        elif f == 14 and wire == 0 and v == 1:         # data_location EXTERNAL
            refuse("UNSUPPORTED", f"tensor '{t.name}' uses external data")
    return t


def _initializer(buf: bytes) -> tuple[str, int]:
    """A TensorProto initializer's name and element count (a negative dimension as 0)."""
    t = _tensor(buf, read_values=False)
    return t.name, math.prod(max(d, 0) for d in t.dims)


def float_tensor(buf: bytes) -> dict[str, Any] | None:
    """{"name", "raw", "float_data"} of a float TensorProto that `tensor_fault` passed (the
    values as little-endian float32 bytes), None for other element types."""
    t = _tensor(buf)
    if t.data_type != FLOAT:
        return None
    return {"name": t.name, "raw": t.raw, "float_data": bytes(t.float_data)}


def tensor_fault(buf: bytes) -> tuple[str, str] | None:
    """What onnx.c's onnx_tensor_header says of one TensorProto before it holds it: None
    where it takes it, else (libposecorr's status name, its words): a rank above MAX_RANK,
    external data, a negative or too large shape, an element type it does not hold, raw_data
    or a values field whose size is not the shape's."""
    try:
        t = _tensor(buf)
    except _Truncated as exc:
        return "TRUNCATED", str(exc)
    except _Malformed as exc:
        return "MALFORMED", str(exc)
    if t.fault:
        return t.fault
    count = 1
    for d in t.dims:
        if d < 0 or (d > 0 and count > MAX_ELEMENTS // d):
            return "MALFORMED", f"tensor '{t.name}' has an invalid shape"
        count *= d
    if t.data_type not in RAW_BYTES:
        return "UNSUPPORTED", f"tensor '{t.name}' has unsupported data type {t.data_type}"
    if t.raw is not None:
        need = count * RAW_BYTES[t.data_type]
        return None if len(t.raw) == need else ("MALFORMED", f"tensor '{t.name}': raw_data has "
                                                             f"{len(t.raw)} bytes, shape needs {need}")
    have = t.counts[4] if t.data_type == FLOAT else t.counts[7] if t.data_type == 7 else t.counts[5]
    return None if have == count else ("MALFORMED", f"tensor '{t.name}' has {have} values, shape needs {count}")


def _readable(read: Callable[..., dict[str, Any]]) -> Callable[..., dict[str, Any]]:
    """`read` raising ValueError where the bytes are no ONNX model, TruncatedModel (one)
    where they end inside a field."""
    @functools.wraps(read)
    def wrapped(*args: Any, **kwargs: Any) -> dict[str, Any]:
        try:
            return read(*args, **kwargs)
        except _Truncated as exc:
            raise TruncatedModel(str(exc)) from None
        except _Malformed as exc:
            raise ValueError(str(exc)) from None
        except RecursionError:
            raise ValueError("nesting too deep") from None
    return wrapped


# The load-time checks' readers (`checks.check_model`), one per stage of libposecorr's load,
# so that a file with two faults is named by the one libposecorr meets first.
@_readable
def read_model(data: bytes) -> dict[str, Any]:
    """The ModelProto's top level: {"metadata": {key: value as stored}, "opset_import":
    {domain: version}, "ir_version", "producer", "graph": its bytes}."""
    if not data:
        raise _Truncated(EMPTY)
    return _model(data)


@_readable
def read_graph(model: dict[str, Any]) -> dict[str, Any]:
    """A `read_model`'s graph, up to its nodes: {"io": [("input" or "output", {"name",
    "dtype", "elem", "shape"})], "initializers": [(name, element count)], ...}."""
    return _graph(model["graph"])


@_readable
def read_nodes(graph: dict[str, Any], each: Callable[[str, str, str], None] | None = None) -> dict[str, Any]:
    """A `read_graph`'s nodes: {"nodes": [(op_type, domain, name)], "node_io": [([inputs],
    [outputs])], "constant_nodes": [the bytes of each Constant node]}. `each(op_type,
    domain, name)` is called on each node before the next is read, as libposecorr looks at
    a node's operator (a fault it raises stops the reading there)."""
    return _nodes(graph, each)


@_readable
def constant_tensors(node: bytes) -> list[bytes]:
    """The TensorProto of a Constant node's "value" attribute, if it has one: read where
    libposecorr folds the node, after the graph's references."""
    out = []
    for f, wire, v in _fields(node):
        if f == 5 and wire == 2:
            attr = _pick(_fields(v), {1: b"", 5: None})     # AttributeProto: name, t
            if _str(attr[1]) == "value" and attr[5] is not None:
                out.append(attr[5])
    return out
