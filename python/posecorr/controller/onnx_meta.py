"""Read an .onnx file's metadata without the onnx package (controller-side `posecorr info`).

A minimal protobuf wire-format reader (stdlib only) for the few ModelProto fields that
`info` shows: metadata_props, opset imports, producer, the graph's inputs / outputs with
their element types and shapes, node operator counts and initializer sizes; and, for the
load-time checks of the Python back ends (`checks.check_model`, `read_graph`), the nodes
and the bytes of the graph's float tensors.

Field numbers follow onnx.proto (ModelProto: ir_version 1, producer_name 2,
producer_version 3, doc_string 6, graph 7, opset_import 8, metadata_props 14; GraphProto:
node 1, name 2, initializer 5, input 11, output 12; NodeProto: op_type 4, domain 7;
ValueInfoProto: name 1, type 2; TypeProto.tensor_type 1: elem_type 1, shape 2;
TensorShapeProto.dim 1: dim_value 1, dim_param 2; TensorProto: dims 1, data_type 2,
float_data 4, name 8, raw_data 9; NodeProto: name 3, attribute 5; AttributeProto: name 1,
t 5).
"""
from __future__ import annotations

import json
import os
from collections import Counter
from typing import Any, Iterator

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
        yield field, wire, value


def _pick(buf: bytes, defaults: dict[int, Any]) -> dict[int, Any]:
    """{field number: value} of one message for the fields `defaults` names (the last
    occurrence wins, as in protobuf), the default where a field is absent."""
    out = dict(defaults)
    for field, _, value in _fields(buf):
        if field in out:
            out[field] = value
    return out


def _str(value: Any) -> str:
    if not isinstance(value, (bytes, bytearray)):
        raise _Malformed("expected a string field")
    try:
        return bytes(value).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _Malformed("string field is not UTF-8") from exc


def _msg(value: Any) -> bytes:
    if not isinstance(value, (bytes, bytearray)):
        raise _Malformed("expected an embedded message")
    return value if isinstance(value, _Slice) else bytes(value)


def _signed(v: int) -> int:
    return v - (1 << 64) if v >= 1 << 63 else v


def _value_info(buf: bytes) -> dict[str, Any]:
    out: dict[str, Any] = {"name": "", "dtype": None, "shape": None}
    for f, _, v in _fields(buf):
        if f == 1:
            out["name"] = _str(v)
        elif f == 2:
            for tf, _, tv in _fields(_msg(v)):
                if tf != 1:        # tensor_type only
                    continue
                for ttf, _, ttv in _fields(_msg(tv)):
                    if ttf == 1:
                        out["dtype"] = ELEM_TYPES.get(ttv, f"type{ttv}")
                    elif ttf == 2:
                        shape: list[Any] = []
                        for sf, _, sv in _fields(_msg(ttv)):
                            if sf != 1:
                                continue
                            dim: Any = None
                            for df, _, dv in _fields(_msg(sv)):
                                if df == 1:
                                    dim = _signed(dv)
                                elif df == 2:
                                    dim = _str(dv)
                            shape.append(dim)
                        out["shape"] = shape
    return out


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
        return _parse(data, path)
    except _Truncated as exc:
        raise TruncatedModel(f"{path}: {exc}") from None
    except _Malformed as exc:
        raise ValueError(f"{path}: not a valid ONNX model ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: not a valid ONNX model (nesting too deep)") from None


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
    `fit` states them (`test_metrics` "rigid": {"model": its variant, "rmse_pos", ...}); None
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
    meta, model = _model_fields(data)
    graph = _graph_fields(model.pop("graph"))
    structure = {"file": path, "file_size": len(data), **model, **graph}
    info = dict(meta)
    for key, value in structure.items():
        if key in info:
            info[f"metadata_{key}"] = info.pop(key)  # never let metadata hide the file's facts
        info[key] = value
    return info


def _model_fields(data: bytes) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ModelProto's metadata (values decoded) and its header: ir_version, producer,
    opset_import and the graph's bytes."""
    meta: dict[str, Any] = {}
    opsets: dict[str, int] = {}
    ir_version = None
    producer = {"name": "", "version": ""}
    graph: bytes | None = None
    for f, wire, v in _fields(data):
        if f == 1 and wire == 0:
            ir_version = v
        elif f == 2 and wire == 2:
            producer["name"] = _str(v)
        elif f == 3 and wire == 2:
            producer["version"] = _str(v)
        elif f == 7 and wire == 2:
            graph = _msg(v)
        elif f == 8 and wire == 2:
            opset = _pick(_msg(v), {1: b"", 2: 0})       # OperatorSetIdProto: domain, version
            opsets[_str(opset[1]) or "ai.onnx"] = opset[2]
        elif f == 14 and wire == 2:
            entry = _pick(_msg(v), {1: b"", 2: b""})     # StringStringEntryProto: key, value
            meta[_str(entry[1])] = decode_value(_str(entry[2]))
    if ir_version is None or graph is None:
        raise _Malformed("no ir_version or no graph (is this an ONNX ModelProto?)")
    return meta, {"ir_version": ir_version, "producer": producer, "opset_import": opsets,
                  "graph": graph}


