"""ONNX files whose initializers can be read where they lie.

A C runtime that loads a model from flash or a memory-mapped file reads its float32 and
int64 weights in place only when their `raw_data` starts at an aligned offset of the file
(libposecorr: `PC_LOAD_IN_PLACE`). protobuf writes fields in number order and gives no
say over offsets, but a parser accepts a message's fields in any order and keeps the last
of a repeated scalar field. So each initializer is written as: its other fields, then a
padding `doc_string` (TensorProto field 12, spaces) sized so that the `raw_data` bytes
(field 9) that follow start at a multiple of `ALIGN`; the graph's initializers come after
its other fields, and the graph comes last in the model. Lengths of enclosing messages change with the padding, so the layout is
iterated until every offset holds. onnx.load, onnx.checker and onnxruntime read the
result as the same model (tests/test_export.py checks all three).

`python -m posecorr.export.aligned models/*.onnx` rewrites files in place (same weights and
metadata, byte for byte in every field but the padding and a `model_digest`, written anew)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import onnx

from posecorr.controller.digest import length_delimited

ALIGN = 16
# Field numbers of onnx.proto: ModelProto.graph, GraphProto.initializer,
# TensorProto.raw_data and doc_string.
_MODEL_GRAPH, _GRAPH_INITIALIZER, _TENSOR_RAW_DATA, _TENSOR_DOC_STRING = 7, 5, 9, 12
_BYTES = 2  # wire type of length-delimited fields


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _field(number: int, payload: bytes) -> bytes:
    return _varint(number << 3 | _BYTES) + _varint(len(payload)) + payload


def _padding(size: int) -> bytes:
    """A doc_string field of exactly `size` bytes (0, or at least 2: tag and length)."""
    if size == 0:
        return b""
    body = size - 2
    while len(_field(_TENSOR_DOC_STRING, b" " * body)) > size:
        body -= 1
    return _field(_TENSOR_DOC_STRING, b" " * body)


def _tensor_bytes(t: onnx.TensorProto, pad: int) -> tuple[bytes, int]:
    """The tensor with its raw_data last behind `pad` bytes of padding; the raw data's
    offset within the returned bytes (-1 without raw_data)."""
    if not t.raw_data:
        return t.SerializeToString(), -1
    rest = onnx.TensorProto()
    rest.CopyFrom(t)
    rest.ClearField("raw_data")
    rest.ClearField("doc_string")
    head = rest.SerializeToString() + _padding(pad)
    raw = _field(_TENSOR_RAW_DATA, t.raw_data)
    return head + raw, len(head) + len(raw) - len(t.raw_data)


def serialize_aligned(model: onnx.ModelProto, align: int = ALIGN) -> bytes:
    """`model` serialized with every initializer's raw_data at a multiple of `align`."""
    if align != ALIGN:
        raise ValueError(f"align must be {ALIGN}")
    inits = list(model.graph.initializer)
    graph = onnx.GraphProto()
    graph.CopyFrom(model.graph)
    del graph.initializer[:]
    outer = onnx.ModelProto()
    outer.CopyFrom(model)
    outer.ClearField("graph")
    # The model's other fields, then its graph: the graph's offset no longer depends on
    # the metadata after it, and a parser takes fields in any order.
    head, tail, graph_head = outer.SerializeToString(), b"", graph.SerializeToString()
    graph_start = len(head) + 2  # where the graph's bytes begin: known after a sweep
    for _ in range(8):
        # One sweep in file order: each initializer takes the smallest padding that puts its
        # raw_data on ALIGN, given where the ones before it ended.
        offset, fields = graph_start + len(graph_head), []
        for t in inits:
            for pad in range(0, 4 * ALIGN):
                if pad == 1 or (pad and len(_padding(pad)) != pad):
                    continue
                body, raw_at = _tensor_bytes(t, pad)
                f = _field(_GRAPH_INITIALIZER, body)
                if raw_at < 0 or (offset + len(f) - len(body) + raw_at) % ALIGN == 0:
                    break
            else:
                raise RuntimeError(f"no padding aligns initializer {t.name!r}")
            fields.append(f)
            offset += len(f)
        graph_bytes = graph_head + b"".join(fields)
        whole = head + _field(_MODEL_GRAPH, graph_bytes)
        if len(whole) - len(graph_bytes) == graph_start:
            return whole + tail
        graph_start = len(whole) - len(graph_bytes)
    raise RuntimeError("initializer offsets did not settle")


def raw_data_offsets(data: bytes) -> list[int]:
    """Offsets of the initializers' raw_data in a serialized model, in file order, found by
    walking the wire format (ModelProto.graph -> GraphProto.initializer ->
    TensorProto.raw_data)."""
    out = []
    for number, g0, g1 in length_delimited(data, 0, len(data)):
        if number != _MODEL_GRAPH:
            continue
        for number2, t0, t1 in length_delimited(data, g0, g1):
            if number2 == _GRAPH_INITIALIZER:
                out.extend(r0 for n3, r0, _ in length_delimited(data, t0, t1) if n3 == _TENSOR_RAW_DATA)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m posecorr.export.aligned",
                                     description="rewrite .onnx files with aligned initializers")
    parser.add_argument("files", nargs="+", type=Path)
    args = parser.parse_args(argv)
    from posecorr.safeio import write_bytes

    from posecorr.controller import digest

    for path in args.files:
        model = onnx.load(str(path))
        signed = False
        for entry in model.metadata_props:
            if entry.key == digest.KEY:  # the bytes change: the digest is written anew
                entry.value, signed = digest.PLACEHOLDER, True
        data = serialize_aligned(model)
        data = digest.sign(data) if signed else data
        write_bytes(path, data)
        print(f"{path}: {len(data)} bytes, {len(model.graph.initializer)} initializers aligned "
              f"to {ALIGN}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
