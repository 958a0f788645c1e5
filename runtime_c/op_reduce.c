/* Reductions: Softmax, ArgMax, ReduceSum, ReduceMax. */
#include "op.h"

#include <float.h>
#include <math.h>
#include <string.h>

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

pc_status pc_op_Softmax(pc_prep *p)
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
    return pc_set_out_as(p, 0, PC_F32, p->in[0]);
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

pc_status pc_op_ArgMax(pc_prep *p)
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


#define PC_REDUCE(NAME, T, INIT, ACC)                                                          \
    static pc_status NAME(const pc_step *s)                                                    \
    {                                                                                          \
        const pc_reduce *q = (const pc_reduce *)s->prm;                                        \
        const T *A = (const T *)s->io[0];                                                      \
        T *O = (T *)s->io[1];                                                                  \
        size_t i0, i1, i2, i3, i4, i5, i = 0;                                                  \
        for (i0 = 0; i0 < s->n; i0++)                                                          \
            O[i0] = (INIT);                                                                    \
        for (i0 = 0; i0 < q->d[0]; i0++)                                                       \
            for (i1 = 0; i1 < q->d[1]; i1++)                                                   \
                for (i2 = 0; i2 < q->d[2]; i2++)                                               \
                    for (i3 = 0; i3 < q->d[3]; i3++)                                           \
                        for (i4 = 0; i4 < q->d[4]; i4++) {                                     \
                            T *o = O + i0 * q->ost[0] + i1 * q->ost[1] + i2 * q->ost[2] +  \
                                       i3 * q->ost[3] + i4 * q->ost[4];                        \
                            for (i5 = 0; i5 < q->d[5]; i5++, i++) {                            \
                                T *y = o + i5 * q->ost[5];                                     \
                                const T a = A[i];                                              \
                                ACC;                                                           \
                            }                                                                  \
                        }                                                                      \
        return PC_OK;                                                                          \
    }
PC_REDUCE(k_reduce_sum, float, 0.0f, *y += a)
PC_REDUCE(k_reduce_max, float, -INFINITY, if (a > *y || a != a) *y = a)
PC_REDUCE(k_reduce_sum_i, int64_t, 0, *y = (int64_t)((uint64_t)*y + (uint64_t)a))
PC_REDUCE(k_reduce_max_i, int64_t, INT64_MIN, if (a > *y) *y = a)
PC_REDUCE(k_reduce_max_b, uint8_t, 0, *y = (uint8_t)(*y | a))

/* fn[0] float32, fn[1] int64, fn[2] bool (NULL: not defined for that type). */
static pc_status pc_reduce_prepare(pc_prep *p, const pc_kernel_fn *fns)
{
    int64_t axes[PC_MAX_RANK], keep, noop, dims[PC_MAX_RANK];
    int red[PC_MAX_RANK] = {0}, j, r = 0, given;
    size_t n, k, ost[PC_MAX_RANK], stride = 1;
    pc_reduce *q;
    const pc_value *a;
    pc_status s;
    pc_kernel_fn fn;
    if (p->n_in < 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs one input and one output");
    a = p->in[0];
    fn = fns[a->dtype == PC_F32 ? 0 : a->dtype == PC_I64 ? 1 : 2];
    if (!fn)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "no kernel for %s input",
                            pc_dtype_name(a->dtype));
    if ((s = pc_axes(p, axes, &n, &given)) != PC_OK ||
        (s = pc_attr_int(p, "keepdims", 1, &keep)) != PC_OK ||
        (s = pc_attr_int(p, "noop_with_empty_axes", 0, &noop)) != PC_OK)
        return s;
    if (n == 0 && noop) {
        p->alias_of = p->in_ids[0];
        return pc_set_out_as(p, 0, a->dtype, a);
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
            p->emap = PC_EMAP_SUM;
        }
    }
    p->n_in = 1; /* axes are consumed here, not by the kernel */
    return pc_set_out(p, 0, a->dtype, r, dims);
}

pc_status pc_op_ReduceSum(pc_prep *p)
{
    static const pc_kernel_fn fns[3] = {k_reduce_sum, k_reduce_sum_i, NULL};
    return pc_reduce_prepare(p, fns);
}

pc_status pc_op_ReduceMax(pc_prep *p)
{
    static const pc_kernel_fn fns[3] = {k_reduce_max, k_reduce_max_i, k_reduce_max_b};
    return pc_reduce_prepare(p, fns);
}
