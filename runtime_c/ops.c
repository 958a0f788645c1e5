/* Operators. Each ONNX operator is one prepare function in pc_ops[]: it checks input
 * types, infers output shapes, and picks a kernel specialised for the layout it sees
 * (same shape, scalar broadcast, general broadcast), with all strides precomputed into
 * a parameter block. Kernels then only loop. */
#include "pc_internal.h"

#include <float.h>
#include <math.h>
#include <string.h>

/* ---- maths ------------------------------------------------------------------------ */

float pc_tanh(float x)
{
    return pc_tanh_inline(x);
}


/* Float -> int64 without undefined behaviour for NaN or out-of-range values. */
static int64_t pc_f2i(float x)
{
    if (x != x)
        return 0;
    if (x >= 9.2233720e18f)
        return INT64_MAX;
    if (x <= -9.2233720e18f)
        return INT64_MIN;
    return (int64_t)x;
}

/* ---- broadcasting ----------------------------------------------------------------- */

#define PC_BMAX 8 /* operands of one broadcast kernel (Max/Min may take more: chained) */

typedef struct pc_bcast_n {
    size_t n_in;
    size_t d[PC_MAX_RANK];
    size_t st[PC_BMAX][PC_MAX_RANK];
} pc_bcast_n;

static pc_status pc_bcast_shape(pc_prep *p, size_t n_ops, pc_value *const *ins, int *rank,
                                int64_t *dims)
{
    size_t k;
    int r = 0, j;
    for (k = 0; k < n_ops; k++)
        if (ins[k]->rank > r)
            r = ins[k]->rank;
    for (j = 0; j < r; j++) {
        int64_t d = 1;
        for (k = 0; k < n_ops; k++) {
            const int jj = ins[k]->rank - r + j;
            const int64_t dk = jj >= 0 ? ins[k]->dims[jj] : 1;
            if (dk == 1)
                continue;
            if (d == 1)
                d = dk;
            else if (d != dk)
                return pc_prep_fail(p, PC_ERR_SHAPE,
                                    "operands cannot be broadcast together (dimension %d: %lld vs %lld)",
                                    j, (long long)d, (long long)dk);
        }
        dims[j] = d;
    }
    *rank = r;
    return PC_OK;
}

/* Coalesced strides of each operand against the output shape. Returns the layout class;
 * d/st are padded on the left to PC_MAX_RANK for the general kernels. */
static int pc_bcast_layout(size_t n_ops, pc_value *const *ins, int rank, const int64_t *dims,
                           size_t *d_out, size_t (*st_out)[PC_MAX_RANK])
{
    size_t d[PC_MAX_RANK], st[PC_BMAX][PC_MAX_RANK];
    int r = 0, j, same[PC_BMAX], scalar[PC_BMAX], all_same = 1;
    size_t k;
    /* Walk from the innermost dimension so merging is a single pass. */
    for (j = rank - 1; j >= 0; j--) {
        size_t s[PC_BMAX];
        int merge = r > 0;
        if (dims[j] == 1)
            continue;
        for (k = 0; k < n_ops; k++) {
            const pc_value *v = ins[k];
            const int jj = v->rank - rank + j;
            size_t stride = 1;
            int i;
            if (jj < 0 || v->dims[jj] == 1) {
                s[k] = 0;
            } else {
                for (i = jj + 1; i < v->rank; i++)
                    stride *= (size_t)v->dims[i];
                s[k] = stride;
            }
            if (merge && s[k] != st[k][r - 1] * d[r - 1])
                merge = 0;
        }
        if (merge) {
            d[r - 1] *= (size_t)dims[j];
        } else {
            d[r] = (size_t)dims[j];
            for (k = 0; k < n_ops; k++)
                st[k][r] = s[k];
            r++;
        }
    }
    /* d/st are innermost-first here. */
    for (k = 0; k < n_ops; k++) {
        same[k] = r == 0 || (r == 1 && st[k][0] == 1);
        scalar[k] = 1;
        for (j = 0; j < r; j++)
            if (st[k][j])
                scalar[k] = 0;
        if (!same[k])
            all_same = 0;
    }
    for (j = 0; j < PC_MAX_RANK; j++) {
        const int src = PC_MAX_RANK - 1 - j; /* innermost-first -> outermost-first */
        d_out[j] = src < r ? d[src] : 1;
        for (k = 0; k < n_ops; k++)
            st_out[k][j] = src < r ? st[k][src] : 0;
    }
    if (all_same)
        return PC_SAME;
    if (n_ops == 2 && scalar[0] && same[1])
        return PC_SCALAR_A;
    if (n_ops == 2 && same[0] && scalar[1])
        return PC_SCALAR_B;
    /* Innermost-first here: A is [M,K] contiguous, B strides (1, 0) or (0, 1). */
    if (n_ops == 2 && r == 2 && st[0][0] == 1 && st[0][1] == d[0]) {
        if (st[1][0] == 1 && st[1][1] == 0)
            return PC_ROW_B;
        if (st[1][0] == 0 && st[1][1] == 1)
            return PC_COL_B;
    }
    return r <= 2 ? PC_GENERAL2 : PC_GENERAL;
}

/* Prepares an n-ary broadcast op: output shape, layout class, params for general. */
static pc_status pc_bcast_prepare(pc_prep *p, size_t n_ops, pc_value *const *ins, int out_dtype,
                                  int *mode)
{
    int rank = 0;
    int64_t dims[PC_MAX_RANK];
    size_t d[PC_MAX_RANK], st[PC_BMAX][PC_MAX_RANK];
    pc_status st_;
    size_t k;
    if ((st_ = pc_bcast_shape(p, n_ops, ins, &rank, dims)) != PC_OK)
        return st_;
    if ((st_ = pc_set_out(p, 0, out_dtype, rank, dims)) != PC_OK)
        return st_;
    *mode = pc_bcast_layout(n_ops, ins, rank, dims, d, st);
    /* Every layout but SAME reads the strides (the general kernels serve them all). */
    if (*mode != PC_SAME && n_ops <= 3) {
        pc_bcast *q = pc_prep_params(p, sizeof *q);
        if (!q)
            return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
        memcpy(q->d, d, sizeof d);
        for (k = 0; k < n_ops; k++)
            memcpy(q->st[k], st[k], sizeof st[k]);
    }
    return PC_OK;
}

/* Integer, boolean and comparison kernels: rare on the run-time path (shape arithmetic
 * is folded at load), so one contiguous kernel and one general kernel serve all layouts. */
