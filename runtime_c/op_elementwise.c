/* Elementwise operators: arithmetic and comparisons with broadcasting (the layout is
 * chosen at load; the float kernels of every layout are in kernels.c, the integer and
 * boolean ones here), Where, the unary maths, Clip and Cast. */
#include "op.h"

#include <float.h>
#include <math.h>
#include <string.h>

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

/* A float operator with an element operation: one-pose programs compute it per element. */
static void pc_elementwise(pc_prep *p, int sop)
{
    p->sop = sop;
    p->emap = sop ? PC_EMAP_SOP : PC_EMAP_NONE;
}

#define PC_BMAX 8 /* operands of one broadcast kernel: a Max or Min of more is refused */

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

/* Each operand's strides against the output shape, innermost dimension first, with
 * dimensions merged where every operand steps through them as one (a single pass from the
 * innermost); size-1 dimensions dropped. Returns the number of dimensions left. */
static int pc_bcast_coalesce(size_t n_ops, pc_value *const *ins, int rank, const int64_t *dims,
                             size_t *d, size_t (*st)[PC_MAX_RANK])
{
    int r = 0, j;
    size_t k;
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
    return r;
}

/* The layout class of coalesced (innermost-first) dimensions and strides. */
static int pc_bcast_class(size_t n_ops, int r, const size_t *d, size_t (*st)[PC_MAX_RANK])
{
    int j, same[PC_BMAX], scalar[PC_BMAX], all_same = 1;
    size_t k;
    for (k = 0; k < n_ops; k++) {
        same[k] = r == 0 || (r == 1 && st[k][0] == 1);
        scalar[k] = 1;
        for (j = 0; j < r; j++)
            if (st[k][j])
                scalar[k] = 0;
        if (!same[k])
            all_same = 0;
    }
    if (all_same)
        return PC_SAME;
    if (n_ops == 2 && scalar[0] && same[1])
        return PC_SCALAR_A;
    if (n_ops == 2 && same[0] && scalar[1])
        return PC_SCALAR_B;
    /* A is [M,K] contiguous, B strides (1, 0) or (0, 1). */
    if (n_ops == 2 && r == 2 && st[0][0] == 1 && st[0][1] == d[0]) {
        if (st[1][0] == 1 && st[1][1] == 0)
            return PC_ROW_B;
        if (st[1][0] == 0 && st[1][1] == 1)
            return PC_COL_B;
    }
    return r <= 2 ? PC_GENERAL2 : PC_GENERAL;
}

/* Coalesced strides of each operand against the output shape. Returns the layout class;
 * d/st are padded on the left to PC_MAX_RANK for the general kernels. */
static int pc_bcast_layout(size_t n_ops, pc_value *const *ins, int rank, const int64_t *dims,
                           size_t *d_out, size_t (*st_out)[PC_MAX_RANK])
{
    size_t d[PC_MAX_RANK], st[PC_BMAX][PC_MAX_RANK];
    const int r = pc_bcast_coalesce(n_ops, ins, rank, dims, d, st);
    int j;
    size_t k;
    for (j = 0; j < PC_MAX_RANK; j++) {
        const int src = PC_MAX_RANK - 1 - j; /* innermost-first -> outermost-first */
        d_out[j] = src < r ? d[src] : 1;
        for (k = 0; k < n_ops; k++)
            st_out[k][j] = src < r ? st[k][src] : 0;
    }
    return pc_bcast_class(n_ops, r, d, st);
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
                           const pc_kernel_fn *kb, int out_bool, int sop)
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
    pc_elementwise(p, dt == PC_F32 ? sop : 0);
    return PC_OK;
}

pc_status pc_op_Add(pc_prep *p) { return pc_binary(p, k_add_f, k_add_i, NULL, 0, PC_SOP_ADD); }
pc_status pc_op_Sub(pc_prep *p) { return pc_binary(p, k_sub_f, k_sub_i, NULL, 0, PC_SOP_SUB); }
pc_status pc_op_Mul(pc_prep *p) { return pc_binary(p, k_mul_f, k_mul_i, NULL, 0, PC_SOP_MUL); }
pc_status pc_op_Div(pc_prep *p) { return pc_binary(p, k_div_f, k_div_i, NULL, 0, PC_SOP_DIV); }
pc_status pc_op_Equal(pc_prep *p) { return pc_binary(p, k_eq_f, k_eq_i, k_eq_b, 1, PC_SOP_EQ); }
pc_status pc_op_Greater(pc_prep *p) { return pc_binary(p, k_gt_f, k_gt_i, NULL, 1, PC_SOP_GT); }
pc_status pc_op_GreaterOrEqual(pc_prep *p) { return pc_binary(p, k_ge_f, k_ge_i, NULL, 1, PC_SOP_GE); }
pc_status pc_op_Less(pc_prep *p) { return pc_binary(p, k_lt_f, k_lt_i, NULL, 1, PC_SOP_LT); }
pc_status pc_op_LessOrEqual(pc_prep *p) { return pc_binary(p, k_le_f, k_le_i, NULL, 1, PC_SOP_LE); }
pc_status pc_op_And(pc_prep *p) { return pc_binary(p, NULL, NULL, k_and_b, 1, 0); }
pc_status pc_op_Or(pc_prep *p) { return pc_binary(p, NULL, NULL, k_or_b, 1, 0); }

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
                           pc_kernel_fn nf, pc_kernel_fn ni, int sop)
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
        return pc_set_out_as(p, 0, p->in[0]->dtype, p->in[0]);
    }
    if (p->n_in == 2)
        return pc_binary(p, kf, ki, NULL, 0, sop);
    if (p->n_in > PC_BMAX)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "more than %d inputs", PC_BMAX);
    if ((st = pc_bcast_prepare(p, p->n_in, p->in, p->in[0]->dtype, &mode)) != PC_OK)
        return st;
    {
        /* The n-ary kernel always reads the n-operand parameter block. */
        pc_bcast_n *q = pc_prep_params(p, sizeof *q);
        if (!q)
            return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
        int64_t dims[PC_MAX_RANK];
        int j;
        q->n_in = p->n_in;
        for (j = 0; j < p->out[0]->rank; j++)
            dims[j] = p->out[0]->dims[j];
        pc_bcast_layout(p->n_in, p->in, p->out[0]->rank, dims, q->d, q->st);
    }
    p->fn = p->in[0]->dtype == PC_F32 ? nf : ni;
    return PC_OK;
}

