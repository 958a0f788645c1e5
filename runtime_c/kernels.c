/* The float elementwise kernels that run on every pose: arithmetic in each broadcast
 * layout, Where, and the unary maths. Built with the vectoriser on (see CMakeLists.txt);
 * the general broadcast kernels, which only odd graphs reach, are built for size. */
#include "kernels.h"

#include <math.h>
#include <string.h>

/* One operand a single value: io[SCALAR] is it, io[ARRAY] the other. */
#define PC_SCALAR_SIDE(NAME, SUFFIX, SCALAR, ARRAY, READ, EXPR)                                \
    static pc_status NAME##SUFFIX(const pc_step *s)                                            \
    {                                                                                          \
        const float x = *(const float *)s->io[SCALAR];                                         \
        const float *restrict X = (const float *)s->io[ARRAY];                                 \
        float *restrict O = (float *)s->io[2];                                                 \
        size_t i;                                                                              \
        for (i = 0; i < s->n; i++) {                                                           \
            READ;                                                                              \
            O[i] = (EXPR);                                                                     \
        }                                                                                      \
        return PC_OK;                                                                          \
    }
/* ROW_B and COL_B are [M,K] op [K] and [M,K] op [M,1]: d[4] = M, d[5] = K; B_AT is the
 * index of b (k for a row, m for a column). */
#define PC_BLOCK_B(NAME, SUFFIX, B_AT, EXPR)                                                   \
    static pc_status NAME##SUFFIX(const pc_step *s)                                            \
    {                                                                                          \
        const pc_bcast *q = (const pc_bcast *)s->prm;                                          \
        const size_t M = q->d[4], K = q->d[5];                                                 \
        const float *restrict A = (const float *)s->io[0];                                     \
        const float *restrict B = (const float *)s->io[1];                                     \
        float *restrict O = (float *)s->io[2];                                                 \
        size_t m, k;                                                                           \
        for (m = 0; m < M; m++, A += K, O += K)                                                \
            for (k = 0; k < K; k++) {                                                          \
                const float a = A[k], b = B[B_AT];                                             \
                O[k] = (EXPR);                                                                 \
            }                                                                                  \
        return PC_OK;                                                                          \
    }