#define PC_BINARY(NAME, TI, TO, EXPR)                                                          \
    static PC_BINARY_SAME(NAME, TI, TO, EXPR)                                                  \
    static PC_BINARY_GEN(NAME, TI, TO, EXPR)                                                   \
    static const pc_kernel_fn NAME[PC_LAYOUTS] = {                                             \
        [PC_SAME] = NAME##_same,   [PC_SCALAR_A] = NAME##_gen, [PC_SCALAR_B] = NAME##_gen,    \
        [PC_ROW_B] = NAME##_gen,   [PC_COL_B] = NAME##_gen,    [PC_GENERAL2] = NAME##_gen,    \
        [PC_GENERAL] = NAME##_gen};

/* int64 arithmetic wraps in unsigned to stay defined; division by zero gives 0. */
PC_BINARY(k_add_i, int64_t, int64_t, (int64_t)((uint64_t)a + (uint64_t)b))
PC_BINARY(k_sub_i, int64_t, int64_t, (int64_t)((uint64_t)a - (uint64_t)b))
PC_BINARY(k_mul_i, int64_t, int64_t, (int64_t)((uint64_t)a * (uint64_t)b))
PC_BINARY(k_div_i, int64_t, int64_t, b == 0 || (b == -1 && a == INT64_MIN) ? 0 : a / b)
PC_BINARY(k_max_i, int64_t, int64_t, a > b ? a : b)
PC_BINARY(k_min_i, int64_t, int64_t, a < b ? a : b)
PC_BINARY(k_eq_f, float, uint8_t, a == b)
PC_BINARY(k_gt_f, float, uint8_t, a > b)
PC_BINARY(k_ge_f, float, uint8_t, a >= b)
PC_BINARY(k_lt_f, float, uint8_t, a < b)
PC_BINARY(k_le_f, float, uint8_t, a <= b)
PC_BINARY(k_eq_i, int64_t, uint8_t, a == b)
PC_BINARY(k_gt_i, int64_t, uint8_t, a > b)
PC_BINARY(k_ge_i, int64_t, uint8_t, a >= b)
PC_BINARY(k_lt_i, int64_t, uint8_t, a < b)
PC_BINARY(k_le_i, int64_t, uint8_t, a <= b)
PC_BINARY(k_eq_b, uint8_t, uint8_t, a == b)
PC_BINARY(k_and_b, uint8_t, uint8_t, a && b)
PC_BINARY(k_or_b, uint8_t, uint8_t, a || b)

static pc_status pc_binary(pc_prep *p, const pc_kernel_fn *kf, const pc_kernel_fn *ki,
                           const pc_kernel_fn *kb, int out_bool)
{
    const pc_kernel_fn *set;
    int mode, dt;
    pc_status st;
    if (p->n_in != 2 || !p->in[0] || !p->in[1] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 2 inputs and 1 output");
    dt = p->in[0]->dtype;
    if (p->in[1]->dtype != dt)
        return pc_prep_fail(p, PC_ERR_SHAPE, "input types differ (%s, %s)", pc_dtype_name(dt),
                            pc_dtype_name(p->in[1]->dtype));
    set = dt == PC_F32 ? kf : dt == PC_I64 ? ki : kb;
    if (!set)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "input type %s is not supported",
                            pc_dtype_name(dt));
    if ((st = pc_bcast_prepare(p, 2, p->in, out_bool ? PC_BOOL : dt, &mode)) != PC_OK)
        return st;
    p->fn = set[mode];
    return PC_OK;
}

static pc_status pc_op_Add(pc_prep *p) { return pc_binary(p, k_add_f, k_add_i, NULL, 0); }
static pc_status pc_op_Sub(pc_prep *p) { return pc_binary(p, k_sub_f, k_sub_i, NULL, 0); }
static pc_status pc_op_Mul(pc_prep *p) { return pc_binary(p, k_mul_f, k_mul_i, NULL, 0); }
static pc_status pc_op_Div(pc_prep *p) { return pc_binary(p, k_div_f, k_div_i, NULL, 0); }
static pc_status pc_op_Equal(pc_prep *p) { return pc_binary(p, k_eq_f, k_eq_i, k_eq_b, 1); }
static pc_status pc_op_Greater(pc_prep *p) { return pc_binary(p, k_gt_f, k_gt_i, NULL, 1); }
static pc_status pc_op_GreaterOrEqual(pc_prep *p) { return pc_binary(p, k_ge_f, k_ge_i, NULL, 1); }
static pc_status pc_op_Less(pc_prep *p) { return pc_binary(p, k_lt_f, k_lt_i, NULL, 1); }
static pc_status pc_op_LessOrEqual(pc_prep *p) { return pc_binary(p, k_le_f, k_le_i, NULL, 1); }
static pc_status pc_op_And(pc_prep *p) { return pc_binary(p, NULL, NULL, k_and_b, 1); }
static pc_status pc_op_Or(pc_prep *p) { return pc_binary(p, NULL, NULL, k_or_b, 1); }

/* Max/Min with more than two operands: out = op(in0, in1, ...) in one pass per operand. */
#define PC_MINMAX_N(NAME, T, CMP)                                                              \
    static pc_status NAME(const pc_step *s)                                                    \
    {                                                                                          \
        const pc_bcast_n *q = (const pc_bcast_n *)s->prm;                                      \
        T *O = (T *)s->io[q->n_in];                                                            \
        size_t k;                                                                              \
        for (k = 0; k < q->n_in; k++) {                                                        \
            const T *A = (const T *)s->io[k];                                                  \
            pc_bcast one;                                                                      \
            memcpy(one.d, q->d, sizeof one.d);                                                 \
            memcpy(one.st[0], q->st[k], sizeof one.st[0]);                                     \
            PC_FOR6(&one, 1, {                                                                 \
                const T a = A[base[0] + i5 * one.st[0][5]];                                    \
                if (k == 0 || a != a || (a CMP O[o]))                                          \
                    O[o] = a;                                                                  \
            });                                                                                \
        }                                                                                      \
        return PC_OK;                                                                          \
    }
PC_MINMAX_N(k_max_nf, float, >)
PC_MINMAX_N(k_min_nf, float, <)
PC_MINMAX_N(k_max_ni, int64_t, >)
PC_MINMAX_N(k_min_ni, int64_t, <)

static pc_status pc_minmax(pc_prep *p, const pc_kernel_fn *kf, const pc_kernel_fn *ki,
                           pc_kernel_fn nf, pc_kernel_fn ni)
{
    size_t k;
    int mode;
    pc_status st;
    if (p->n_in < 1 || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs at least one input");
    for (k = 0; k < p->n_in; k++)
        if (!p->in[k] || p->in[k]->dtype != p->in[0]->dtype)
            return pc_prep_fail(p, PC_ERR_SHAPE, "inputs must all be present and of one type");
    if (p->in[0]->dtype != PC_F32 && p->in[0]->dtype != PC_I64)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "type %s not supported",
                            pc_dtype_name(p->in[0]->dtype));
    if (p->n_in == 1) {
        p->alias_of = p->in_ids[0];
        return pc_set_out(p, 0, p->in[0]->dtype, p->in[0]->rank, p->in[0]->dims);
    }
    if (p->n_in == 2)
        return pc_binary(p, kf, ki, NULL, 0);
    if (p->n_in > PC_BMAX)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "more than %d inputs", PC_BMAX);
    if ((st = pc_bcast_prepare(p, p->n_in, p->in, p->in[0]->dtype, &mode)) != PC_OK)
        return st;
    {
        /* The n-ary kernel always reads the n-operand parameter block. */
        pc_bcast_n *q = pc_prep_params(p, sizeof *q);
        if (!q)
            return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
        q->n_in = p->n_in;
        pc_bcast_layout(p->n_in, p->in, p->out[0]->rank, p->out[0]->dims, q->d, q->st);
    }
    p->fn = p->in[0]->dtype == PC_F32 ? nf : ni;
    return PC_OK;
}

static pc_status pc_op_Max(pc_prep *p) { return pc_minmax(p, k_max_f, k_max_i, k_max_nf, k_max_ni); }
static pc_status pc_op_Min(pc_prep *p) { return pc_minmax(p, k_min_f, k_min_i, k_min_nf, k_min_ni); }

/* ---- Where ------------------------------------------------------------------------ */

#define PC_WHERE_BCAST(NAME, T)                                                                \
    static pc_status NAME##_gen2(const pc_step *s)                                             \
    {                                                                                          \
        const pc_bcast *q = (const pc_bcast *)s->prm;                                          \
        const uint8_t *C = (const uint8_t *)s->io[0];                                          \
        const T *X = (const T *)s->io[1];                                                      \
        const T *Y = (const T *)s->io[2];                                                      \
        T *O = (T *)s->io[3];                                                                  \
        size_t i4, i5;                                                                         \
        for (i4 = 0; i4 < q->d[4]; i4++) {                                                     \
            const uint8_t *c4 = C + i4 * q->st[0][4];                                          \
            const T *x4 = X + i4 * q->st[1][4];                                                \
            const T *y4 = Y + i4 * q->st[2][4];                                                \
            for (i5 = 0; i5 < q->d[5]; i5++)                                                   \
                *O++ = c4[i5 * q->st[0][5]] ? x4[i5 * q->st[1][5]] : y4[i5 * q->st[2][5]];     \
        }                                                                                      \
        return PC_OK;                                                                          \
    }                                                                                          \
    static pc_status NAME##_gen(const pc_step *s)                                              \
    {                                                                                          \
        const pc_bcast *q = (const pc_bcast *)s->prm;                                          \
        const uint8_t *C = (const uint8_t *)s->io[0];                                          \
        const T *X = (const T *)s->io[1];                                                      \
        const T *Y = (const T *)s->io[2];                                                      \
        T *O = (T *)s->io[3];                                                                  \
        PC_FOR6(q, 3, {                                                                        \
            O[o] = C[base[0] + i5 * q->st[0][5]] ? X[base[1] + i5 * q->st[1][5]]               \
                                                 : Y[base[2] + i5 * q->st[2][5]];              \
        });                                                                                    \
        return PC_OK;                                                                          \
    }

