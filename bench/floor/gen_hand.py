"""Write a hand-written AVX2 single-pose function for ANY MLP exported by posecorr with an
orientation representation (zhou, quat, eaa, R: the model's `representation` metadata) and
tanh, logistic sigmoid or radbas (exp(-x^2)) hidden layers: Mul/Add input scaling, a chain of
Gemms with the activation between, Mul/Add output scaling. Every layer's K and column blocks
are compile-time constants, accumulators in registers, no FMA, the runtime's activation
formulas and summation order; each representation's encode/decode is in hand_core.h.
Usage: gen_hand.py MODEL.onnx OUT_DIR (writes the C source hand_any into OUT_DIR)
A copy of the host floor's generator (the issue's floor script), extended past zhou tanh MLPs;
used by bench/floor_all.py and bench/floor/run.sh."""
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

# the representations (metadata) with an encode_REP/decode_REP pair in hand_core.h
CODECS = ("zhou", "quat", "eaa", "R")
# hidden activation -> (what it does to eight accumulators, or None: per lane by this
# hand_core.h function after the store)
ACTIVATIONS = {"tanh": ("tanh8", None), "sigmoid": (None, "act_sigmoid"), "radbas": (None, "act_radbas")}

TANH8 = '''
static inline __m256 tanh8(__m256 x)
{
    __m256 c = _mm256_min_ps(x, _mm256_set1_ps(9.0f)), t, p, q;
    c = _mm256_max_ps(c, _mm256_set1_ps(-9.0f));
    t = _mm256_mul_ps(c, c);
#define STEP(acc, coef) acc = _mm256_add_ps(_mm256_mul_ps(acc, t), _mm256_set1_ps(coef))
    p = _mm256_set1_ps(-8.291313e-14f);
    STEP(p, 5.1926935e-11f); STEP(p, -2.0029567e-08f); STEP(p, 1.1101826e-05f);
    STEP(p, 0.0030986548f); STEP(p, 0.13079165f); STEP(p, 0.99999994f);
    q = _mm256_set1_ps(0.00025386017f);
    STEP(q, 0.024473764f); STEP(q, 0.46412486f); STEP(q, 1.0f);
#undef STEP
    p = _mm256_div_ps(_mm256_mul_ps(c, p), q);
    p = _mm256_min_ps(p, _mm256_set1_ps(1.0f));
    return _mm256_max_ps(p, _mm256_set1_ps(-1.0f));
}
'''


def hidden_activation(path, nodes, gemm, nxt_gemm) -> str:
    """The activation between gemm and nxt_gemm: Tanh, Sigmoid, or Mul(x, x) -> Neg -> Exp."""
    users = lambda name: [n for n in nodes if name in n.input]
    first = users(gemm.output[0])
    chain = [first[0]] if len(first) == 1 else []
    while chain and chain[-1].output[0] != nxt_gemm.input[0] and len(users(chain[-1].output[0])) == 1:
        chain.append(users(chain[-1].output[0])[0])
    ops = [n.op_type for n in chain]
    if ops == ["Tanh"]:
        return "tanh"
    if ops == ["Sigmoid"]:
        return "sigmoid"
    if ops == ["Mul", "Neg", "Exp"] and list(chain[0].input) == [gemm.output[0]] * 2:
        return "radbas"
    raise SystemExit(f"{path}: hidden activation {' -> '.join(ops) or 'none'} after {gemm.name or gemm.output[0]}: "
                     "expected Tanh, Sigmoid or Mul(x, x) -> Neg -> Exp")


def arr(name, a):
    a = np.asarray(a, np.float32).ravel()
    return f"static const float {name}[{a.size}] __attribute__((aligned(32))) = {{" + ",".join(repr(float(x)) + "f" for x in a) + "};\n"