#define PC_BINARY_F(NAME, EXPR)                                                                \
    static PC_BINARY_SAME(NAME, float, float, EXPR)                                            \
    PC_SCALAR_SIDE(NAME, _sa, 0, 1, const float a = x; const float b = X[i], EXPR)             \
    PC_SCALAR_SIDE(NAME, _sb, 1, 0, const float a = X[i]; const float b = x, EXPR)             \
    PC_BLOCK_B(NAME, _row, k, EXPR)                                                            \
    PC_BLOCK_B(NAME, _col, m, EXPR)                                                            \
    PC_COLD static pc_status NAME##_gen2(const pc_step *s)                                     \
    {                                                                                          \
        const pc_bcast *q = (const pc_bcast *)s->prm;                                          \
        const float *A = (const float *)s->io[0];                                              \
        const float *B = (const float *)s->io[1];                                              \
        float *O = (float *)s->io[2];                                                          \
        size_t i4, i5;                                                                         \
        for (i4 = 0; i4 < q->d[4]; i4++) {                                                     \
            const float *a4 = A + i4 * q->st[0][4];                                            \
            const float *b4 = B + i4 * q->st[1][4];                                            \
            for (i5 = 0; i5 < q->d[5]; i5++) {                                                 \
                const float a = a4[i5 * q->st[0][5]], b = b4[i5 * q->st[1][5]];                \
                *O++ = (EXPR);                                                                 \
            }                                                                                  \
        }                                                                                      \
        return PC_OK;                                                                          \
    }                                                                                          \
    PC_COLD static PC_BINARY_GEN(NAME, float, float, EXPR)                                     \
    const pc_kernel_fn NAME[PC_LAYOUTS] = {                                                    \
        [PC_SAME] = NAME##_same, [PC_SCALAR_A] = NAME##_sa,    [PC_SCALAR_B] = NAME##_sb,      \
        [PC_ROW_B] = NAME##_row, [PC_COL_B] = NAME##_col,      [PC_GENERAL2] = NAME##_gen2,    \
        [PC_GENERAL] = NAME##_gen};

#define PC_DEFINE_BINARY(NAME, CODE, EXPR) PC_BINARY_F(NAME, EXPR)
PC_FLOAT_BINARY_OPS(PC_DEFINE_BINARY)
#undef PC_DEFINE_BINARY

PC_WHERE_SAME(k_where_f, float)

#define PC_DEFINE_UNARY(NAME, CODE, EXPR) PC_UNARY(NAME, float, float, EXPR)
PC_FLOAT_UNARY_OPS(PC_DEFINE_UNARY)
#undef PC_DEFINE_UNARY

/* One-pose plans spend more time launching small steps than computing them: their
 * element operations run here, each the same IEEE operation as its kernel. Operands are
 * byte offsets from one base, so an op costs its loads, its arithmetic and its store. */

/* A group's loop over its entries, op left past the group. */
#define PC_EACH(STMT)                                                                          \
    for (; op < last; op++) {                                                                  \
        STMT;                                                                                  \
    }
/* One case per element operation; the float arithmetic comes from the kernels' own list. */
#define PC_CASE(CODE, BODY)                                                                    \
    case CODE:                                                                                 \
        BODY break;
#define PC_BINARY_CASE(KERNEL, CODE, EXPR)                                                     \
    PC_CASE(CODE, PC_EACH(const float a = F(a); const float b = F(b); F(o) = (EXPR)))
#define PC_UNARY_CASE(KERNEL, CODE, EXPR) PC_CASE(CODE, PC_EACH(const float a = F(a); F(o) = (EXPR)))
#define PC_SOP_CASES                                                                           \
    PC_FLOAT_BINARY_OPS(PC_BINARY_CASE)                                                        \
    PC_FLOAT_UNARY_OPS(PC_UNARY_CASE)                                                          \
    PC_CASE(PC_SOP_EQ, PC_EACH(B(o) = F(a) == F(b)))                                           \
    PC_CASE(PC_SOP_GT, PC_EACH(B(o) = F(a) > F(b)))                                            \
    PC_CASE(PC_SOP_GE, PC_EACH(B(o) = F(a) >= F(b)))                                           \
    PC_CASE(PC_SOP_LT, PC_EACH(B(o) = F(a) < F(b)))                                            \
    PC_CASE(PC_SOP_LE, PC_EACH(B(o) = F(a) <= F(b)))                                           \
    PC_CASE(PC_SOP_WHERE, PC_EACH(F(o) = B(c) ? F(a) : F(b)))                                  \
    /* the bits, as the copy kernels move them */                                              \
    PC_CASE(PC_SOP_COPY, PC_EACH(memcpy(base + op->o, base + op->a, 4)))                       \
    PC_CASE(PC_SOP_COPY1, PC_EACH(B(o) = B(a)))                                                \
    /* dot products: a DOT entry and its terms */                                              \
    PC_CASE(PC_SOP_DOT, while (op < last) {                                                    \
        float acc = F(c);                                                                      \
        const int32_t o = op->o;                                                               \
        do {                                                                                   \
            acc += F(a) * F(b);                                                                \
            op++;                                                                              \
        } while (op < last && op->o == PC_TERM_MARK);                                          \
        *(float *)(base + o) = acc;                                                            \
    })

#define F(r) (*(float *)(base + op->r))
#define B(r) (*(uint8_t *)(base + op->r))
/* One dispatch per group (threaded code measured no faster: the groups' dependency
 * chains through memory, not the jumps, set the pace). */
/* One interpreter per entry width: 16-bit offsets halve a program's bytes (the usual
 * case: a one-pose plan's activations and pool span a few hundred bytes). */
#define PC_SCALAR_PROGRAM(NAME, PROGRAM, OP)                                                   \
    PC_HOT pc_status NAME(const pc_step *s)                                                    \
    {                                                                                          \
        const PROGRAM *q = (const PROGRAM *)s->prm;                                            \
        char *const base = (char *)s->io[0];                                                   \
        const OP *op = q->ops, *const end = q->ops + q->n_ops, *last;                          \
        while (op < end) {                                                                     \
            const int32_t code = op->a;                                                        \
            last = op + 1 + op->b;                                                             \
            op++;                                                                              \
            switch (code) {                                                                    \
                PC_SOP_CASES                                                                   \
            default:                                                                           \
                return PC_ERR_RUNTIME;                                                         \
            }                                                                                  \
        }                                                                                      \
        return PC_OK;                                                                          \
    }
#define PC_TERM_MARK PC_DOT_TERM
PC_SCALAR_PROGRAM(k_scalar_program, pc_scalar_program, pc_scalar_op)
#undef PC_TERM_MARK
#define PC_TERM_MARK PC_DOT_TERM16
PC_SCALAR_PROGRAM(k_scalar_program16, pc_scalar_program16, pc_scalar_op16)
#undef PC_TERM_MARK
#undef PC_SCALAR_PROGRAM
#undef F
#undef B

/* The same cases on four-byte values: slot[0..2] are a, b and c, slot[3] the result. */
uint32_t pc_sop_eval(int code, uint32_t a, uint32_t b, uint32_t c)
{
    float slot[4] = {0.0f, 0.0f, 0.0f, 0.0f};
    char *const base = (char *)slot;
    pc_scalar_op one, *op = &one;
    const pc_scalar_op *last = op + 1;
    uint32_t out = 0;
    memcpy(&slot[0], &a, 4);
    memcpy(&slot[1], &b, 4);
    memcpy(&slot[2], &c, 4);
    one.a = 0;
    one.b = 4;
    one.c = 8;
    one.o = 12;
#define PC_TERM_MARK PC_DOT_TERM
#define F(r) (*(float *)(base + op->r))
#define B(r) (*(uint8_t *)(base + op->r))
    switch (code) {
        PC_SOP_CASES
    default:
        break;
    }
#undef F
#undef B
#undef PC_TERM_MARK
    memcpy(&out, &slot[3], 4);
    return out;
}
#undef PC_EACH
#undef PC_CASE
#undef PC_BINARY_CASE
#undef PC_UNARY_CASE
#undef PC_SOP_CASES

/* ---- data movement ---------------------------------------------------------------- */

/* A contiguous run: the common "take columns a..b of one row" slice at N = 1. */
pc_status k_copy_4(const pc_step *s)
{
    const pc_strided *q = (const pc_strided *)s->prm;
    const uint32_t *restrict A = (const uint32_t *)s->io[0] + q->base;
    uint32_t *restrict O = (uint32_t *)s->io[1];
    size_t i;
    for (i = 0; i < s->n; i++)
        O[i] = A[i];
    return PC_OK;
}

/* Two-level strided copy (rows of a column block, a 2-D transpose). */
pc_status k_strided2_4(const pc_step *s)
{
    const pc_strided *q = (const pc_strided *)s->prm;
    const uint32_t *restrict A = (const uint32_t *)s->io[0] + q->base;
    uint32_t *restrict O = (uint32_t *)s->io[1];
    const size_t rows = q->d[4], cols = q->d[5];
    const ptrdiff_t rs = q->st[4], cs = q->st[5];
    size_t i4, i5;
    for (i4 = 0; i4 < rows; i4++, O += cols) {
        const uint32_t *restrict a = A + (ptrdiff_t)i4 * rs;
        for (i5 = 0; i5 < cols; i5++)
            O[i5] = a[(ptrdiff_t)i5 * cs];
    }
    return PC_OK;
}

pc_status k_concat(const pc_step *s)
{
    const pc_concat *q = (const pc_concat *)s->prm;
    const size_t n_in = q->n_in, outer = q->outer;
    uint8_t *O = (uint8_t *)s->io[n_in];
    size_t o, k;
    if (q->columns) {
        /* Columns into rows: one strided pass each. */
        for (k = 0; k < n_in; k++) {
            const float *restrict A = (const float *)s->io[k];
            float *restrict F = (float *)O + k;
            for (o = 0; o < outer; o++)
                F[o * n_in] = A[o];
        }
        return PC_OK;
    }
    for (o = 0; o < outer; o++)
        for (k = 0; k < n_in; k++) {
            const size_t bytes = q->inner[k] * q->esize;
            if (bytes)
                memcpy(O, (const uint8_t *)s->io[k] + o * bytes, bytes);
            O += bytes;
        }
    return PC_OK;
}

/* Gather of 4-byte elements along the innermost axis with constant indices, range-checked
 * at load (a negative one counts from the end): [outer, len] -> [outer, n_idx]. */
pc_status k_gather_cols_4(const pc_step *s)
{
    const pc_gather *q = (const pc_gather *)s->prm;
    const uint32_t *restrict A = (const uint32_t *)s->io[0];
    const int64_t *restrict I = (const int64_t *)s->io[1];
    uint32_t *restrict O = (uint32_t *)s->io[2];
    const size_t outer = q->outer, len = q->len, n_idx = q->n_idx;
    size_t o, j;
    if (n_idx == 1) {
        const uint32_t *restrict a = A + (I[0] < 0 ? I[0] + (int64_t)len : I[0]);
        for (o = 0; o < outer; o++)
            O[o] = a[o * len];
        return PC_OK;
    }
    for (o = 0; o < outer; o++, A += len, O += n_idx)
        for (j = 0; j < n_idx; j++)
            O[j] = A[I[j] < 0 ? I[j] + (int64_t)len : I[j]];
    return PC_OK;
}

/* Reduction of the innermost block: [outer, len] -> [outer]. Same order of summation as
 * the general kernel (memory order), so results are identical. */
pc_status k_reduce_sum_last(const pc_step *s)
{
    const pc_reduce *q = (const pc_reduce *)s->prm;
    const float *restrict A = (const float *)s->io[0];
    float *restrict O = (float *)s->io[1];
    const size_t len = q->d[5];
    size_t o, k;
    for (o = 0; o < s->n; o++, A += len) {
        float acc = 0.0f;
        for (k = 0; k < len; k++)
            acc += A[k];
        O[o] = acc;
    }
    return PC_OK;
}

float pc_tanh(float x)
{
    return pc_tanh_inline(x);
}
