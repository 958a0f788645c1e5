/* Dense kernels (Gemm, MatMul, fused activations): the hot path of an MLP corrector.
 * Built with the vectoriser on; the operators' preparation (op_*.c) is built for size. */
#include "kernels.h"

#include <math.h>
#include <string.h>

/* The dense layers dominate a run; on x86-64 with GCC or Clang they are also compiled
 * for AVX2 and picked at load when the CPU and OS support it (cpuid + xgetbv, no libgcc
 * CPU model). Each output lane sums in the same order and no multiply-add is fused, so
 * both variants give bit-identical results. */
#if defined(__GNUC__) && defined(__x86_64__) && !defined(PC_NO_AVX2) && \
    !defined(__SANITIZE_ADDRESS__)
#define PC_HAVE_AVX2 1
#include <cpuid.h>
#endif


/* Radbas's loop out of line: inlined in the switch below, it cost the rows of a
 * Cortex-M4 160 instructions a pose of the zhou MLP, which has no radbas layer (make
 * embedded: 11014, out of line 10868, without radbas 10854). */
PC_NOINLINE static void pc_radbas_lanes(float *restrict o, size_t n)
{
    size_t i;
    for (i = 0; i < n; i++)
        o[i] = pc_radbas(o[i]);
}

/* Separate flat loops so each one vectorises. */
PC_INLINE void pc_apply_act(const pc_gemm *q, float *restrict o, size_t n)
{
    size_t i;
    const float lo = q->lo, hi = q->hi;
    switch (q->act) {
    case PC_ACT_TANH:
        for (i = 0; i < n; i++)
            o[i] = pc_tanh_inline(o[i]);
        break;
    case PC_ACT_SIGMOID:
        for (i = 0; i < n; i++)
            o[i] = pc_sigmoid(o[i]);
        break;
    case PC_ACT_RELU:
        for (i = 0; i < n; i++)
            o[i] = PC_RELU_EXPR(o[i]);
        break;
    case PC_ACT_CLIP:
        for (i = 0; i < n; i++)
            o[i] = pc_clip(o[i], lo, hi);
        break;
    case PC_ACT_RADBAS:
        pc_radbas_lanes(o, n);
        break;
    default:
        break;
    }
}

/* o[0..N) += a . B for one row; B row-major with row stride b_rs. Accumulators live in
 * registers in blocks of 8 and 4 outputs (a store-reload per k was the bottleneck); the
 * summation order per output (o first, then k ascending) is that of the plain loop. */
PC_INLINE void pc_row(const float *a, size_t a_cs, const float *B, size_t b_rs, size_t K,
                   size_t N, float *o)
{
    size_t n0 = 0, k, j;
    for (; n0 + 8 <= N; n0 += 8) {
        float acc[8];
        for (j = 0; j < 8; j++)
            acc[j] = o[n0 + j];
        for (k = 0; k < K; k++) {
            const float av = a[k * a_cs];
            const float *b = B + k * b_rs + n0;
            for (j = 0; j < 8; j++)
                acc[j] += av * b[j];
        }
        for (j = 0; j < 8; j++)
            o[n0 + j] = acc[j];
    }
    for (; n0 + 4 <= N; n0 += 4) {
        float acc[4];
        for (j = 0; j < 4; j++)
            acc[j] = o[n0 + j];
        for (k = 0; k < K; k++) {
            const float av = a[k * a_cs];
            const float *b = B + k * b_rs + n0;
            for (j = 0; j < 4; j++)
                acc[j] += av * b[j];
        }
        for (j = 0; j < 4; j++)
            o[n0 + j] = acc[j];
    }
    for (; n0 < N; n0++) {
        float acc = o[n0];
        for (k = 0; k < K; k++)
            acc += a[k * a_cs] * B[k * b_rs + n0];
        o[n0] = acc;
    }
}

