"""ONNX's own conformance tests for libposecorr.

The onnx wheel builds its backend node tests in memory
(`onnx.backend.test.loader.load_model_tests(kind="node")`, no download). Every case
whose operators are all in export/operators.txt and whose default-domain opset is in the
range posecorr.h claims runs through the test-only entry of libposecorr_testing.so
(runtime_c/tests/testing.c: any input and output names, static shapes) and must match
the expected outputs with the case's own tolerances. Skips are named: a data type the
runtime does not support (it computes in float32, int64 and bool only).

The runtime plans every shape at load, so operands that set shapes or parameters (axes,
Slice bounds, Reshape's shape, Clip's bounds) must be constants, as they are in every
posecorr graph; where a node test feeds them as graph inputs, they are bound to the data
set's values as initializers before loading (PARAMETER_INPUTS).
"""
from __future__ import annotations

import ctypes
import re
import sys
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "runtime_c" / "tests"))

import graphs  # noqa: E402
from posecorr.controller.runtime import _Error  # noqa: E402

HEADER = (ROOT / "runtime_c" / "posecorr.h").read_text()
OPSETS = range(int(re.search(r"#define PC_OPSET_MIN (\d+)", HEADER)[1]),
               int(re.search(r"#define PC_OPSET_MAX (\d+)", HEADER)[1]) + 1)
OPERATORS = {ln.split("#")[0].strip() for ln in
             (ROOT / "export" / "operators.txt").read_text().splitlines()} - {""}
# numpy dtype of each TensorProto type the runtime computes in (bool travels as uint8).
SUPPORTED = {onnx.TensorProto.FLOAT: np.float32, onnx.TensorProto.INT64: np.int64,
             onnx.TensorProto.BOOL: np.bool_}


# Inputs the runtime needs at load, by operator: index of the input slot.
PARAMETER_INPUTS = {"Slice": {1, 2, 3, 4}, "ReduceSum": {1}, "ReduceMax": {1}, "Clip": {1, 2},
                    "Reshape": {1}, "Squeeze": {1}, "Unsqueeze": {1}}


def bind_parameters(case):
    """(model, data_sets) with the graph inputs in PARAMETER_INPUTS slots made initializers
    holding the first data set's values (every data set must agree on them)."""
    from onnx import numpy_helper

    model = onnx.ModelProto()
    model.CopyFrom(case.model)
    g = model.graph
    names = [vi.name for vi in g.input]
    bound = {n.input[k] for n in g.node for k in PARAMETER_INPUTS.get(n.op_type, ())
             if k < len(n.input) and n.input[k] in names}
    if not bound:
        return model, case.data_sets
    keep = [i for i, nm in enumerate(names) if nm not in bound]
    for nm in bound:
        i = names.index(nm)
        values = [np.asarray(inputs[i]) for inputs, _ in case.data_sets]
        assert all(np.array_equal(v, values[0]) for v in values), f"{nm} differs by data set"
        g.initializer.append(numpy_helper.from_array(values[0], nm))
    kept = [g.input[i] for i in keep]
    del g.input[:]
    g.input.extend(kept)
    data = [([inputs[i] for i in keep], outputs) for inputs, outputs in case.data_sets]
    return model, data


def _load_cases():
    from onnx.backend.test.loader import load_model_tests

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the case generators divide by zero on purpose
        return load_model_tests(kind="node")


def _ops(model) -> set[str]:
    return {n.op_type if n.domain in ("", "ai.onnx") else f"{n.domain}.{n.op_type}"
            for n in model.graph.node}


def _opset(model) -> int | None:
    return next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), None)


def select(cases) -> tuple[list, Counter]:
    """Cases the runtime claims (operators and opset); the others counted by reason."""
    chosen, other = [], Counter()
    for c in cases:
        ops = _ops(c.model)
        if not ops <= OPERATORS:
            other["operator not in operators.txt"] += 1
        elif _opset(c.model) not in OPSETS:
            other[f"opset {_opset(c.model)} outside {OPSETS.start}..{OPSETS.stop - 1}"] += 1
        else:
            chosen.append(c)
    return chosen, other


def _types_used(model) -> set[int]:
    """Every tensor element type the graph names: inputs, outputs, initializers, Cast
    targets and Constant values."""
    g = model.graph
    types = {vi.type.tensor_type.elem_type for vi in [*g.input, *g.output, *g.value_info]}
    types |= {t.data_type for t in g.initializer}
    for n in g.node:
        for a in n.attribute:
            if n.op_type == "Cast" and a.name == "to":
                types.add(a.i)
            if a.type == onnx.AttributeProto.TENSOR:
                types.add(a.t.data_type)
    return types


def skip_reason(case) -> str | None:
    g = case.model.graph
    if any(not vi.type.HasField("tensor_type") for vi in [*g.input, *g.output]):
        return "type optional or sequence (the runtime has tensors only)"
    bad = sorted(_types_used(case.model) - set(SUPPORTED))
    if bad:
        return "data type " + ", ".join(onnx.TensorProto.DataType.Name(t) for t in bad)
    return None