pc_status pc_op_Max(pc_prep *p) { return pc_minmax(p, k_max_f, k_max_i, k_max_nf, k_max_ni, PC_SOP_MAX); }
pc_status pc_op_Min(pc_prep *p) { return pc_minmax(p, k_min_f, k_min_i, k_min_nf, k_min_ni, PC_SOP_MIN); }

/* ---- Where ------------------------------------------------------------------------ */

#define PC_WHERE_BCAST(NAME, T)                                                                \
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

pc_status pc_op_Where(pc_prep *p)
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
    else
        p->fn = dt == PC_F32 ? k_where_f_gen : dt == PC_I64 ? k_where_i_gen : k_where_b_gen;
    pc_elementwise(p, dt == PC_F32 ? PC_SOP_WHERE : 0);
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

static pc_status pc_unary(pc_prep *p, pc_kernel_fn kf, pc_kernel_fn ki, pc_kernel_fn kb,
                          int sop)
{
    const pc_value *a;
    int dt;
    if (p->n_in != 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 1 input and 1 output");
    a = p->in[0];
    dt = a->dtype;
    p->fn = dt == PC_F32 ? kf : dt == PC_I64 ? ki : kb;
    pc_elementwise(p, dt == PC_F32 ? sop : 0);
    if (!p->fn)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "input type %s is not supported",
                            pc_dtype_name(dt));
    return pc_set_out_as(p, 0, dt, a);
}

pc_status pc_op_Abs(pc_prep *p) { return pc_unary(p, k_abs_f, k_abs_i, NULL, PC_SOP_ABS); }
pc_status pc_op_Neg(pc_prep *p) { return pc_unary(p, k_neg_f, k_neg_i, NULL, PC_SOP_NEG); }
pc_status pc_op_Atan(pc_prep *p) { return pc_unary(p, k_atan_f, NULL, NULL, PC_SOP_ATAN); }
pc_status pc_op_Cos(pc_prep *p) { return pc_unary(p, k_cos_f, NULL, NULL, PC_SOP_COS); }
pc_status pc_op_Sin(pc_prep *p) { return pc_unary(p, k_sin_f, NULL, NULL, PC_SOP_SIN); }
pc_status pc_op_Tan(pc_prep *p) { return pc_unary(p, k_tan_f, NULL, NULL, PC_SOP_TAN); }
pc_status pc_op_Exp(pc_prep *p) { return pc_unary(p, k_exp_f, NULL, NULL, PC_SOP_EXP); }
pc_status pc_op_Sqrt(pc_prep *p) { return pc_unary(p, k_sqrt_f, NULL, NULL, PC_SOP_SQRT); }
pc_status pc_op_Relu(pc_prep *p) { return pc_unary(p, k_relu_f, k_relu_i, NULL, PC_SOP_RELU); }
pc_status pc_op_Sigmoid(pc_prep *p) { return pc_unary(p, k_sigmoid_f, NULL, NULL, PC_SOP_SIGMOID); }
pc_status pc_op_Tanh(pc_prep *p) { return pc_unary(p, k_tanh_f, NULL, NULL, PC_SOP_TANH); }
pc_status pc_op_Not(pc_prep *p) { return pc_unary(p, NULL, NULL, k_not_b, 0); }

typedef struct pc_clip_range {
    float lo, hi;
} pc_clip_range;

static pc_status k_clip_f(const pc_step *s)
{
    const pc_clip_range *q = (const pc_clip_range *)s->prm;
    const float *restrict A = (const float *)s->io[0];
    float *restrict O = (float *)s->io[s->prm ? 3 : 1];
    const float lo = q->lo, hi = q->hi;
    size_t i;
    for (i = 0; i < s->n; i++)
        O[i] = pc_clip(A[i], lo, hi); /* hi when lo > hi, as ONNX says */
    return PC_OK;
}

pc_status pc_op_Clip(pc_prep *p)
{
    pc_clip_range *q;
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
    if ((st = pc_pad_inputs(p, 3)) != PC_OK)
        return st;
    p->fn = k_clip_f;
    return pc_set_out_as(p, 0, PC_F32, p->in[0]);
}

pc_status pc_op_Cast(pc_prep *p)
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
    return pc_set_out_as(p, 0, dt, p->in[0]);
}