PC_INLINE void pc_gemm_one(const pc_gemm *q, const float *A, const float *B, const float *C,
                        float *O)
{
    size_t m, k, n;
    const size_t N = q->N;
    for (m = 0; m < q->M; m++) {
        float *restrict o = O + m * N;
        const float *a = A + m * q->a_rs;
        switch (q->c_mode) {
        case 0: for (n = 0; n < N; n++) o[n] = 0.0f; break;
        case 1: for (n = 0; n < N; n++) o[n] = q->beta * C[0]; break;
        case 2: for (n = 0; n < N; n++) o[n] = q->beta * C[n]; break;
        case 3: for (n = 0; n < N; n++) o[n] = q->beta * C[m]; break;
        default: for (n = 0; n < N; n++) o[n] = q->beta * C[m * N + n]; break;
        }
        if (q->b_cs == 1 && q->alpha == 1.0f) {
            pc_row(a, q->a_cs, B, q->b_rs, q->K, N, o);
        } else if (q->b_cs == 1) {
            for (k = 0; k < q->K; k++) {
                const float av = q->alpha * a[k * q->a_cs];
                const float *restrict b = B + k * q->b_rs;
                for (n = 0; n < N; n++)
                    o[n] += av * b[n];
            }
        } else {
            for (k = 0; k < q->K; k++) {
                const float av = q->alpha * a[k * q->a_cs];
                const float *b = B + k * q->b_rs;
                for (n = 0; n < N; n++)
                    o[n] += av * b[n * q->b_cs];
            }
        }
    }
    pc_apply_act(q, O, q->M * N);
}

PC_COLD pc_status k_gemm(const pc_step *s)
{
    pc_gemm_one((const pc_gemm *)s->prm, (const float *)s->io[0], (const float *)s->io[1],
                (const float *)s->io[2], (float *)s->io[3]);
    return PC_OK;
}

/* GCC/Clang vector types where the target has vector registers (no intrinsics): on a
 * Cortex-M's scalar FPU the compiler splits them through the stack, and the plain rows
 * (pc_row) run in fewer instructions. */
#if defined(__GNUC__) && !(defined(__arm__) && !defined(__ARM_NEON))
#define PC_HAVE_ROWS4 1
/* GCC/Clang vector types (no intrinsics, no ISA assumption): lanes are independent, so
 * per output the summation order is that of pc_row (C first, then k ascending) and the
 * results are bit-identical. Each B load serves four rows. */
typedef float pc_v8 __attribute__((vector_size(32)));
typedef float pc_v4 __attribute__((vector_size(16)));

/* A scalar times a vector is written as a vector of that scalar: where C evaluates float
 * arithmetic in a wider type (FLT_EVAL_METHOD 1 on s390x, 2 on x87), GCC refuses a scalar
 * operand whose lanes would narrow it. The splat is the broadcast the scalar form compiles to
 * (a macro: a function returning a 32-byte vector has an ABI that depends on AVX). X is a
 * plain float variable, read once per lane. */
#define PC_SPLAT8(X) ((pc_v8){(X), (X), (X), (X), (X), (X), (X), (X)})
#define PC_SPLAT4(X) ((pc_v4){(X), (X), (X), (X)})

PC_INLINE void pc_rows4(const float *A, size_t K, const float *B, size_t N, const float *C,
                        float *O)
{
    size_t n0 = 0, k, j;
    /* Columns in blocks of WIDTH lanes of type VEC, four rows at a time. */
#define PC_ROWS4_BLOCKS(VEC, WIDTH, SPLAT)                           \
    for (; n0 + (WIDTH) <= N; n0 += (WIDTH)) {                       \
        VEC a0, a1, a2, a3;                                          \
        memcpy(&a0, C + n0, sizeof a0);                              \
        a1 = a2 = a3 = a0;                                           \
        for (k = 0; k < K; k++) {                                    \
            const float s0 = A[k], s1 = A[K + k], s2 = A[2 * K + k], \
                        s3 = A[3 * K + k];                           \
            VEC b;                                                   \
            memcpy(&b, B + k * N + n0, sizeof b);                    \
            a0 += SPLAT(s0) * b;                                     \
            a1 += SPLAT(s1) * b;                                     \
            a2 += SPLAT(s2) * b;                                     \
            a3 += SPLAT(s3) * b;                                     \
        }                                                            \
        memcpy(O + n0, &a0, sizeof a0);                              \
        memcpy(O + N + n0, &a1, sizeof a1);                          \
        memcpy(O + 2 * N + n0, &a2, sizeof a2);                      \
        memcpy(O + 3 * N + n0, &a3, sizeof a3);                      \
    }
    PC_ROWS4_BLOCKS(pc_v8, 8, PC_SPLAT8)
    PC_ROWS4_BLOCKS(pc_v4, 4, PC_SPLAT4)
#undef PC_ROWS4_BLOCKS
    for (; n0 < N; n0++) {
        for (j = 0; j < 4; j++) {
            float acc = C[n0];
            for (k = 0; k < K; k++)
                acc += A[j * K + k] * B[k * N + n0];
            O[j * N + n0] = acc;
        }
    }
}