def _initializer(buf: bytes) -> tuple[str, int]:
    """A TensorProto initializer's name and element count (dims packed or not)."""
    dims, name = [], ""
    for tf, twire, tv in _fields(buf):
        if tf == 1:
            if twire == 2:  # packed
                pos, b = 0, _msg(tv)
                while pos < len(b):
                    d, pos = _varint(b, pos)
                    dims.append(_signed(d))
            else:
                dims.append(_signed(tv))
        elif tf == 8:
            name = _str(tv)
    size = 1
    for d in dims:
        size *= max(d, 0)
    return name, size


def _graph_fields(graph: bytes) -> dict[str, Any]:
    """The GraphProto's inputs, outputs, op counts and initializer counts."""
    ops: Counter[str] = Counter()
    inputs, outputs = [], []
    initializer_names: set[str] = set()
    n_params = 0
    for f, wire, v in _fields(graph):
        if f == 1 and wire == 2:
            node = _pick(_msg(v), {4: b"", 7: b""})      # NodeProto: op_type, domain
            op, domain = _str(node[4]), _str(node[7])
            ops[f"{domain}::{op}" if domain and domain != "ai.onnx" else op] += 1
        elif f == 5 and wire == 2:
            name, size = _initializer(_msg(v))
            initializer_names.add(name)
            n_params += size
        elif f == 11 and wire == 2:
            inputs.append(_value_info(_msg(v)))
        elif f == 12 and wire == 2:
            outputs.append(_value_info(_msg(v)))
    return {
        # Graph inputs that are initializers (IR < 4 style) are not real inputs.
        "inputs": [i for i in inputs if i["name"] not in initializer_names], "outputs": outputs,
        "op_counts": dict(sorted(ops.items())), "node_count": int(sum(ops.values())),
        "initializer_count": len(initializer_names), "parameter_count": n_params,
    }


FLOAT = 1  # TensorProto.FLOAT


def _float_tensor(buf: bytes) -> dict[str, Any] | None:
    """{"name", "raw", "float_data"} of a float TensorProto (the values as little-endian
    float32 bytes), None for other element types."""
    name, data_type, raw, packed = "", 0, None, bytearray()
    for f, wire, v in _fields(buf):
        if f == 8 and wire == 2:
            name = _str(v)
        elif f == 2 and wire == 0:
            data_type = v
        elif f == 9 and wire == 2:
            raw = bytes(v)
        elif f == 4:
            packed += _msg(v) if wire == 2 else int(v).to_bytes(4, "little")
    if data_type != FLOAT:
        return None
    if raw is not None and len(raw) % 4:
        raise _Malformed(f"tensor '{name}': raw_data of {len(raw)} bytes is not float32")
    return {"name": name, "raw": raw, "float_data": bytes(packed)}


def read_graph(data: bytes) -> dict[str, Any]:
    """What the load-time checks look at: {"metadata": {key: value as stored},
    "opset_import": {domain: version}, "nodes": [(op_type, domain, name)],
    "float_tensors": [float initialisers and Constant values, see _float_tensor],
    "inputs": [names of the graph's inputs]}.
    Raises ValueError when the bytes are not an ONNX ModelProto, TruncatedModel (one) when
    they end inside a field."""
    try:
        if not data:
            raise _Truncated(EMPTY)
        return _read_graph(data)
    except _Truncated as exc:
        raise TruncatedModel(str(exc)) from None
    except _Malformed as exc:
        raise ValueError(str(exc)) from None
    except RecursionError:
        raise ValueError("nesting too deep") from None


def _read_graph(data: bytes) -> dict[str, Any]:
    meta: dict[str, str] = {}
    opsets: dict[str, int] = {}
    graph: bytes | None = None
    for f, wire, v in _fields(data):
        if f == 7 and wire == 2:
            graph = _msg(v)
        elif f == 8 and wire == 2:
            opset = _pick(_msg(v), {1: b"", 2: 0})
            opsets[_str(opset[1]) or "ai.onnx"] = opset[2]
        elif f == 14 and wire == 2:
            entry = _pick(_msg(v), {1: b"", 2: b""})
            meta[_str(entry[1])] = _str(entry[2])
    if graph is None:
        raise _Malformed("no graph (is this an ONNX ModelProto?)")
    nodes, tensors, inputs = [], [], []
    for f, wire, v in _fields(graph):
        if f == 1 and wire == 2:
            node = _pick(_msg(v), {3: b"", 4: b"", 7: b""})      # NodeProto: name, op_type, domain
            op = _str(node[4])
            nodes.append((op, _str(node[7]), _str(node[3])))
            if op != "Constant":
                continue
            for nf, nwire, nv in _fields(_msg(v)):              # the Constant's "value" tensor
                if nf == 5 and nwire == 2:
                    attr = _pick(_msg(nv), {1: b"", 5: None})
                    if _str(attr[1]) == "value" and attr[5] is not None:
                        tensor = _float_tensor(_msg(attr[5]))
                        if tensor is not None:
                            tensors.append(tensor)
        elif f == 5 and wire == 2:
            tensor = _float_tensor(_msg(v))
            if tensor is not None:
                tensors.append(tensor)
        elif f == 11 and wire == 2:
            inputs.append(_str(_pick(_msg(v), {1: b""})[1]))
    return {"metadata": meta, "opset_import": opsets, "nodes": nodes, "float_tensors": tensors,
            "inputs": inputs}