def read_model(path):
    """(codec, scaling arrays, [(W, b)], hidden activations) of an exported MLP."""
    m = onnx.load(path)
    meta = {p.key: p.value for p in m.metadata_props}
    rep = meta.get("representation")
    if rep not in CODECS:
        raise SystemExit(f"{path}: representation {rep!r} has no hand encode/decode; expected one of {', '.join(CODECS)}")
    I = {t.name: numpy_helper.to_array(t) for t in m.graph.initializer}
    nodes = list(m.graph.node)
    gemms = [n for n in nodes if n.op_type == "Gemm"]
    if not gemms or meta.get("method") != "mlp":
        raise SystemExit(f"{path}: method {meta.get('method')!r}: an MLP (method 'mlp', Gemm layers) is expected")
    assert all(not g.attribute for g in gemms), "Gemm attributes not handled"
    by_out = lambda name: [n for n in nodes if name in n.output][0]
    pre_add = by_out(gemms[0].input[0]); pre_mul = by_out(pre_add.input[0])
    assert pre_add.op_type == "Add" and pre_mul.op_type == "Mul"
    post_mul = [n for n in nodes if gemms[-1].output[0] in n.input][0]
    post_add = [n for n in nodes if post_mul.output[0] in n.input][0]
    scaling = [I[pre_mul.input[1]], I[pre_add.input[1]], I[post_mul.input[1]], I[post_add.input[1]]]
    acts = [hidden_activation(path, nodes, g, h) for g, h in zip(gemms, gemms[1:])]
    layers = [(I[g.input[1]], I[g.input[2]]) for g in gemms]
    return rep, scaling, layers, acts


def layer_code(li, K, N, NP, act, src_buf, dst):
    """One layer: NP / 8 accumulators over k, the activation, the store."""
    nb = NP // 8
    vec, lane = ACTIVATIONS[act] if act else (None, None)
    wrap = (lambda s: f"{vec}({s})") if vec else (lambda s: s)
    body = ["    {\n"]
    body.append("".join(f"        __m256 a{j} = _mm256_load_ps(BQ{li} + {8*j});\n" for j in range(nb)))
    body.append(f"        for (k = 0; k < {K}; k++) {{\n            const __m256 v = _mm256_broadcast_ss({src_buf} + k);\n")
    body.append("".join(f"            a{j} = _mm256_add_ps(a{j}, _mm256_mul_ps(v, _mm256_load_ps(WQ{li} + k * {NP} + {8*j})));\n" for j in range(nb)))
    body.append("        }\n")
    body.append("".join(f"        _mm256_store_ps({dst} + {8*j}, {wrap(f'a{j}')});\n" for j in range(nb)))
    if lane:
        body.append(f"        for (i = 0; i < {N}; i++) {dst}[i] = {lane}({dst}[i]);\n")
    body.append("    }\n")
    return body


def write(path, out):
    codec, scaling, layers, acts = read_model(path)
    src = ['#include <immintrin.h>\n#include <math.h>\n#include <string.h>\n#include "hand_core.h"\n']
    src.append(arr("IN_SCALE_", scaling[0]) + arr("IN_SHIFT_", scaling[1]))
    src.append(arr("OUT_SCALE_", scaling[2]) + arr("OUT_SHIFT_", scaling[3]))
    dims = []
    for k, (W, b) in enumerate(layers):
        K, N = W.shape; NP = (N + 7) // 8 * 8
        Wp = np.zeros((K, NP), np.float32); Wp[:, :N] = W
        bp = np.zeros(NP, np.float32); bp[:N] = b
        src.append(arr(f"WQ{k}", Wp) + arr(f"BQ{k}", bp)); dims.append((K, N, NP))
    if "tanh" in acts:
        src.append(TANH8)
    maxp = max(NP for _, _, NP in dims)
    body = [f"    float x[16] __attribute__((aligned(32))), h0[{maxp}] __attribute__((aligned(32))), h1[{maxp}] __attribute__((aligned(32)));\n",
            "    int i, k;\n", f"    for (i = 0; i < {dims[0][0]}; i++) x[i] = f[i] * IN_SCALE_[i] + IN_SHIFT_[i];\n"]
    src_buf = "x"
    for li, (K, N, NP) in enumerate(dims):
        dst = "h0" if src_buf != "h0" else "h1"
        body += layer_code(li, K, N, NP, acts[li] if li < len(acts) else None, src_buf, dst)
        src_buf = dst
    body.append(f"    for (i = 0; i < {dims[-1][1]}; i++) y[i] = {src_buf}[i] * OUT_SCALE_[i] + OUT_SHIFT_[i];\n")
    src.append("static inline void mlp_any(const float *f, float *y)\n{\n" + "".join(body) + "}\n")
    src.append(f'''
__attribute__((noinline)) void hand_avx_correct(const float *in, float *out)
{{
    float f[16], y[16];
    encode_{codec}(in, f);
    mlp_any(f, y);
    decode_{codec}(y, out);
}}
''')
    out.mkdir(parents=True, exist_ok=True)
    (out / "hand_any.c").write_text("".join(src))
    print("representation", codec, "activations", acts, "dims", [(K, N) for K, N, _ in dims])


if __name__ == "__main__":
    write(sys.argv[1], Path(sys.argv[2]))