/* One row of A B + c, the columns in NV8 eight-lane and NV4 four-lane accumulators that
 * all run in one pass over k: a pose's layer is latency-bound, and independent chains of
 * additions overlap where one pass per block waited on each chain in turn. NV8 and NV4
 * are constants after inlining, so the accumulators stay in registers. Same summation
 * order as pc_row (c first, then k ascending). */
PC_INLINE void pc_row1_block(const float *a, const float *B, size_t K, size_t N,
                             const float *C, float *O, const size_t NV8, const size_t NV4)
{
    pc_v8 acc8[3];
    pc_v4 acc4[1];
    const float *C4 = C + 8 * NV8;
    size_t k, j;
    for (j = 0; j < NV8; j++)
        memcpy(&acc8[j], C + 8 * j, sizeof acc8[j]);
    for (j = 0; j < NV4; j++)
        memcpy(&acc4[j], C4 + 4 * j, sizeof acc4[j]);
    for (k = 0; k < K; k++) {
        const float av = a[k];
        const pc_v8 av8 = PC_SPLAT8(av);
        const pc_v4 av4 = PC_SPLAT4(av);
        const float *b = B + k * N;
        for (j = 0; j < NV8; j++) {
            pc_v8 bv;
            memcpy(&bv, b + 8 * j, sizeof bv);
            acc8[j] += av8 * bv;
        }
        for (j = 0; j < NV4; j++) {
            pc_v4 bv;
            memcpy(&bv, b + 8 * NV8 + 4 * j, sizeof bv);
            acc4[j] += av4 * bv;
        }
    }
    for (j = 0; j < NV8; j++)
        memcpy(O + 8 * j, &acc8[j], sizeof acc8[j]);
    for (j = 0; j < NV4; j++)
        memcpy(O + 8 * NV8 + 4 * j, &acc4[j], sizeof acc4[j]);
}

/* a B + c for one row (a fused tanh runs over the whole output after: a separate
 * vectorised pass measured faster than four-lane tanh on the accumulators). */
PC_INLINE void pc_row1(const float *a, const float *B, size_t K, size_t N, const float *C,
                       float *restrict O)
{
    size_t n0 = 0, k;
    while (N - n0 >= 4) {
        const size_t nv8 = (N - n0) / 8 < 3 ? (N - n0) / 8 : 3;
        const size_t nv4 = (N - n0 - 8 * nv8) >= 4 && nv8 < 3;
#define PC_ROW1_CASE(A8, A4)                                                                   \
    case 2 * (A8) + (A4): pc_row1_block(a, B + n0, K, N, C + n0, O + n0, A8, A4); break;
        switch (2 * nv8 + nv4) {
            PC_ROW1_CASE(0, 1)
            PC_ROW1_CASE(1, 0)
            PC_ROW1_CASE(1, 1)
            PC_ROW1_CASE(2, 0)
            PC_ROW1_CASE(2, 1)
        default:
            pc_row1_block(a, B + n0, K, N, C + n0, O + n0, 3, 0);
            break;
        }
#undef PC_ROW1_CASE
        n0 += 8 * nv8 + 4 * nv4;
    }
    for (; n0 < N; n0++) {
        float acc = C[n0];
        for (k = 0; k < K; k++)
            acc += a[k] * B[k * N + n0];
        O[n0] = acc;
    }
}
#endif

#ifndef PC_HAVE_ROWS4
/* a B + c for one row on a scalar FPU: the columns in blocks of eight, then four, then one,
 * their sums in registers over the whole pass on k (a load, a multiply and an add per
 * multiply-add; stores and reloads of o per k doubled that). Same order as pc_row. */
