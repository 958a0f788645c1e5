"""Write a hand-written AVX2 single-pose function for ANY zhou tanh MLP exported by posecorr
(Mul/Add input scaling, a chain of Gemms with Tanh between, Mul/Add output scaling): every
layer's K and column blocks are compile-time constants, accumulators in registers, no FMA,
the runtime's tanh approximation and summation order, encode/decode from hand_core.h.
Usage: gen_hand.py MODEL.onnx OUT_DIR (writes the C source hand_any into OUT_DIR)
A copy of the host floor's generator (the issue's floor script), used by bench/floor_all.py."""
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

m = onnx.load(sys.argv[1]); out = Path(sys.argv[2])
I = {t.name: numpy_helper.to_array(t) for t in m.graph.initializer}
nodes = list(m.graph.node)
gemms = [n for n in nodes if n.op_type == "Gemm"]
assert all(not g.attribute for g in gemms), "Gemm attributes not handled"
by_out = lambda name: [n for n in nodes if name in n.output][0]
pre_add = by_out(gemms[0].input[0]); pre_mul = by_out(pre_add.input[0])
assert pre_add.op_type == "Add" and pre_mul.op_type == "Mul"
post_mul = [n for n in nodes if gemms[-1].output[0] in n.input][0]
post_add = [n for n in nodes if post_mul.output[0] in n.input][0]
for g in gemms[:-1]:
    nxt = [n for n in nodes if g.output[0] in n.input]
    assert len(nxt) == 1 and nxt[0].op_type == "Tanh", f"hidden activation {nxt[0].op_type} not tanh"


def arr(name, a):
    a = np.asarray(a, np.float32).ravel()
    return f"static const float {name}[{a.size}] __attribute__((aligned(32))) = {{" + ",".join(repr(float(x)) + "f" for x in a) + "};\n"


src = ['#include <immintrin.h>\n#include <math.h>\n#include <string.h>\n#include "hand_core.h"\n']
src.append(arr("IN_SCALE_", I[pre_mul.input[1]]) + arr("IN_SHIFT_", I[pre_add.input[1]]))
src.append(arr("OUT_SCALE_", I[post_mul.input[1]]) + arr("OUT_SHIFT_", I[post_add.input[1]]))
dims = []
for k, g in enumerate(gemms):
    W, b = I[g.input[1]], I[g.input[2]]
    K, N = W.shape; NP = (N + 7) // 8 * 8
    Wp = np.zeros((K, NP), np.float32); Wp[:, :N] = W
    bp = np.zeros(NP, np.float32); bp[:N] = b
    src.append(arr(f"WQ{k}", Wp) + arr(f"BQ{k}", bp)); dims.append((K, N, NP))
src.append('''
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
''')
maxp = max(NP for _, _, NP in dims)
body = [f"    float x[16] __attribute__((aligned(32))), h0[{maxp}] __attribute__((aligned(32))), h1[{maxp}] __attribute__((aligned(32)));\n",
        "    int i, k;\n", f"    for (i = 0; i < {dims[0][0]}; i++) x[i] = f[i] * IN_SCALE_[i] + IN_SHIFT_[i];\n"]
bufs = ["x", "h0", "h1"]
src_buf = "x"
for li, (K, N, NP) in enumerate(dims):
    last = li == len(dims) - 1
    dst = "h0" if src_buf != "h0" else "h1"
    nb = NP // 8
    body.append("    {\n")
    body.append("".join(f"        __m256 a{j} = _mm256_load_ps(BQ{li} + {8*j});\n" for j in range(nb)))
    body.append(f"        for (k = 0; k < {K}; k++) {{\n            const __m256 v = _mm256_broadcast_ss({src_buf} + k);\n")
    body.append("".join(f"            a{j} = _mm256_add_ps(a{j}, _mm256_mul_ps(v, _mm256_load_ps(WQ{li} + k * {NP} + {8*j})));\n" for j in range(nb)))
    body.append("        }\n")
    act = (lambda s: s) if last else (lambda s: f"tanh8({s})")
    body.append("".join(f"        _mm256_store_ps({dst} + {8*j}, {act(f'a{j}')});\n" for j in range(nb)))
    body.append("    }\n")
    src_buf = dst
body.append(f"    for (i = 0; i < {dims[-1][1]}; i++) y[i] = {src_buf}[i] * OUT_SCALE_[i] + OUT_SHIFT_[i];\n")
src.append("static inline void mlp_any(const float *f, float *y)\n{\n" + "".join(body) + "}\n")
src.append('''
__attribute__((noinline)) void hand_avx_correct(const float *in, float *out)
{
    float f[16], y[16];
    encode(in, f);
    mlp_any(f, y);
    decode(y, out);
}
''')
out.mkdir(parents=True, exist_ok=True)
(out / "hand_any.c").write_text("".join(src))
print("dims", [(K, N) for K, N, _ in dims])
