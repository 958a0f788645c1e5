"""The weights of a posecorr tanh MLP .onnx file (the exporter's graph: input Mul/Add
scaling, a chain of Gemm layers with Tanh between them, output Mul/Add scaling) for the
hand-written C function of zhou_reference.c: `network()` reads any such MLP of the zhou or
quat representation (runtime_c/embedded/embed.py writes it as a pc_mlp); the main program
writes the shipped zhou 9-20-20-20-20-9 as the float32 file posecorr-bench --reference-zhou
reads (the field order of pc_zhou_weights in zhou_reference.h).

    python zhou_weights.py MODEL.onnx WEIGHTS.bin
"""
from __future__ import annotations

import sys
from typing import NamedTuple

import numpy as np
import onnx
from onnx import numpy_helper

# The representations the hand-written function encodes, with the network's width.
WIDTH = {"zhou": 9, "quat": 7}
ZHOU_SHAPES = [(9, 20), (20, 20), (20, 20), (20, 20), (20, 9)]


class Network(NamedTuple):
    # a NamedTuple, not a dataclass: bench/latency.py loads this file outside sys.modules
    representation: str
    in_scale: np.ndarray
    in_offset: np.ndarray
    layers: list[tuple[np.ndarray, np.ndarray]]  # (W [k][n], b [n]) in order
    out_scale: np.ndarray
    out_offset: np.ndarray


def network(path: str) -> Network:
    """The MLP of `path`; ValueError, naming the file, for another graph."""
    model = onnx.load(path)
    meta = {p.key: p.value for p in model.metadata_props}
    rep = meta.get("representation")
    if rep not in WIDTH or meta.get("method") != "mlp":
        raise ValueError(f"{path}: a {meta.get('method')} model of representation {rep}; "
                         f"the hand-written function is an MLP of {' or '.join(WIDTH)}")
    init = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    nodes = list(model.graph.node)
    gemms = [k for k, n in enumerate(nodes) if n.op_type == "Gemm"]
    if not gemms or gemms[0] < 2 or gemms[-1] + 2 >= len(nodes):
        raise ValueError(f"{path}: no Gemm chain between input and output scaling")
    for a, b in zip(gemms, gemms[1:]):
        if b != a + 2 or nodes[a + 1].op_type != "Tanh":
            raise ValueError(f"{path}: node '{nodes[a + 1].name}' between Gemm layers is "
                             f"{nodes[a + 1].op_type}, the hand-written function has Tanh")
    for k in gemms:
        if any(a.name in ("transA", "transB", "alpha", "beta") for a in nodes[k].attribute):
            raise ValueError(f"{path}: Gemm '{nodes[k].name}' has attributes the reference does not model")
    mul_in, add_in = nodes[gemms[0] - 2], nodes[gemms[0] - 1]
    mul_out, add_out = nodes[gemms[-1] + 1], nodes[gemms[-1] + 2]
    if [n.op_type for n in (mul_in, add_in, mul_out, add_out)] != ["Mul", "Add"] * 2:
        raise ValueError(f"{path}: no Mul/Add scaling around the network")
    f32 = lambda name: np.asarray(init[name], np.float32)  # noqa: E731
    layers = [(f32(nodes[k].input[1]), f32(nodes[k].input[2]).ravel()) for k in gemms]
    width = WIDTH[rep]
    if layers[0][0].shape[0] != width or layers[-1][0].shape[1] != width:
        raise ValueError(f"{path}: network {layers[0][0].shape[0]} in, {layers[-1][0].shape[1]} "
                         f"out; {rep} has {width}")
    return Network(rep, f32(mul_in.input[1]).ravel(), f32(add_in.input[1]).ravel(), layers,
                   f32(mul_out.input[1]).ravel(), f32(add_out.input[1]).ravel())


def weights(path: str) -> np.ndarray:
    """The pc_zhou_weights fields of the shipped zhou MLP, flattened; ValueError for another."""
    net = network(path)
    shapes = [w.shape for w, _ in net.layers]
    if net.representation != "zhou" or shapes != ZHOU_SHAPES:
        raise ValueError(f"{path}: {net.representation} layers {shapes}, expected zhou {ZHOU_SHAPES}")
    ws, bs = [w for w, _ in net.layers], [b for _, b in net.layers]
    parts = [net.in_scale, net.in_offset, ws[0], bs[0], *ws[1:-1], *bs[1:-1], ws[-1], bs[-1],
             net.out_scale, net.out_offset]
    return np.concatenate([p.ravel() for p in parts])


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__.strip().splitlines()[-1].strip(), file=sys.stderr)
        return 2
    weights(argv[1]).astype("<f4").tofile(argv[2])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