#define PC_SCALAR_BLOCK(W, BODY)                                                               \
    for (; n0 + (W) <= N; n0 += (W)) {                                                         \
        const float *b = B + n0, *const a_end = a + K, *ak;                                    \
        float s0 = C[n0], s1 = 0.0f, s2 = 0.0f, s3 = 0.0f, s4 = 0.0f, s5 = 0.0f, s6 = 0.0f,     \
              s7 = 0.0f;                                                                       \
        if ((W) > 1) { s1 = C[n0 + 1]; s2 = C[n0 + 2]; s3 = C[n0 + 3]; }                        \
        if ((W) > 4) { s4 = C[n0 + 4]; s5 = C[n0 + 5]; s6 = C[n0 + 6]; s7 = C[n0 + 7]; }        \
        for (ak = a; ak < a_end; ak++, b += N) {                                               \
            const float av = *ak;                                                              \
            BODY;                                                                              \
        }                                                                                      \
        O[n0] = s0;                                                                            \
        if ((W) > 1) { O[n0 + 1] = s1; O[n0 + 2] = s2; O[n0 + 3] = s3; }                        \
        if ((W) > 4) { O[n0 + 4] = s4; O[n0 + 5] = s5; O[n0 + 6] = s6; O[n0 + 7] = s7; }        \
    }
PC_INLINE void pc_row_scalar(const float *a, const float *B, size_t K, size_t N,
                             const float *C, float *restrict O)
{
    size_t n0 = 0;
    PC_SCALAR_BLOCK(8, s0 += av * b[0]; s1 += av * b[1]; s2 += av * b[2]; s3 += av * b[3];
                    s4 += av * b[4]; s5 += av * b[5]; s6 += av * b[6]; s7 += av * b[7])
    PC_SCALAR_BLOCK(4, s0 += av * b[0]; s1 += av * b[1]; s2 += av * b[2]; s3 += av * b[3])
    PC_SCALAR_BLOCK(1, s0 += av * b[0])
}
#undef PC_SCALAR_BLOCK
#endif

/* Rows of act(A B + c): no transposes, bias row, alpha = beta = 1 (the MLP layer). Four
 * rows at a time for batches; the activation runs once over the whole contiguous output. */
PC_INLINE void pc_gemm_rows(const pc_gemm *q, void *const *io)
{
    const float *A = (const float *)io[0];
    const float *B = (const float *)io[1];
    const float *C = (const float *)io[2];
    float *restrict O = (float *)io[3];
    const size_t N = q->N, K = q->K, M = q->M;
    size_t m = 0;
#ifdef PC_HAVE_ROWS4
    for (; m + 4 <= M; m += 4)
        pc_rows4(A + m * K, K, B, N, C, O + m * N);
    for (; m < M; m++)
        pc_row1(A + m * K, B, K, N, C, O + m * N);
#else
    for (; m < M; m++)
        pc_row_scalar(A + m * K, B, K, N, C, O + m * N);
#endif
    pc_apply_act(q, O, M * N);
}

/* One copy of the layer serves the step and the chain. */
PC_NOINLINE static void pc_layer_rows(const pc_gemm *q, void *const *io)
{
    pc_gemm_rows(q, io);
}

/* One kernel for both activations: the test per launch is free next to the layer. */
static pc_status k_gemm_rows(const pc_step *s)
{
    pc_layer_rows((const pc_gemm *)s->prm, s->io);
    return PC_OK;
}

/* The layers of a chain in turn, each by the function the planner picked for its shape
 * (pc_chain_layer_fn). */
PC_HOT pc_status k_gemm_chain(const pc_step *s)
{
    const pc_gemm_chain *q = (const pc_gemm_chain *)s->prm;
    const pc_chain_layer *l = q->layer, *const end = l + q->n_layers;
    void *const *io = s->io;
    for (; l < end; l++, io += 4)
        l->fn(&l->g, io);
    return PC_OK;
}

#ifdef PC_HAVE_AVX2
#include <immintrin.h>
#define PC_AVX2_INLINE static inline __attribute__((always_inline, target("avx2")))

/* pc_tanh_inline on eight lanes: the same operations in the same order (the clamps as
 * min/max with the constant first, which keeps a NaN as the scalar comparisons do). */
