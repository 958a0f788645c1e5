"""Writes the weights of a zhou MLP .onnx file (the exporter's graph: input Mul/Add
scaling, five Gemm layers with Tanh between them, output Mul/Add scaling) as the float32
file posecorr-bench --reference-zhou reads (the field order of pc_zhou_weights in
zhou_reference.h).

    python zhou_weights.py MODEL.onnx WEIGHTS.bin
"""
from __future__ import annotations

import sys

import numpy as np
import onnx
from onnx import numpy_helper

IN, HIDDEN, LAYERS = 9, 20, 5


def weights(path: str) -> np.ndarray:
    """The pc_zhou_weights fields of the model, flattened; ValueError for another graph."""
    model = onnx.load(path)
    init = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    nodes = list(model.graph.node)
    gemms = [k for k, n in enumerate(nodes) if n.op_type == "Gemm"]
    if len(gemms) != LAYERS or gemms[0] < 2 or gemms[-1] + 2 >= len(nodes):
        raise ValueError(f"{path}: {len(gemms)} Gemm nodes, a zhou MLP 9-20-20-20-20-9 has {LAYERS}")
    for k in gemms:
        if any(a.name in ("transA", "transB", "alpha", "beta") for a in nodes[k].attribute):
            raise ValueError(f"{path}: Gemm '{nodes[k].name}' has attributes the reference does not model")
    mul_in, add_in = nodes[gemms[0] - 2], nodes[gemms[0] - 1]
    mul_out, add_out = nodes[gemms[-1] + 1], nodes[gemms[-1] + 2]
    if [n.op_type for n in (mul_in, add_in, mul_out, add_out)] != ["Mul", "Add"] * 2:
        raise ValueError(f"{path}: no Mul/Add scaling around the network")
    parts = [init[mul_in.input[1]], init[add_in.input[1]]]
    ws = [init[nodes[k].input[1]] for k in gemms]
    bs = [init[nodes[k].input[2]] for k in gemms]
    shapes = [(IN, HIDDEN)] + [(HIDDEN, HIDDEN)] * (LAYERS - 2) + [(HIDDEN, IN)]
    if [w.shape for w in ws] != shapes:
        raise ValueError(f"{path}: layer shapes {[w.shape for w in ws]}, expected {shapes}")
    parts += [ws[0], bs[0], *ws[1:-1], *bs[1:-1], ws[-1], bs[-1]]
    parts += [init[mul_out.input[1]], init[add_out.input[1]]]
    return np.concatenate([np.asarray(p, np.float32).ravel() for p in parts])


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__.strip().splitlines()[-1].strip(), file=sys.stderr)
        return 2
    weights(argv[1]).astype("<f4").tofile(argv[2])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