/* The float SAME kernel is in kernels.c. */
static PC_WHERE_SAME(k_where_i, int64_t)
static PC_WHERE_SAME(k_where_b, uint8_t)
PC_WHERE_BCAST(k_where_f, float)
PC_WHERE_BCAST(k_where_i, int64_t)
PC_WHERE_BCAST(k_where_b, uint8_t)

static pc_status pc_op_Where(pc_prep *p)
{
    int mode, dt;
    pc_status st;
    if (p->n_in != 3 || !p->in[0] || !p->in[1] || !p->in[2] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 3 inputs and 1 output");
    dt = p->in[1]->dtype;
    if (p->in[0]->dtype != PC_BOOL || p->in[2]->dtype != dt)
        return pc_prep_fail(p, PC_ERR_SHAPE, "needs a bool condition and two inputs of one type");
    if ((st = pc_bcast_prepare(p, 3, p->in, dt, &mode)) != PC_OK)
        return st;
    if (mode == PC_SAME)
        p->fn = dt == PC_F32 ? k_where_f_same : dt == PC_I64 ? k_where_i_same : k_where_b_same;
    else if (mode == PC_GENERAL2)
        p->fn = dt == PC_F32 ? k_where_f_gen2 : dt == PC_I64 ? k_where_i_gen2 : k_where_b_gen2;
    else
        p->fn = dt == PC_F32 ? k_where_f_gen : dt == PC_I64 ? k_where_i_gen : k_where_b_gen;
    return PC_OK;
}

/* ---- unary ------------------------------------------------------------------------ */

static PC_UNARY(k_abs_i, int64_t, int64_t, a < 0 ? (int64_t)(0 - (uint64_t)a) : a)
static PC_UNARY(k_neg_i, int64_t, int64_t, (int64_t)(0 - (uint64_t)a))
static PC_UNARY(k_relu_i, int64_t, int64_t, a > 0 ? a : 0)
static PC_UNARY(k_not_b, uint8_t, uint8_t, !a)
static PC_UNARY(k_cast_fb, float, uint8_t, a != 0.0f)
static PC_UNARY(k_cast_fi, float, int64_t, pc_f2i(a))
static PC_UNARY(k_cast_bf, uint8_t, float, a ? 1.0f : 0.0f)
static PC_UNARY(k_cast_bi, uint8_t, int64_t, a ? 1 : 0)
static PC_UNARY(k_cast_if, int64_t, float, (float)a)
static PC_UNARY(k_cast_ib, int64_t, uint8_t, a != 0)

static pc_status pc_unary(pc_prep *p, pc_kernel_fn kf, pc_kernel_fn ki, pc_kernel_fn kb)
{
    const pc_value *a;
    int dt;
    if (p->n_in != 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 1 input and 1 output");
    a = p->in[0];
    dt = a->dtype;
    p->fn = dt == PC_F32 ? kf : dt == PC_I64 ? ki : kb;
    if (!p->fn)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "input type %s is not supported",
                            pc_dtype_name(dt));
    return pc_set_out(p, 0, dt, a->rank, a->dims);
}

static pc_status pc_op_Abs(pc_prep *p) { return pc_unary(p, k_abs_f, k_abs_i, NULL); }
static pc_status pc_op_Neg(pc_prep *p) { return pc_unary(p, k_neg_f, k_neg_i, NULL); }
static pc_status pc_op_Atan(pc_prep *p) { return pc_unary(p, k_atan_f, NULL, NULL); }
static pc_status pc_op_Cos(pc_prep *p) { return pc_unary(p, k_cos_f, NULL, NULL); }
static pc_status pc_op_Sin(pc_prep *p) { return pc_unary(p, k_sin_f, NULL, NULL); }
static pc_status pc_op_Tan(pc_prep *p) { return pc_unary(p, k_tan_f, NULL, NULL); }
static pc_status pc_op_Exp(pc_prep *p) { return pc_unary(p, k_exp_f, NULL, NULL); }
static pc_status pc_op_Sqrt(pc_prep *p) { return pc_unary(p, k_sqrt_f, NULL, NULL); }
static pc_status pc_op_Relu(pc_prep *p) { return pc_unary(p, k_relu_f, k_relu_i, NULL); }
static pc_status pc_op_Sigmoid(pc_prep *p) { return pc_unary(p, k_sigmoid_f, NULL, NULL); }
static pc_status pc_op_Tanh(pc_prep *p) { return pc_unary(p, k_tanh_f, NULL, NULL); }
static pc_status pc_op_Not(pc_prep *p) { return pc_unary(p, NULL, NULL, k_not_b); }

typedef struct pc_clip {
    float lo, hi;
} pc_clip;

static pc_status k_clip_f(const pc_step *s)
{
    const pc_clip *q = (const pc_clip *)s->prm;
    const float *restrict A = (const float *)s->io[0];
    float *restrict O = (float *)s->io[s->prm ? 3 : 1];
    const float lo = q->lo, hi = q->hi;
    size_t i;
    for (i = 0; i < s->n; i++) {
        const float a = A[i];
        O[i] = a < lo ? lo : a > hi ? hi : a;
    }
    return PC_OK;
}

static pc_status pc_op_Clip(pc_prep *p)
{
    pc_clip *q;
    pc_status st;
    if (p->n_in < 1 || !p->in[0] || p->in[0]->dtype != PC_F32 || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "needs one float input");
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    q->lo = -FLT_MAX;
    q->hi = FLT_MAX;
    if (p->n_in > 1 && p->in[1] && (st = pc_input_float_scalar(p, 1, &q->lo)) != PC_OK)
        return st;
    if (p->n_in > 2 && p->in[2] && (st = pc_input_float_scalar(p, 2, &q->hi)) != PC_OK)
        return st;
    /* The kernel finds its output after the three (possibly absent) input slots. */
    if (p->n_in != 3) {
        int32_t *ids = pc_scratch_alloc(&p->b->scratch, 3 * sizeof(int32_t));
        pc_value **vs = pc_scratch_alloc(&p->b->scratch, 3 * sizeof(pc_value *));
        size_t k;
        if (!ids || !vs)
            return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
        for (k = 0; k < 3; k++) {
            ids[k] = k < p->n_in ? p->in_ids[k] : -1;
            vs[k] = k < p->n_in ? p->in[k] : NULL;
        }
        p->in_ids = ids;
        p->in = vs;
        p->n_in = 3;
    }
    p->fn = k_clip_f;
    return pc_set_out(p, 0, PC_F32, p->in[0]->rank, p->in[0]->dims);
}

static pc_status pc_op_Cast(pc_prep *p)
{
    int64_t to;
    int from, dt;
    pc_status st;
    if (p->n_in != 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 1 input and 1 output");
    if ((st = pc_attr_int(p, "to", 0, &to)) != PC_OK)
        return st;
    dt = to == 1 ? PC_F32 : to == 7 ? PC_I64 : to == 9 ? PC_BOOL : 0;
    if (!dt)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "cast to data type %lld is not supported",
                            (long long)to);
    from = p->in[0]->dtype;
    if (from == dt)
        p->alias_of = p->in_ids[0];
    else if (from == PC_F32)
        p->fn = dt == PC_BOOL ? k_cast_fb : k_cast_fi;
    else if (from == PC_BOOL)
        p->fn = dt == PC_F32 ? k_cast_bf : k_cast_bi;
    else
        p->fn = dt == PC_F32 ? k_cast_if : k_cast_ib;
    return pc_set_out(p, 0, dt, p->in[0]->rank, p->in[0]->dims);
}

/* ---- views: Identity, Reshape, Squeeze, Unsqueeze, Constant ------------------------ */

static pc_status pc_op_Identity(pc_prep *p)
{
    if (p->n_in != 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 1 input and 1 output");
    p->alias_of = p->in_ids[0];
    return pc_set_out(p, 0, p->in[0]->dtype, p->in[0]->rank, p->in[0]->dims);
}

static pc_status pc_op_Reshape(pc_prep *p)
{
    int64_t shape[PC_MAX_RANK + 1], allowzero;
    size_t n, k, known = 1;
    int infer = -1;
    const pc_value *a;
    pc_status st;
    if (p->n_in != 2 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 2 inputs and 1 output");
    a = p->in[0];
    if ((st = pc_input_ints(p, 1, shape, PC_MAX_RANK, &n)) != PC_OK)
        return st;
    if ((st = pc_attr_int(p, "allowzero", 0, &allowzero)) != PC_OK)
        return st;
    for (k = 0; k < n; k++) {
        if (shape[k] == 0 && !allowzero) {
            if ((int)k >= a->rank)
                return pc_prep_fail(p, PC_ERR_SHAPE, "shape[%zu] = 0 copies a missing dimension", k);
            shape[k] = a->dims[k];
        }
        if (shape[k] == -1) {
            if (infer >= 0)
                return pc_prep_fail(p, PC_ERR_SHAPE, "more than one -1 in shape");
            infer = (int)k;
            continue;
        }
        if (shape[k] < 0)
            return pc_prep_fail(p, PC_ERR_SHAPE, "negative dimension %lld in shape",
                                (long long)shape[k]);
        if (shape[k] > 0 && known > ((size_t)1 << 40) / (size_t)shape[k])
            return pc_prep_fail(p, PC_ERR_SHAPE, "shape too large");
        known *= (size_t)shape[k];
    }
    if (infer >= 0) {
        if (known == 0 || a->count % known)
            return pc_prep_fail(p, PC_ERR_SHAPE, "cannot infer -1 for %zu elements", a->count);
        shape[infer] = (int64_t)(a->count / known);
        known = a->count;
    }
    if (known != a->count)
        return pc_prep_fail(p, PC_ERR_SHAPE, "cannot reshape %zu elements into %zu", a->count, known);
    p->alias_of = p->in_ids[0];
    return pc_set_out(p, 0, a->dtype, (int)n, shape);
}

/* Axes from input 1 (opset 13) or the attribute (older exporters). */
static pc_status pc_axes(pc_prep *p, int64_t *axes, size_t *n, int *given)
{
    pc_status st;
    *n = 0;
    *given = 0;
    if (p->n_in > 1 && p->in[1]) {
        *given = 1;
        return pc_input_ints(p, 1, axes, PC_MAX_RANK, n);
    }
    st = pc_attr_ints(p, "axes", axes, PC_MAX_RANK, n, given);
    return st;
}

static pc_status pc_norm_axis(pc_prep *p, int64_t *axis, int rank)
{
    if (*axis < -rank || *axis >= rank)
        return pc_prep_fail(p, PC_ERR_SHAPE, "axis %lld out of range for rank %d",
                            (long long)*axis, rank);
    if (*axis < 0)
        *axis += rank;
    return PC_OK;
}

static pc_status pc_op_Squeeze(pc_prep *p)
{
    int64_t axes[PC_MAX_RANK], dims[PC_MAX_RANK];
    int drop[PC_MAX_RANK] = {0}, r = 0, j, given;
    size_t n, k;
    const pc_value *a;
    pc_status st;
    if (p->n_in < 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs an input");
    a = p->in[0];
    if ((st = pc_axes(p, axes, &n, &given)) != PC_OK)
        return st;
    if (!given || n == 0) {
        for (j = 0; j < a->rank; j++)
            drop[j] = a->dims[j] == 1;
    }
    for (k = 0; k < n; k++) {
        if ((st = pc_norm_axis(p, &axes[k], a->rank)) != PC_OK)
            return st;
        if (a->dims[axes[k]] != 1)
            return pc_prep_fail(p, PC_ERR_SHAPE, "cannot squeeze axis %lld of size %lld",
                                (long long)axes[k], (long long)a->dims[axes[k]]);
        drop[axes[k]] = 1;
    }
    for (j = 0; j < a->rank; j++)
        if (!drop[j])
            dims[r++] = a->dims[j];
    p->alias_of = p->in_ids[0];
    return pc_set_out(p, 0, a->dtype, r, dims);
}

static pc_status pc_op_Unsqueeze(pc_prep *p)
{
    int64_t axes[PC_MAX_RANK], dims[PC_MAX_RANK];
    int ins[PC_MAX_RANK] = {0}, r, j, src = 0, given;
    size_t n, k;
    const pc_value *a;
    pc_status st;
    if (p->n_in < 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs an input");
    a = p->in[0];
    if ((st = pc_axes(p, axes, &n, &given)) != PC_OK)
        return st;
    r = a->rank + (int)n;
    if (!given || r > PC_MAX_RANK)
        return pc_prep_fail(p, PC_ERR_SHAPE, "needs axes and output rank <= %d", PC_MAX_RANK);
    for (k = 0; k < n; k++) {
        if ((st = pc_norm_axis(p, &axes[k], r)) != PC_OK)
            return st;
        if (ins[axes[k]])
            return pc_prep_fail(p, PC_ERR_SHAPE, "repeated axis %lld", (long long)axes[k]);
        ins[axes[k]] = 1;
    }
    for (j = 0; j < r; j++)
        dims[j] = ins[j] ? 1 : a->dims[src++];
    p->alias_of = p->in_ids[0];
    return pc_set_out(p, 0, a->dtype, r, dims);
}

static pc_status pc_op_Constant(pc_prep *p)
{
    pb_slice tensor;
    int found, i;
    int32_t id = -1;
    void *data;
    pc_status st;
    int64_t dims[1];
    if (p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 1 output");
    if ((st = pc_attr_tensor(p, "value", &tensor, &found)) != PC_OK)
        return st;
    if (found) {
        if ((st = pc_tensor_to_const(p->b, tensor, &id)) != PC_OK)
            return st;
    } else if (pc_has_attr(p, "value_float")) {
        if ((st = pc_new_const(p, PC_F32, 0, dims, &data, &id)) != PC_OK ||
            (st = pc_attr_float(p, "value_float", 0.0f, (float *)data)) != PC_OK)
            return st;
    } else if (pc_has_attr(p, "value_int")) {
        if ((st = pc_new_const(p, PC_I64, 0, dims, &data, &id)) != PC_OK ||
            (st = pc_attr_int(p, "value_int", 0, (int64_t *)data)) != PC_OK)
            return st;
    } else if (pc_has_attr(p, "value_floats") || pc_has_attr(p, "value_ints")) {
        const int is_f = pc_has_attr(p, "value_floats");
        float fb[1];
        int64_t ib[1];
        size_t n = 0;
        /* Count first (decode into a 0-capacity buffer fails only past the count). */
        pb_slice msg;
        (void)msg;
        (void)fb;
        (void)ib;
        {
            float big_f[1024];
            int64_t big_i[1024];
            if (is_f)
                st = pc_attr_floats(p, "value_floats", big_f, 1024, &n, &found);
            else
                st = pc_attr_ints(p, "value_ints", big_i, 1024, &n, &found);
            if (st != PC_OK)
                return st;
            dims[0] = (int64_t)n;
            if ((st = pc_new_const(p, is_f ? PC_F32 : PC_I64, 1, dims, &data, &id)) != PC_OK)
                return st;
            if (n)
                memcpy(data, is_f ? (const void *)big_f : (const void *)big_i,
                       n * (is_f ? sizeof(float) : sizeof(int64_t)));
        }
    } else {
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "needs a value, value_float(s) or value_int(s)");
    }
    {
        const pc_value *v = &p->b->values[id];
        int64_t vd[PC_MAX_RANK];
        for (i = 0; i < v->rank; i++)
            vd[i] = v->dims[i];
        p->alias_of = id;
        return pc_set_out(p, 0, v->dtype, v->rank, vd);
    }
}

/* ---- strided copies: Transpose, Slice --------------------------------------------- */

#define PC_STRIDED(NAME, T)                                                                    \
    static pc_status NAME(const pc_step *s)                                                    \
    {                                                                                          \
        const pc_strided *q = (const pc_strided *)s->prm;                                      \
        const T *A = (const T *)s->io[0] + q->base;                                            \
        T *O = (T *)s->io[1];                                                       \
        size_t i0, i1, i2, i3, i4, i5, o = 0;                                                  \
        for (i0 = 0; i0 < q->d[0]; i0++)                                                       \
            for (i1 = 0; i1 < q->d[1]; i1++)                                                   \
                for (i2 = 0; i2 < q->d[2]; i2++)                                               \
                    for (i3 = 0; i3 < q->d[3]; i3++)                                           \
                        for (i4 = 0; i4 < q->d[4]; i4++) {                                     \
                            const T *a = A + (ptrdiff_t)i0 * q->st[0] +                        \
                                         (ptrdiff_t)i1 * q->st[1] + (ptrdiff_t)i2 * q->st[2] + \
                                         (ptrdiff_t)i3 * q->st[3] + (ptrdiff_t)i4 * q->st[4];  \
                            for (i5 = 0; i5 < q->d[5]; i5++)                                   \
                                O[o++] = a[(ptrdiff_t)i5 * q->st[5]];                          \
                        }                                                                      \
        return PC_OK;                                                                          \
    }
PC_STRIDED(k_strided_1, uint8_t)
PC_STRIDED(k_strided_4, uint32_t)
PC_STRIDED(k_strided_8, uint64_t)

/* Output dims + input strides (in elements), outermost first. Dimensions of size 1 are
 * dropped and mergeable neighbours merged, so most slices become one contiguous run. */
static pc_status pc_strided_prepare(pc_prep *p, int rank, const int64_t *dims,
                                    const ptrdiff_t *st, ptrdiff_t base)
{
    pc_strided *q;
    int j, r = 0;
    size_t d[PC_MAX_RANK];
    ptrdiff_t t[PC_MAX_RANK];
    pc_status s;
    const int dt = p->in[0]->dtype;
    if ((s = pc_set_out(p, 0, dt, rank, dims)) != PC_OK)
        return s;
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    for (j = 0; j < rank; j++) {
        if (dims[j] == 1)
            continue;
        if (r > 0 && t[r - 1] == st[j] * (ptrdiff_t)dims[j]) {
            d[r - 1] *= (size_t)dims[j];
            t[r - 1] = st[j];
        } else {
            d[r] = (size_t)dims[j];
            t[r] = st[j];
            r++;
        }
    }
    for (j = 0; j < PC_MAX_RANK; j++) {
        const int src = j - (PC_MAX_RANK - r);
        q->d[j] = src >= 0 ? d[src] : 1;
        q->st[j] = src >= 0 ? t[src] : 0;
    }
    q->base = base;
    p->fn = pc_dtype_size(dt) == 4 ? k_strided_4 : pc_dtype_size(dt) == 8 ? k_strided_8
                                                                           : k_strided_1;
    if (pc_dtype_size(dt) == 4 && (r == 0 || (r == 1 && t[0] == 1)))
        p->fn = k_copy_4;
    else if (pc_dtype_size(dt) == 4 && r <= 2)
        p->fn = k_strided2_4;
    return PC_OK;
}

static void pc_contig_strides(const pc_value *v, ptrdiff_t *st)
{
    ptrdiff_t s = 1;
    int j;
    for (j = v->rank - 1; j >= 0; j--) {
        st[j] = s;
        s *= (ptrdiff_t)v->dims[j];
    }
}

static pc_status pc_op_Transpose(pc_prep *p)
{
    int64_t perm[PC_MAX_RANK], dims[PC_MAX_RANK];
    ptrdiff_t in_st[PC_MAX_RANK], st[PC_MAX_RANK];
    int seen[PC_MAX_RANK] = {0}, j, found;
    size_t n;
    const pc_value *a;
    pc_status s;
    if (p->n_in != 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 1 input and 1 output");
    a = p->in[0];
    if ((s = pc_attr_ints(p, "perm", perm, PC_MAX_RANK, &n, &found)) != PC_OK)
        return s;
    if (!found) {
        n = (size_t)a->rank;
        for (j = 0; j < a->rank; j++)
            perm[j] = a->rank - 1 - j;
    }
    if ((int)n != a->rank)
        return pc_prep_fail(p, PC_ERR_SHAPE, "perm has %zu entries for rank %d", n, a->rank);
    pc_contig_strides(a, in_st);
    for (j = 0; j < a->rank; j++) {
        if (perm[j] < 0 || perm[j] >= a->rank || seen[perm[j]])
            return pc_prep_fail(p, PC_ERR_SHAPE, "perm is not a permutation");
        seen[perm[j]] = 1;
        dims[j] = a->dims[perm[j]];
        st[j] = in_st[perm[j]];
    }
    return pc_strided_prepare(p, a->rank, dims, st, 0);
}

static pc_status pc_op_Slice(pc_prep *p)
{
    int64_t starts[PC_MAX_RANK], ends[PC_MAX_RANK], axes[PC_MAX_RANK], steps[PC_MAX_RANK];
    int64_t dims[PC_MAX_RANK];
    ptrdiff_t in_st[PC_MAX_RANK], st[PC_MAX_RANK], base = 0;
    size_t ns, ne, na, nst, k;
    int j, seen[PC_MAX_RANK] = {0};
    const pc_value *a;
    pc_status s;
    if (p->n_in < 3 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs data, starts and ends");
    a = p->in[0];
    if ((s = pc_input_ints(p, 1, starts, PC_MAX_RANK, &ns)) != PC_OK ||
        (s = pc_input_ints(p, 2, ends, PC_MAX_RANK, &ne)) != PC_OK)
        return s;
    if (ns != ne)
        return pc_prep_fail(p, PC_ERR_SHAPE, "starts and ends differ in length");
    na = ns;
    if (p->n_in > 3 && p->in[3]) {
        if ((s = pc_input_ints(p, 3, axes, PC_MAX_RANK, &na)) != PC_OK)
            return s;
    } else {
        for (k = 0; k < ns; k++)
            axes[k] = (int64_t)k;
    }
    nst = ns;
    if (p->n_in > 4 && p->in[4]) {
        if ((s = pc_input_ints(p, 4, steps, PC_MAX_RANK, &nst)) != PC_OK)
            return s;
    } else {
        for (k = 0; k < ns; k++)
            steps[k] = 1;
    }
    if (na != ns || nst != ns)
        return pc_prep_fail(p, PC_ERR_SHAPE, "starts, ends, axes and steps differ in length");
    pc_contig_strides(a, in_st);
    for (j = 0; j < a->rank; j++) {
        dims[j] = a->dims[j];
        st[j] = in_st[j];
    }
    for (k = 0; k < ns; k++) {
        int64_t ax = axes[k], d, b, e, stp = steps[k], len;
        if ((s = pc_norm_axis(p, &ax, a->rank)) != PC_OK)
            return s;
        if (seen[ax])
            return pc_prep_fail(p, PC_ERR_SHAPE, "repeated axis %lld", (long long)ax);
        seen[ax] = 1;
        if (stp == 0)
            return pc_prep_fail(p, PC_ERR_SHAPE, "step 0");
        d = a->dims[ax];
        b = starts[k];
        e = ends[k];
        /* A step of at least the dimension picks one element either way; clamping it
         * keeps the stride arithmetic below far from overflow. */
        if (stp > d)
            stp = d > 0 ? d : 1;
        if (stp < -d)
            stp = d > 0 ? -d : -1;
        if (b < 0)
            b = b < -d ? 0 : b + d; /* clamp before adding to avoid overflow */
        if (e < 0)
            e = e < -d ? -1 : e + d;
        if (stp > 0) {
            if (b > d) b = d;
            if (e > d) e = d;
            if (e < 0) e = 0;
            len = e > b ? (e - b + stp - 1) / stp : 0;
        } else {
            if (b > d - 1) b = d - 1;
            if (e > d - 1) e = d - 1;
            if (b < 0 && d == 0) b = 0;
            len = b > e ? (b - e + (-stp) - 1) / (-stp) : 0;
        }
        dims[ax] = len;
        if (len > 0)
            base += (ptrdiff_t)b * in_st[ax];
        st[ax] = in_st[ax] * (ptrdiff_t)stp;
    }
    p->n_in = 1; /* starts/ends/axes/steps are consumed here, not by the kernel */
    return pc_strided_prepare(p, a->rank, dims, st, base);
}

/* ---- Concat, Gather --------------------------------------------------------------- */

static pc_status pc_op_Concat(pc_prep *p)
{
    int64_t axis, dims[PC_MAX_RANK];
    size_t k, after = 1;
    int j;
    pc_concat *q;
    const pc_value *a;
    pc_status s;
    if (p->n_in < 1 || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs inputs");
    for (k = 0; k < p->n_in; k++)
        if (!p->in[k])
            return pc_prep_fail(p, PC_ERR_GRAPH, "input %zu is missing", k);
    a = p->in[0];
    if ((s = pc_attr_int(p, "axis", 0, &axis)) != PC_OK)
        return s;
    if (!pc_has_attr(p, "axis"))
        return pc_prep_fail(p, PC_ERR_MALFORMED, "axis attribute is required");
    if (a->rank == 0)
        return pc_prep_fail(p, PC_ERR_SHAPE, "cannot concatenate scalars");
    if ((s = pc_norm_axis(p, &axis, a->rank)) != PC_OK)
        return s;
    for (j = 0; j < a->rank; j++)
        dims[j] = a->dims[j];
    dims[axis] = 0;
    for (k = 0; k < p->n_in; k++) {
        const pc_value *v = p->in[k];
        if (v->dtype != a->dtype || v->rank != a->rank)
            return pc_prep_fail(p, PC_ERR_SHAPE, "input %zu differs in type or rank", k);
        for (j = 0; j < a->rank; j++)
            if (j != axis && v->dims[j] != a->dims[j])
                return pc_prep_fail(p, PC_ERR_SHAPE, "input %zu differs in dimension %d", k, j);
        dims[axis] += v->dims[axis];
    }
    for (j = (int)axis + 1; j < a->rank; j++)
        after *= (size_t)a->dims[j];
    q = pc_prep_params(p, sizeof *q + p->n_in * sizeof(size_t));
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    q->outer = 1;
    for (j = 0; j < axis; j++)
        q->outer *= (size_t)a->dims[j];
    q->n_in = p->n_in;
    q->esize = pc_dtype_size(a->dtype);
    for (k = 0; k < p->n_in; k++)
        q->inner[k] = (size_t)p->in[k]->dims[axis] * after;
    q->total = (size_t)dims[axis] * after;
    p->fn = k_concat;
    return pc_set_out(p, 0, a->dtype, a->rank, dims);
}

static pc_status k_gather(const pc_step *s)
{
    const pc_gather *q = (const pc_gather *)s->prm;
    const uint8_t *A = (const uint8_t *)s->io[0];
    const int64_t *I = (const int64_t *)s->io[1];
    uint8_t *O = (uint8_t *)s->io[2];
    const size_t chunk = q->inner * q->esize;
    size_t o, j;
    for (o = 0; o < q->outer; o++)
        for (j = 0; j < q->n_idx; j++) {
            int64_t idx = I[j];
            if (idx < 0)
                idx += (int64_t)q->len;
            if (idx < 0 || idx >= (int64_t)q->len)
                return PC_ERR_RUNTIME;
            memcpy(O, A + (o * q->len + (size_t)idx) * chunk, chunk);
            O += chunk;
        }
    return PC_OK;
}

enum { PC_DERIVED_TRANSPOSE = 1, PC_DERIVED_GATHER = 2 };

static pc_status pc_op_Gather(pc_prep *p)
{
    int64_t axis, dims[PC_MAX_RANK];
    int j, r = 0;
    pc_gather *q;
    const pc_value *a, *idx;
    pc_status s;
    if (p->n_in != 2 || !p->in[0] || !p->in[1] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs data and indices");
    a = p->in[0];
    idx = p->in[1];
    if (idx->dtype != PC_I64)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "indices must be int64");
    if ((s = pc_attr_int(p, "axis", 0, &axis)) != PC_OK ||
        (s = pc_norm_axis(p, &axis, a->rank)) != PC_OK)
        return s;
    if (a->rank - 1 + idx->rank > PC_MAX_RANK)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "output rank exceeds %d", PC_MAX_RANK);
    for (j = 0; j < axis; j++)
        dims[r++] = a->dims[j];
    for (j = 0; j < idx->rank; j++)
        dims[r++] = idx->dims[j];
    for (j = (int)axis + 1; j < a->rank; j++)
        dims[r++] = a->dims[j];
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    q->outer = 1;
    for (j = 0; j < axis; j++)
        q->outer *= (size_t)a->dims[j];
    q->len = (size_t)a->dims[axis];
    q->inner = 1;
    for (j = (int)axis + 1; j < a->rank; j++)
        q->inner *= (size_t)a->dims[j];
    q->n_idx = idx->count;
    q->esize = pc_dtype_size(a->dtype);
    p->fn = k_gather;
    if (idx->cdata) {
        /* Constant indices: normalise and range-check once, at load. */
        const int kind = PC_DERIVED_GATHER + 4 * (int)(q->len & 0xfffffff);
        int32_t id = pc_find_derived(p->b, p->in_ids[1], kind);
        size_t k;
        for (k = 0; k < idx->count; k++) {
            const int64_t v = ((const int64_t *)idx->cdata)[k];
            if (v < -(int64_t)q->len || v >= (int64_t)q->len)
                return pc_prep_fail(p, PC_ERR_SHAPE, "index %lld out of range for axis of %zu",
                                    (long long)v, q->len);
        }
        if (id < 0) {
            void *data;
            int64_t *nd;
            if ((s = pc_new_const(p, PC_I64, idx->rank, idx->dims, &data, &id)) != PC_OK ||
                (s = pc_add_derived(p->b, p->in_ids[1], kind, id)) != PC_OK)
                return s;
            nd = (int64_t *)data;
            for (k = 0; k < idx->count; k++) {
                const int64_t v = ((const int64_t *)p->b->values[p->in_ids[1]].cdata)[k];
                nd[k] = v < 0 ? v + (int64_t)q->len : v;
            }
        }
        p->in_ids[1] = id;
        p->in[1] = &p->b->values[id];
        if (q->inner == 1 && q->esize == 4)
            p->fn = k_gather_cols_4;
    }
    return pc_set_out(p, 0, a->dtype, r, dims);
}

/* ---- Gemm, MatMul ----------------------------------------------------------------- */


/* Replaces constant input k by its transpose (2-D), cached across plans. */
static pc_status pc_transposed_const(pc_prep *p, size_t k)
{
    const int32_t src = p->in_ids[k];
    int32_t id = pc_find_derived(p->b, src, PC_DERIVED_TRANSPOSE);
    pc_status s;
    if (id < 0) {
        const pc_value *v = &p->b->values[src];
        const size_t R = (size_t)v->dims[0], C = (size_t)v->dims[1];
        int64_t dims[2];
        void *data;
        size_t i, j;
        dims[0] = v->dims[1];
        dims[1] = v->dims[0];
        if ((s = pc_new_const(p, PC_F32, 2, dims, &data, &id)) != PC_OK ||
            (s = pc_add_derived(p->b, src, PC_DERIVED_TRANSPOSE, id)) != PC_OK)
            return s;
        for (i = 0; i < R; i++)
            for (j = 0; j < C; j++)
                ((float *)data)[j * R + i] = ((const float *)p->b->values[src].cdata)[i * C + j];
    }
    p->in_ids[k] = id;
    p->in[k] = &p->b->values[id];
    return PC_OK;
}

static pc_status pc_op_Gemm(pc_prep *p)
{
    int64_t ta, tb, dims[2];
    pc_gemm *q;
    const pc_value *a, *b, *c;
    pc_status s;
    if (p->n_in < 2 || !p->in[0] || !p->in[1] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs A and B");
    a = p->in[0];
    b = p->in[1];
    c = p->n_in > 2 ? p->in[2] : NULL;
    if (a->dtype != PC_F32 || b->dtype != PC_F32 || (c && c->dtype != PC_F32))
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "only float32 is supported");
    if (a->rank != 2 || b->rank != 2)
        return pc_prep_fail(p, PC_ERR_SHAPE, "A and B must be 2-D");
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    if ((s = pc_attr_int(p, "transA", 0, &ta)) != PC_OK ||
        (s = pc_attr_int(p, "transB", 0, &tb)) != PC_OK ||
        (s = pc_attr_float(p, "alpha", 1.0f, &q->alpha)) != PC_OK ||
        (s = pc_attr_float(p, "beta", 1.0f, &q->beta)) != PC_OK)
        return s;
    q->M = (size_t)(ta ? a->dims[1] : a->dims[0]);
    q->K = (size_t)(ta ? a->dims[0] : a->dims[1]);
    q->N = (size_t)(tb ? b->dims[0] : b->dims[1]);
    if ((size_t)(tb ? b->dims[1] : b->dims[0]) != q->K)
        return pc_prep_fail(p, PC_ERR_SHAPE, "inner dimensions differ (%zu vs %lld)", q->K,
                            (long long)(tb ? b->dims[1] : b->dims[0]));
    q->a_rs = ta ? 1 : q->K;
    q->a_cs = ta ? q->M : 1;
    if (tb && b->cdata) {
        /* Row-major B lets the inner loop run over contiguous outputs. */
        if ((s = pc_transposed_const(p, 1)) != PC_OK)
            return s;
        tb = 0;
    }
    q->b_rs = tb ? 1 : q->N;
    q->b_cs = tb ? q->K : 1;
    q->c_mode = 0;
    if (c) {
        const size_t cn = c->rank >= 1 ? (size_t)c->dims[c->rank - 1] : 1;
        const size_t cm = c->rank >= 2 ? (size_t)c->dims[c->rank - 2] : 1;
        if (c->rank > 2 || (cn != 1 && cn != q->N) || (cm != 1 && cm != q->M))
            return pc_prep_fail(p, PC_ERR_SHAPE, "C cannot be broadcast to [M,N]");
        q->c_mode = c->count == 1 ? 1 : cm == 1 ? 2 : cn == 1 ? 3 : 4;
        if (q->c_mode == 2 && q->N == 1)
            q->c_mode = 1;
    } else if (p->n_in < 3) {
        /* Kernel expects C in slot 2: pad the operand list. */
        int32_t *ids = pc_scratch_alloc(&p->b->scratch, 3 * sizeof(int32_t));
        pc_value **vs = pc_scratch_alloc(&p->b->scratch, 3 * sizeof(pc_value *));
        if (!ids || !vs)
            return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
        ids[0] = p->in_ids[0];
        ids[1] = p->in_ids[1];
        ids[2] = -1;
        vs[0] = p->in[0];
        vs[1] = p->in[1];
        vs[2] = NULL;
        p->in_ids = ids;
        p->in = vs;
        p->n_in = 3;
    }
    q->act = p->node->act;
    q->lo = p->node->act_lo;
    q->hi = p->node->act_hi;
    dims[0] = (int64_t)q->M;
    dims[1] = (int64_t)q->N;
    p->fn = k_gemm;
    if (!ta && !tb && q->c_mode == 2 && q->alpha == 1.0f && q->beta == 1.0f &&
        (q->act == PC_ACT_TANH || q->act == PC_ACT_NONE))
        p->fn = pc_gemm_rows_kernel(p->b);
    return pc_set_out(p, 0, PC_F32, 2, dims);
}

static pc_status pc_op_MatMul(pc_prep *p)
{
    const pc_value *a, *b;
    int64_t ad[PC_MAX_RANK], bd[PC_MAX_RANK], od[PC_MAX_RANK];
    int ar, br, r, j, nb, oa = 0, ob = 0;
    pc_gemm *q;
    if (p->n_in != 2 || !p->in[0] || !p->in[1] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 2 inputs");
    a = p->in[0];
    b = p->in[1];
    if (a->dtype != PC_F32 || b->dtype != PC_F32)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "only float32 is supported");
    if (a->rank < 1 || b->rank < 1)
        return pc_prep_fail(p, PC_ERR_SHAPE, "inputs must have rank >= 1");
    /* numpy semantics: promote 1-D operands, drop the added axes from the output. */
    ar = a->rank;
    br = b->rank;
    for (j = 0; j < ar; j++)
        ad[j] = a->dims[j];
    for (j = 0; j < br; j++)
        bd[j] = b->dims[j];
    if (ar == 1) {
        ad[1] = ad[0];
        ad[0] = 1;
        ar = 2;
        oa = 1;
    }
    if (br == 1) {
        bd[1] = 1;
        br = 2;
        ob = 1;
    }
    if (ad[ar - 1] != bd[br - 2])
        return pc_prep_fail(p, PC_ERR_SHAPE, "inner dimensions differ (%lld vs %lld)",
                            (long long)ad[ar - 1], (long long)bd[br - 2]);
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    q->M = (size_t)ad[ar - 2];
    q->K = (size_t)ad[ar - 1];
    q->N = (size_t)bd[br - 1];
    q->a_rs = q->K;
    q->a_cs = 1;
    q->b_rs = q->N;
    q->b_cs = 1;
    q->alpha = 1.0f;
    q->beta = 0.0f;
    nb = (ar > br ? ar : br) - 2;
    if (nb > 4)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "more than 4 batch dimensions");
    r = 0;
    {
        size_t ast = q->M * q->K, bst = q->K * q->N;
        size_t a_st[4], b_st[4];
        for (j = nb - 1; j >= 0; j--) {
            const int ja = ar - 2 - nb + j, jb = br - 2 - nb + j;
            const int64_t da = ja >= 0 ? ad[ja] : 1, db = jb >= 0 ? bd[jb] : 1;
            if (da != db && da != 1 && db != 1)
                return pc_prep_fail(p, PC_ERR_SHAPE, "batch dimensions cannot be broadcast");
            q->bd[j] = (size_t)(da > db ? da : db);
            if (da == 0 || db == 0)
                q->bd[j] = 0;
            a_st[j] = da == 1 ? 0 : ast;
            b_st[j] = db == 1 ? 0 : bst;
            ast *= (size_t)da;
            bst *= (size_t)db;
        }
        for (j = 0; j < nb; j++) {
            q->a_bst[j] = a_st[j];
            q->b_bst[j] = b_st[j];
            od[r++] = (int64_t)q->bd[j];
        }
        q->nbd = (size_t)nb;
        /* B shared by all batches and A contiguous: one big [M*batch, K] product. */
        {
            int b_shared = 1;
            for (j = 0; j < nb; j++)
                if (q->b_bst[j])
                    b_shared = 0;
            if (b_shared && nb > 0 && ar - 2 == nb) {
                size_t tot = 1;
                for (j = 0; j < nb; j++)
                    tot *= q->bd[j];
                q->M *= tot;
                q->nbd = 0;
            }
        }
    }
    if (!oa)
        od[r++] = ad[ar - 2];
    if (!ob)
        od[r++] = bd[br - 1];
    p->fn = k_matmul;
    return pc_set_out(p, 0, PC_F32, r, od);
}

/* ---- Softmax, ArgMax, ReduceSum, ReduceMax ---------------------------------------- */

typedef struct pc_axis3 {
    size_t outer, len, inner;
    int last;
} pc_axis3;

static void pc_split_axis(const pc_value *v, int axis, pc_axis3 *q)
{
    int j;
    q->outer = 1;
    q->inner = 1;
    for (j = 0; j < axis; j++)
        q->outer *= (size_t)v->dims[j];
    q->len = (size_t)v->dims[axis];
    for (j = axis + 1; j < v->rank; j++)
        q->inner *= (size_t)v->dims[j];
}

static pc_status k_softmax(const pc_step *s)
{
    const pc_axis3 *q = (const pc_axis3 *)s->prm;
    const float *A = (const float *)s->io[0];
    float *O = (float *)s->io[1];
    size_t o, i, k;
    for (o = 0; o < q->outer; o++)
        for (i = 0; i < q->inner; i++) {
            const float *a = A + o * q->len * q->inner + i;
            float *y = O + o * q->len * q->inner + i;
            float mx = -INFINITY, sum = 0.0f;
            for (k = 0; k < q->len; k++)
                if (a[k * q->inner] > mx)
                    mx = a[k * q->inner];
            for (k = 0; k < q->len; k++) {
                y[k * q->inner] = expf(a[k * q->inner] - mx);
                sum += y[k * q->inner];
            }
            for (k = 0; k < q->len; k++)
                y[k * q->inner] /= sum;
        }
    return PC_OK;
}

static pc_status pc_op_Softmax(pc_prep *p)
{
    int64_t axis;
    pc_axis3 *q;
    pc_status s;
    if (p->n_in != 1 || !p->in[0] || p->in[0]->dtype != PC_F32 || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "needs one float input");
    if ((s = pc_attr_int(p, "axis", -1, &axis)) != PC_OK ||
        (s = pc_norm_axis(p, &axis, p->in[0]->rank)) != PC_OK)
        return s;
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    pc_split_axis(p->in[0], (int)axis, q);
    p->fn = k_softmax;
    return pc_set_out(p, 0, PC_F32, p->in[0]->rank, p->in[0]->dims);
}

static pc_status k_argmax(const pc_step *s)
{
    const pc_axis3 *q = (const pc_axis3 *)s->prm;
    const float *A = (const float *)s->io[0];
    int64_t *O = (int64_t *)s->io[1];
    size_t o, i, k;
    for (o = 0; o < q->outer; o++)
        for (i = 0; i < q->inner; i++) {
            const float *a = A + o * q->len * q->inner + i;
            size_t best = 0;
            for (k = 1; k < q->len; k++) {
                const float v = a[k * q->inner], bv = a[best * q->inner];
                if (v > bv || (q->last && v == bv))
                    best = k;
            }
            O[o * q->inner + i] = (int64_t)best;
        }
    return PC_OK;
}

static pc_status pc_op_ArgMax(pc_prep *p)
{
    int64_t axis, keep, last, dims[PC_MAX_RANK];
    int j, r = 0;
    pc_axis3 *q;
    const pc_value *a;
    pc_status s;
    if (p->n_in != 1 || !p->in[0] || p->in[0]->dtype != PC_F32 || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "needs one float input");
    a = p->in[0];
    if ((s = pc_attr_int(p, "axis", 0, &axis)) != PC_OK ||
        (s = pc_attr_int(p, "keepdims", 1, &keep)) != PC_OK ||
        (s = pc_attr_int(p, "select_last_index", 0, &last)) != PC_OK ||
        (s = pc_norm_axis(p, &axis, a->rank)) != PC_OK)
        return s;
    if (a->dims[axis] == 0)
        return pc_prep_fail(p, PC_ERR_SHAPE, "ArgMax over an empty axis");
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    pc_split_axis(a, (int)axis, q);
    q->last = last != 0;
    for (j = 0; j < a->rank; j++) {
        if (j == axis) {
            if (keep)
                dims[r++] = 1;
        } else {
            dims[r++] = a->dims[j];
        }
    }
    p->fn = k_argmax;
    return pc_set_out(p, 0, PC_I64, r, dims);
}


#define PC_REDUCE(NAME, INIT, ACC)                                                             \
    static pc_status NAME(const pc_step *s)                                                    \
    {                                                                                          \
        const pc_reduce *q = (const pc_reduce *)s->prm;                                        \
        const float *A = (const float *)s->io[0];                                              \
        float *O = (float *)s->io[1];                                                          \
        size_t i0, i1, i2, i3, i4, i5, i = 0;                                                  \
        for (i0 = 0; i0 < s->n; i0++)                                                          \
            O[i0] = (INIT);                                                                    \
        for (i0 = 0; i0 < q->d[0]; i0++)                                                       \
            for (i1 = 0; i1 < q->d[1]; i1++)                                                   \
                for (i2 = 0; i2 < q->d[2]; i2++)                                               \
                    for (i3 = 0; i3 < q->d[3]; i3++)                                           \
                        for (i4 = 0; i4 < q->d[4]; i4++) {                                     \
                            float *o = O + i0 * q->ost[0] + i1 * q->ost[1] + i2 * q->ost[2] +  \
                                       i3 * q->ost[3] + i4 * q->ost[4];                        \
                            for (i5 = 0; i5 < q->d[5]; i5++, i++) {                            \
                                float *y = o + i5 * q->ost[5];                                 \
                                const float a = A[i];                                          \
                                ACC;                                                           \
                            }                                                                  \
                        }                                                                      \
        return PC_OK;                                                                          \
    }
PC_REDUCE(k_reduce_sum, 0.0f, *y += a)
PC_REDUCE(k_reduce_max, -INFINITY, if (a > *y || a != a) *y = a)

static pc_status pc_reduce_prepare(pc_prep *p, pc_kernel_fn fn)
{
    int64_t axes[PC_MAX_RANK], keep, noop, dims[PC_MAX_RANK];
    int red[PC_MAX_RANK] = {0}, j, r = 0, given;
    size_t n, k, ost[PC_MAX_RANK], stride = 1;
    pc_reduce *q;
    const pc_value *a;
    pc_status s;
    if (p->n_in < 1 || !p->in[0] || p->in[0]->dtype != PC_F32 || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "needs one float input");
    a = p->in[0];
    if ((s = pc_axes(p, axes, &n, &given)) != PC_OK ||
        (s = pc_attr_int(p, "keepdims", 1, &keep)) != PC_OK ||
        (s = pc_attr_int(p, "noop_with_empty_axes", 0, &noop)) != PC_OK)
        return s;
    if (n == 0 && noop) {
        p->alias_of = p->in_ids[0];
        return pc_set_out(p, 0, PC_F32, a->rank, a->dims);
    }
    for (k = 0; k < n; k++) {
        if ((s = pc_norm_axis(p, &axes[k], a->rank)) != PC_OK)
            return s;
        red[axes[k]] = 1;
    }
    if (n == 0)
        for (j = 0; j < a->rank; j++)
            red[j] = 1;
    /* Output strides for each input dimension; 0 where the dimension is reduced. */
    for (j = a->rank - 1; j >= 0; j--) {
        ost[j] = red[j] ? 0 : stride;
        if (!red[j])
            stride *= (size_t)a->dims[j];
    }
    for (j = 0; j < a->rank; j++) {
        if (red[j]) {
            if (keep)
                dims[r++] = 1;
        } else {
            dims[r++] = a->dims[j];
        }
    }
    q = pc_prep_params(p, sizeof *q);
    if (!q)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    for (j = 0; j < PC_MAX_RANK; j++) {
        const int src = j - (PC_MAX_RANK - a->rank);
        q->d[j] = src >= 0 ? (size_t)a->dims[src] : 1;
        q->ost[j] = src >= 0 ? ost[src] : 0;
    }
    p->fn = fn;
    {
        /* Trailing reduced block after a kept prefix: use the 2-level kernel. */
        int first_red = a->rank, ok = 1;
        size_t inner = 1;
        for (j = 0; j < a->rank; j++)
            if (red[j]) {
                first_red = j;
                break;
            }
        for (j = first_red; j < a->rank; j++) {
            if (!red[j])
                ok = 0;
            inner *= (size_t)a->dims[j];
        }
        if (ok && fn == k_reduce_sum && first_red < a->rank) {
            q->d[5] = inner;
            p->fn = k_reduce_sum_last;
        }
    }
    p->n_in = 1; /* axes are consumed here, not by the kernel */
    return pc_set_out(p, 0, PC_F32, r, dims);
}

static pc_status pc_op_ReduceSum(pc_prep *p) { return pc_reduce_prepare(p, k_reduce_sum); }
static pc_status pc_op_ReduceMax(pc_prep *p) { return pc_reduce_prepare(p, k_reduce_max); }

/* ---- the table -------------------------------------------------------------------- */

const pc_op_info pc_ops[PC_OP_COUNT] = {
#define PC_OP(name) [PC_OP_##name] = {#name, pc_op_##name},
#include "pc_operators.def"
#undef PC_OP
};

int pc_op_lookup(pb_slice name)
{
    int i;
    for (i = 0; i < PC_OP_COUNT; i++)
        if (pb_slice_eq(name, pc_ops[i].name))
            return i;
    return -1;
}