PC_AVX2_INLINE __m256 pc_tanh8(__m256 x)
{
    const __m256 c = _mm256_max_ps(_mm256_set1_ps(-9.0f), _mm256_min_ps(_mm256_set1_ps(9.0f), x));
    const __m256 t = _mm256_mul_ps(c, c);
    __m256 p = _mm256_set1_ps(-8.291313e-14f), q = _mm256_set1_ps(0.00025386017f);
#define PC_HORNER(acc, coef) acc = _mm256_add_ps(_mm256_mul_ps(acc, t), _mm256_set1_ps(coef))
    PC_HORNER(p, 5.1926935e-11f);
    PC_HORNER(p, -2.0029567e-08f);
    PC_HORNER(p, 1.1101826e-05f);
    PC_HORNER(p, 0.0030986548f);
    PC_HORNER(p, 0.13079165f);
    PC_HORNER(p, 0.99999994f);
    PC_HORNER(q, 0.024473764f);
    PC_HORNER(q, 0.46412486f);
    PC_HORNER(q, 1.0f);
#undef PC_HORNER
    p = _mm256_div_ps(_mm256_mul_ps(c, p), q);
    return _mm256_max_ps(_mm256_set1_ps(-1.0f), _mm256_min_ps(_mm256_set1_ps(1.0f), p));
}

/* The first n (1 to 8) lanes of v at o. */
PC_AVX2_INLINE void pc_store_lanes(float *o, __m256 v, int n)
{
    __m128 part = _mm256_castps256_ps128(v);
    if (n == 8) {
        _mm256_storeu_ps(o, v);
        return;
    }
    if (n >= 4) {
        _mm_storeu_ps(o, part);
        part = _mm256_extractf128_ps(v, 1);
        o += 4;
        n -= 4;
    }
    if (n >= 2) {
        _mm_storel_pi((__m64 *)(void *)o, part);
        part = _mm_movehl_ps(part, part);
        o += 2;
        n -= 2;
    }
    if (n)
        _mm_store_ss(o, part);
}

/* Eight-lane blocks a one-pose layer keeps in registers at most. */
#define PC_MAX_BLOCKS 8

/* One pose through one layer of at most 8 NB outputs (NB up to PC_MAX_BLOCKS): NB
 * accumulators that stay in registers over the whole pass on k, the activation applied
 * to them before the one store. The last block reads whole vectors while they lie inside
 * B (its lanes past N then hold the next row's weights: summed, never stored) and masked
 * loads for the last rows, so nothing is read beyond B and weights used in place need no
 * padding. Per lane the order is that of pc_row1 (c, then k ascending, no fused
 * multiply-add): results are bit-identical. The accumulators are named, not an array:
 * GCC then schedules the activation of three blocks without spilling. It stays whole:
 * its parts share those accumulators, which a call between them would send to memory. */