@pytest.fixture(scope="module")
def testing_lib() -> ctypes.CDLL:
    build = graphs.build_test_runtime()
    lib = ctypes.CDLL(str(build / "libposecorr_testing.so"))
    vp, sz = ctypes.c_void_p, ctypes.c_size_t
    lib.pc_test_load.argtypes = [ctypes.c_char_p, sz, ctypes.POINTER(vp), ctypes.POINTER(_Error)]
    lib.pc_test_load.restype = ctypes.c_int
    for fn in (lib.pc_test_input_count, lib.pc_test_output_count):
        fn.argtypes, fn.restype = [vp], sz
    lib.pc_test_slot_bytes.argtypes, lib.pc_test_slot_bytes.restype = [vp, sz], sz
    lib.pc_test_run.argtypes = [vp, ctypes.POINTER(vp), ctypes.POINTER(vp)]
    lib.pc_test_run.restype = ctypes.c_int
    lib.pc_free.argtypes, lib.pc_free.restype = [vp], None
    lib.pc_status_name.argtypes, lib.pc_status_name.restype = [ctypes.c_int], ctypes.c_char_p
    return lib


def run_case(lib: ctypes.CDLL, case) -> None:
    """Loads and runs one case on each of its data sets; raises AssertionError."""
    model, data_sets = bind_parameters(case)
    blob = model.SerializeToString()
    handle, err = ctypes.c_void_p(), _Error()
    st = lib.pc_test_load(blob, len(blob), ctypes.byref(handle), ctypes.byref(err))
    assert st == 0, f"load: {err.message.decode(errors='replace')}"
    try:
        n_in, n_out = lib.pc_test_input_count(handle), lib.pc_test_output_count(handle)
        for inputs, expected in data_sets:
            assert len(inputs) == n_in and len(expected) == n_out
            ins = [np.ascontiguousarray(x) for x in inputs]
            for k, x in enumerate(ins):
                assert x.nbytes == lib.pc_test_slot_bytes(handle, k), f"input {k} size"
            outs = [np.empty(np.shape(e), dtype=np.asarray(e).dtype) for e in expected]
            for k, o in enumerate(outs):
                assert o.nbytes == lib.pc_test_slot_bytes(handle, n_in + k), \
                    f"output {k}: {lib.pc_test_slot_bytes(handle, n_in + k)} bytes, " \
                    f"expected {o.shape} {o.dtype}"
            in_ptrs = (ctypes.c_void_p * max(1, n_in))(*[x.ctypes.data for x in ins])
            out_ptrs = (ctypes.c_void_p * max(1, n_out))(*[o.ctypes.data for o in outs])
            st = lib.pc_test_run(handle, in_ptrs, out_ptrs)
            assert st == 0, f"run: {lib.pc_status_name(st).decode()}"
            for k, (got, want) in enumerate(zip(outs, expected)):
                np.testing.assert_allclose(got, want, rtol=case.rtol, atol=case.atol,
                                           err_msg=f"{case.name} output {k}")
    finally:
        lib.pc_free(handle)


# Attributes a newer operator version added that cannot matter for the data types the
# runtime computes in, with the reason.
ALLOWED_NEW_ATTRIBUTES = {("Cast", "round_mode"): "rounding of float8/float4 targets only"}
# The opset whose operator signatures the runtime was written against.
BASE_OPSET = 21


def _signature(schema):
    return ({a.name: (a.type, a.required) for a in schema.attributes.values()},
            [(i.name, i.option) for i in schema.inputs], [(o.name, o.option) for o in schema.outputs],
            schema.min_input, schema.max_input, schema.min_output, schema.max_output)


def test_claimed_opsets_keep_every_operator_signature():
    """Claiming opsets past BASE_OPSET is sound only while no operator of operators.txt
    gained an input, output or attribute that matters (new versions that only widen
    the type lists are fine: the loader refuses types it does not compute in)."""
    from onnx import defs

    for op in sorted(OPERATORS):
        old = _signature(defs.get_schema(op, BASE_OPSET))
        for opset in range(BASE_OPSET + 1, OPSETS.stop):
            new = _signature(defs.get_schema(op, opset))
            added = {a for a in new[0].keys() - old[0].keys()
                     if (op, a) not in ALLOWED_NEW_ATTRIBUTES}
            assert not added and {a: new[0][a] for a in old[0]} == old[0], (op, opset)
            assert new[1:] == old[1:], (op, opset)


def test_onnx_node_conformance(testing_lib, summary):
    chosen, other = select(_load_cases())
    passed, skipped, failed = [], Counter(), []
    for case in chosen:
        reason = skip_reason(case)
        if reason:
            skipped[reason] += 1
            continue
        try:
            run_case(testing_lib, case)
        except AssertionError as e:
            failed.append(f"{case.name}: {str(e).strip().splitlines()[0][:300]}")
        else:
            passed.append(case.name)
    lines = [f"ONNX node tests: {len(passed)} passed, {sum(skipped.values())} skipped, "
             f"{len(failed)} failed (of {len(chosen)} whose operators and opset the runtime "
             f"claims)"]
    lines += [f"  skipped {n}: {reason}" for reason, n in sorted(skipped.items())]
    lines += [f"  not run {n}: {reason}" for reason, n in sorted(other.items())]
    summary("\n".join(lines))
    assert len(passed) >= 100, "implausibly few node tests ran"
    assert not failed, "\n".join(failed)