PC_AVX2_INLINE void pc_layer1_blocks(const float *a, const float *B, size_t ldb, size_t K,
                                     size_t N, const float *C, int tanh_act, float *O,
                                     const int NB)
{
    const int tail = (int)(N - 8 * (size_t)(NB - 1));
    const __m256i mask = _mm256_cmpgt_epi32(_mm256_set1_epi32(tail),
                                            _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
    /* The last block reads `over` floats past a row, which ends the row of B (ldb apart):
     * the rows from `whole` on would read past B (no division for ldb >= over, which
     * every layer of NB > 1 has). */
    const size_t over = (size_t)(8 - tail);
    const size_t masked_rows = over == 0 ? 0 : over <= ldb ? 1 : (over + ldb - 1) / ldb;
    const size_t whole = K > masked_rows ? K - masked_rows : 0;
    __m256 a0, a1 = _mm256_setzero_ps(), a2 = a1, a3 = a1, a4 = a1, a5 = a1, a6 = a1, a7 = a1;
    size_t k;
#define PC_LOAD_BLOCK(p, j, last_masked)                                                  \
    ((last_masked) && (j) == NB - 1 ? _mm256_maskload_ps((p) + 8 * (j), mask)             \
                                    : _mm256_loadu_ps((p) + 8 * (j)))
#define PC_ACC(j, b, last_masked)                                                         \
    if (NB > (j)) a##j = _mm256_add_ps(a##j, _mm256_mul_ps(av, PC_LOAD_BLOCK(b, j, last_masked)))
#define PC_ROW(k, last_masked)                                                            \
    do {                                                                                  \
        const __m256 av = _mm256_broadcast_ss(a + (k));                                   \
        const float *b = B + (k) * ldb;                                                   \
        PC_ACC(0, b, last_masked);                                                        \
        PC_ACC(1, b, last_masked);                                                        \
        PC_ACC(2, b, last_masked);                                                        \
        PC_ACC(3, b, last_masked);                                                        \
        PC_ACC(4, b, last_masked);                                                        \
        PC_ACC(5, b, last_masked);                                                        \
        PC_ACC(6, b, last_masked);                                                        \
        PC_ACC(7, b, last_masked);                                                        \
    } while (0)
#define PC_EACH(X) X(0) X(1) X(2) X(3) X(4) X(5) X(6) X(7)
#define PC_INIT(j) if (NB > (j)) a##j = PC_LOAD_BLOCK(C, j, 1);
    PC_EACH(PC_INIT)
#undef PC_INIT
    /* four rows a turn: a quarter of the loop's bookkeeping, the same order per lane */
    for (k = 0; k + 4 <= whole; k += 4) {
        PC_ROW(k, 0);
        PC_ROW(k + 1, 0);
        PC_ROW(k + 2, 0);
        PC_ROW(k + 3, 0);
    }
    for (; k < whole; k++)
        PC_ROW(k, 0);
    for (; k < K; k++)
        PC_ROW(k, 1);
#undef PC_ROW
#undef PC_ACC
#undef PC_LOAD_BLOCK
    if (tanh_act) {
#define PC_TANH(j) if (NB > (j)) a##j = pc_tanh8(a##j);
        PC_EACH(PC_TANH)
#undef PC_TANH
    }
    /* Whole blocks, then the last block's lanes in pieces: a masked store costs more than
     * the whole layer's tail, and the next layer's loads would wait behind it. */
#define PC_STORE(j) if (NB > (j) + 1) _mm256_storeu_ps(O + 8 * (j), a##j);
    PC_EACH(PC_STORE)
#undef PC_STORE
#undef PC_EACH
    pc_store_lanes(O + 8 * (NB - 1),
                   NB == 1 ? a0 : NB == 2 ? a1 : NB == 3 ? a2 : NB == 4 ? a3 :
                   NB == 5 ? a4 : NB == 6 ? a5 : NB == 7 ? a6 : a7, tail);
}

__attribute__((target("avx2"), noinline)) static void pc_layer_rows_avx2(const pc_gemm *q,
                                                                         void *const *io)
{
    pc_gemm_rows(q, io);
}

__attribute__((target("avx2"))) static pc_status k_gemm_rows_avx2(const pc_step *s)
{
    pc_layer_rows_avx2((const pc_gemm *)s->prm, s->io);
    return PC_OK;
}

/* Any activation but tanh on a one-pose layer's outputs, after the store, lane by lane:
 * expf (sigmoid, radbas) has no eight-lane form with libm's bits, and the others are
 * rare enough that the portable layer's forms serve. Out of line: inlined, its loops
 * cost every layer a stack frame (17 instructions a layer, callgrind). */
PC_NOINLINE static void pc_act_lanes(const pc_gemm *l, float *O)
{
    pc_apply_act(l, O, l->N);
}

PC_AVX2_INLINE void pc_act_after(const pc_gemm *l, float *O)
{
    if (l->act != PC_ACT_TANH && l->act != PC_ACT_NONE)
        pc_act_lanes(l, O);
}

/* The block kernel for any K and N: its outputs in groups of PC_MAX_BLOCKS blocks of 8,
 * each group in one pass on k (a pose's layer is bound by the latency of its chains of
 * additions: one pass for all the blocks overlaps them). */
PC_AVX2_INLINE void pc_layer1_any(const float *a, const float *B, size_t K, size_t N,
                                  const float *C, int tanh_act, float *O)
{
    size_t n0;
    for (n0 = 0; n0 < N; n0 += 8 * PC_MAX_BLOCKS) {
        const size_t w = N - n0 < 8 * PC_MAX_BLOCKS ? N - n0 : 8 * PC_MAX_BLOCKS;
        switch ((w + 7) / 8) {
#define PC_BLOCKS_CASE(NB)                                                                     \
    case NB: pc_layer1_blocks(a, B + n0, N, K, w, C + n0, tanh_act, O + n0, NB); break;
            PC_BLOCKS_CASE(1)
            PC_BLOCKS_CASE(2)
            PC_BLOCKS_CASE(3)
            PC_BLOCKS_CASE(4)
            PC_BLOCKS_CASE(5)
            PC_BLOCKS_CASE(6)
            PC_BLOCKS_CASE(7)
            default: pc_layer1_blocks(a, B + n0, N, K, w, C + n0, tanh_act, O + n0, 8); break;
#undef PC_BLOCKS_CASE
        }
    }
}

/* A one-pose layer (a bias row, any activation: every layer the planner chains) runs in
 * registers with K and N read at run time; more rows would be the rows kernel (a call:
 * inlined, its loops would take the registers the block accumulators need). */
__attribute__((target("avx2"), noinline)) static void pc_chain_layer_avx2(const pc_gemm *l,
                                                                          void *const *io)
{
    const int tanh_act = l->act == PC_ACT_TANH;
    if (l->M != 1 || l->N == 0) {
        pc_layer_rows_avx2(l, io);
        return;
    }
    pc_layer1_any((const float *)io[0], (const float *)io[1], l->K, l->N,
                  (const float *)io[2], tanh_act, (float *)io[3]);
    pc_act_after(l, (float *)io[3]);
}

/* Specialised one-pose layers: one function per (K, N) of the layers the project trains
 * (PC_LAYER_SIZES: the pose vectors of the representations and table 1's hidden widths),
 * the same code for every model with such a layer. With K and N constants the row loop
 * unrolls and every address is a constant offset: about a third fewer instructions than
 * pc_chain_layer_avx2, the same operations in the same order (the same bits). */
#define PC_LAYER_SPECIALISED(K, N)                                                             \
    __attribute__((target("avx2"), hot)) static void pc_layer_##K##_##N(const pc_gemm *l,      \
                                                                        void *const *io)       \
    {                                                                                          \
        pc_layer1_blocks((const float *)io[0], (const float *)io[1], N, K, N,                  \
                         (const float *)io[2], l->act == PC_ACT_TANH, (float *)io[3],          \
                         ((N) + 7) / 8);                                                       \
        pc_act_after(l, (float *)io[3]);                                                   \
    }
PC_LAYER_SHAPES(PC_LAYER_SPECIALISED)
#undef PC_LAYER_SPECIALISED

/* One-pose layers of up to 64 outputs by their number of 8-lane blocks, K and N read at
 * run time: the planner picks the function, so the run has no branch on N left. */
#define PC_LAYER_BLOCKS(NB)                                                                    \
    __attribute__((target("avx2"), hot)) static void pc_layer_blocks_##NB(const pc_gemm *l,    \
                                                                          void *const *io)     \
    {                                                                                          \
        pc_layer1_blocks((const float *)io[0], (const float *)io[1], l->N, l->K, l->N,         \
                         (const float *)io[2], l->act == PC_ACT_TANH, (float *)io[3], NB);     \
        pc_act_after(l, (float *)io[3]);                                                   \
    }
PC_LAYER_BLOCKS(1)
PC_LAYER_BLOCKS(2)
PC_LAYER_BLOCKS(3)
PC_LAYER_BLOCKS(4)
PC_LAYER_BLOCKS(5)
PC_LAYER_BLOCKS(6)
PC_LAYER_BLOCKS(7)
PC_LAYER_BLOCKS(8)
#undef PC_LAYER_BLOCKS
static const pc_layer_fn pc_layers_by_blocks[PC_MAX_BLOCKS] = {
    pc_layer_blocks_1, pc_layer_blocks_2, pc_layer_blocks_3, pc_layer_blocks_4,
    pc_layer_blocks_5, pc_layer_blocks_6, pc_layer_blocks_7, pc_layer_blocks_8};

/* AVX2 needs the CPU flag and the OS saving YMM state (XCR0 bits 1 and 2). */
int pc_cpu_avx2(void)
{
    unsigned a, b, c, d;
    if (!__get_cpuid(1, &a, &b, &c, &d) || !(c & bit_OSXSAVE) || !(c & bit_AVX))
        return 0;
    __asm__("xgetbv" : "=a"(a), "=d"(d) : "c"(0));
    if ((a & 6) != 6)
        return 0;
    return __get_cpuid_count(7, 0, &a, &b, &c, &d) && (b & bit_AVX2);
}

const pc_kernel_fn pc_gemm_rows_kernels[2] = {k_gemm_rows, k_gemm_rows_avx2};

#define PC_LAYER_ROW(K, N) {K, N, pc_layer_##K##_##N},
#define PC_LAYERS_GENERAL {pc_layer_rows, pc_chain_layer_avx2}
#else
int pc_cpu_avx2(void)
{
    return 0;
}

const pc_kernel_fn pc_gemm_rows_kernels[2] = {k_gemm_rows, k_gemm_rows};
#define PC_LAYER_ROW(K, N)
#define PC_LAYERS_GENERAL {pc_layer_rows, pc_layer_rows}
#endif

typedef struct pc_layer_kernel {
    uint8_t K, N;
    pc_layer_fn fn;
} pc_layer_kernel;

/* The specialised layers, then an entry without a function (the only one without AVX2). */
static const pc_layer_kernel pc_layer_kernels[] = {PC_LAYER_SHAPES(PC_LAYER_ROW){0, 0, NULL}};
#undef PC_LAYER_ROW
/* The layer of any shape: [0] portable, [1] AVX2. */
static const pc_layer_fn pc_layers_general[2] = PC_LAYERS_GENERAL;
#undef PC_LAYERS_GENERAL

/* Whether n is one of PC_LAYER_SIZES. */
static int pc_layer_size(size_t n)
{
#define PC_IS_SIZE(S) n == (S) ||
    return PC_LAYER_SIZES(PC_IS_SIZE) 0;
#undef PC_IS_SIZE
}

pc_layer_fn pc_chain_layer_fn(const pc_gemm *l, int avx2, const char **why)
{
    const pc_layer_kernel *k;
    for (k = pc_layer_kernels; avx2 && l->M == 1 && k->fn; k++)
        if (k->K == l->K && k->N == l->N) {
            *why = "";
            return k->fn;
        }
    if (!pc_layer_kernels[0].fn)
        *why = "the library is built without AVX2 kernels";
    else if (!avx2)
        *why = "the CPU has no AVX2";
    else if (l->M != 1)
        *why = "more than one row";
    else if (!pc_layer_size(l->K) || !pc_layer_size(l->N))
        *why = "K or N is not a layer size the project trains (" PC_LAYER_SIZES_TEXT ")";
    else
        *why = "no specialised kernel for this pair of sizes (into a hidden width of table 1, "
               "or out of one)";
#ifdef PC_HAVE_AVX2
    if (avx2 && l->M == 1 && l->N >= 1 && l->N <= 8 * PC_MAX_BLOCKS)
        return pc_layers_by_blocks[(l->N - 1) / 8];
#endif
    return pc_layers_general[avx2 != 0];
}

const char *pc_chain_layer_why(const pc_chain_layer *l)
{
    const char *why;
    pc_chain_layer_fn(&l->g, l->fn != pc_layers_general[0], &why);
    return why;
}

PC_COLD pc_status k_matmul(const pc_step *s)
{
    const pc_gemm *q = (const pc_gemm *)s->prm;
    const float *A = (const float *)s->io[0];
    const float *B = (const float *)s->io[1];
    float *O = (float *)s->io[2];
    size_t idx[4] = {0, 0, 0, 0}, total = 1, t, j;
    for (j = 0; j < q->nbd; j++)
        total *= q->bd[j];
    for (t = 0; t < total; t++) {
        size_t ao = 0, bo = 0;
        for (j = 0; j < q->nbd; j++) {
            ao += idx[j] * q->a_bst[j];
            bo += idx[j] * q->b_bst[j];
        }
        pc_gemm_one(q, A + ao, B + bo, NULL, O + t * q->M * q->N);
        for (j = q->nbd; j-- > 0;) {
            if (++idx[j] < q->bd[j])
                break;
            idx[j] = 0;
        }
    }
    return PC_OK;
}

