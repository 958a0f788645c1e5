/* Shape and data-movement operators: views (Identity, Reshape, Squeeze, Unsqueeze,
 * Constant), strided copies (Transpose, Slice), Concat and Gather. */
#include "op.h"

#include <float.h>
#include <math.h>
#include <string.h>

/* ---- views: Identity, Reshape, Squeeze, Unsqueeze, Constant ------------------------ */

pc_status pc_op_Identity(pc_prep *p)
{
    if (p->n_in != 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 1 input and 1 output");
    p->alias_of = p->in_ids[0];
    return pc_set_out_as(p, 0, p->in[0]->dtype, p->in[0]);
}

pc_status pc_op_Reshape(pc_prep *p)
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
        if (!pc_mul_count(&known, shape[k], PC_MAX_ELEMENTS))
            return pc_prep_fail(p, PC_ERR_SHAPE, "shape too large");
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

/* Squeeze and Unsqueeze: the data input and the axes. */
static pc_status pc_input_and_axes(pc_prep *p, const pc_value **a, int64_t *axes, size_t *n,
                                   int *given)
{
    if (p->n_in < 1 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs an input");
    *a = p->in[0];
    return pc_axes(p, axes, n, given);
}

pc_status pc_op_Squeeze(pc_prep *p)
{
    int64_t axes[PC_MAX_RANK], dims[PC_MAX_RANK];
    int drop[PC_MAX_RANK] = {0}, r = 0, j, given;
    size_t n, k;
    const pc_value *a;
    pc_status st;
    if ((st = pc_input_and_axes(p, &a, axes, &n, &given)) != PC_OK)
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

pc_status pc_op_Unsqueeze(pc_prep *p)
{
    int64_t axes[PC_MAX_RANK], dims[PC_MAX_RANK];
    int ins[PC_MAX_RANK] = {0}, r, j, src = 0, given;
    size_t n, k;
    const pc_value *a;
    pc_status st;
    if ((st = pc_input_and_axes(p, &a, axes, &n, &given)) != PC_OK)
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

pc_status pc_op_Constant(pc_prep *p)
{
    pb_slice tensor;
    int found, i, is_f;
    int32_t id = -1;
    void *data;
    pc_status st;
    int64_t dims[1];
    if (p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs 1 output");
    if ((st = pc_attr_tensor(p, "value", &tensor, &found)) != PC_OK)
        return st;
    if (found) {
        onnx_tensor t;
        if ((st = onnx_tensor_header(p->b, tensor, &t)) != PC_OK ||
            (st = onnx_tensor_data(p->b, tensor, &t, PC_WORK, &data)) != PC_OK ||
            (st = pc_value_const(p->b, t.dtype, (int)t.rank, t.dims, data, -1, &id)) != PC_OK)
            return st;
    } else if (pc_has_attr(p, "value_float")) {
        if ((st = pc_new_const(p, PC_F32, 0, dims, &data, &id)) != PC_OK ||
            (st = pc_attr_float(p, "value_float", 0.0f, (float *)data)) != PC_OK)
            return st;
    } else if (pc_has_attr(p, "value_int")) {
        if ((st = pc_new_const(p, PC_I64, 0, dims, &data, &id)) != PC_OK ||
            (st = pc_attr_int(p, "value_int", 0, (int64_t *)data)) != PC_OK)
            return st;
    } else if ((is_f = pc_has_attr(p, "value_floats")) || pc_has_attr(p, "value_ints")) {
        /* decoded into a buffer of the attribute's size (on the work end: a small target's
         * stack would not hold a fixed one), then shrunk to its count */
        const char *name = is_f ? "value_floats" : "value_ints";
        const size_t cap = pc_attr_bytes(p, name) + 1;
        size_t n = 0;
        if ((st = pc_new_const(p, is_f ? PC_F32 : PC_I64, 1, (dims[0] = (int64_t)cap, dims),
                               &data, &id)) != PC_OK)
            return st;
        if (is_f)
            st = pc_attr_floats(p, name, (float *)data, cap, &n, &found);
        else
            st = pc_attr_ints(p, name, (int64_t *)data, cap, &n, &found);
        if (st != PC_OK)
            return st;
        p->b->values[id].dims[0] = (int64_t)n;
        p->b->values[id].count = n;
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

/* Element e of a strided copy: its coordinates over d, through the strides. */
static void pc_select_strided(const pc_prep *p, size_t e, size_t *input, size_t *elem)
{
    const pc_strided *q = (const pc_strided *)p->prm;
    ptrdiff_t at = q->base;
    int j;
    for (j = PC_MAX_RANK - 1; j >= 0; j--) {
        at += (ptrdiff_t)(e % q->d[j]) * q->st[j];
        e /= q->d[j];
    }
    *input = 0;
    *elem = (size_t)at;
}

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
    if (dt == PC_F32) {
        p->emap = PC_EMAP_SELECT;
        p->select = pc_select_strided;
    }
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

pc_status pc_op_Transpose(pc_prep *p)
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

/* Slice's starts, ends, axes (default 0, 1, ...) and steps (default 1), all of one length
 * *n. */
static pc_status pc_slice_args(pc_prep *p, int64_t *starts, int64_t *ends, int64_t *axes,
                               int64_t *steps, size_t *n)
{
    size_t ns, ne, na, nst, k;
    pc_status s;
    if ((s = pc_input_ints(p, 1, starts, PC_MAX_RANK, &ns)) != PC_OK ||
        (s = pc_input_ints(p, 2, ends, PC_MAX_RANK, &ne)) != PC_OK)
        return s;
    if (ns != ne)
        return pc_prep_fail(p, PC_ERR_SHAPE, "starts and ends differ in length");
    na = nst = ns;
    for (k = 0; k < ns; k++) {
        axes[k] = (int64_t)k;
        steps[k] = 1;
    }
    if (p->n_in > 3 && p->in[3] && (s = pc_input_ints(p, 3, axes, PC_MAX_RANK, &na)) != PC_OK)
        return s;
    if (p->n_in > 4 && p->in[4] && (s = pc_input_ints(p, 4, steps, PC_MAX_RANK, &nst)) != PC_OK)
        return s;
    if (na != ns || nst != ns)
        return pc_prep_fail(p, PC_ERR_SHAPE, "starts, ends, axes and steps differ in length");
    *n = ns;
    return PC_OK;
}

/* One axis of length d sliced from *b to e by *stp, as numpy clamps them: returns the
 * number of elements, *b the first one's index, *stp the step. */
static int64_t pc_slice_axis(int64_t d, int64_t *b, int64_t e, int64_t *stp)
{
    /* A step of at least the dimension picks one element either way; clamping it keeps
     * the stride arithmetic far from overflow. */
    if (*stp > d)
        *stp = d > 0 ? d : 1;
    if (*stp < -d)
        *stp = d > 0 ? -d : -1;
    if (*b < 0)
        *b = *b < -d ? 0 : *b + d; /* clamp before adding to avoid overflow */
    if (e < 0)
        e = e < -d ? -1 : e + d;
    if (*stp > 0) {
        if (*b > d) *b = d;
        if (e > d) e = d;
        if (e < 0) e = 0;
        return e > *b ? (e - *b + *stp - 1) / *stp : 0;
    }
    if (*b > d - 1) *b = d - 1;
    if (e > d - 1) e = d - 1;
    if (*b < 0 && d == 0) *b = 0;
    return *b > e ? (*b - e + (-*stp) - 1) / (-*stp) : 0;
}

pc_status pc_op_Slice(pc_prep *p)
{
    int64_t starts[PC_MAX_RANK], ends[PC_MAX_RANK], axes[PC_MAX_RANK], steps[PC_MAX_RANK];
    int64_t dims[PC_MAX_RANK];
    ptrdiff_t in_st[PC_MAX_RANK], st[PC_MAX_RANK], base = 0;
    size_t ns = 0, k;
    int j, seen[PC_MAX_RANK] = {0};
    const pc_value *a;
    pc_status s;
    if (p->n_in < 3 || !p->in[0] || p->n_out != 1)
        return pc_prep_fail(p, PC_ERR_GRAPH, "needs data, starts and ends");
    a = p->in[0];
    if ((s = pc_slice_args(p, starts, ends, axes, steps, &ns)) != PC_OK)
        return s;
    pc_contig_strides(a, in_st);
    for (j = 0; j < a->rank; j++) {
        dims[j] = a->dims[j];
        st[j] = in_st[j];
    }
    for (k = 0; k < ns; k++) {
        int64_t ax = axes[k], b = starts[k], stp = steps[k], len;
        if ((s = pc_norm_axis(p, &ax, a->rank)) != PC_OK)
            return s;
        if (seen[ax])
            return pc_prep_fail(p, PC_ERR_SHAPE, "repeated axis %lld", (long long)ax);
        seen[ax] = 1;
        if (stp == 0)
            return pc_prep_fail(p, PC_ERR_SHAPE, "step 0");
        len = pc_slice_axis(a->dims[ax], &b, ends[k], &stp);
        dims[ax] = len;
        if (len > 0)
            base += (ptrdiff_t)b * in_st[ax];
        st[ax] = in_st[ax] * (ptrdiff_t)stp;
    }
    p->n_in = 1; /* starts/ends/axes/steps are consumed here, not by the kernel */
    return pc_strided_prepare(p, a->rank, dims, st, base);
}

/* ---- Concat, Gather --------------------------------------------------------------- */

static void pc_select_concat(const pc_prep *p, size_t e, size_t *input, size_t *elem)
{
    const pc_concat *q = (const pc_concat *)p->prm;
    const size_t outer = e / q->total;
    size_t at = e % q->total, k = 0;
    while (at >= q->inner[k]) {
        at -= q->inner[k];
        k++;
    }
    *input = k;
    *elem = outer * q->inner[k] + at;
}

pc_status pc_op_Concat(pc_prep *p)
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
    q->columns = q->esize == 4;
    for (k = 0; k < p->n_in; k++) {
        q->inner[k] = (size_t)p->in[k]->dims[axis] * after;
        /* Inner sizes {2, 1, 0} sum to n_in as well: only all ones are columns. */
        q->columns = q->columns && q->inner[k] == 1;
    }
    q->total = (size_t)dims[axis] * after;
    p->fn = k_concat;
    if (a->dtype == PC_F32) {
        p->emap = PC_EMAP_SELECT;
        p->select = pc_select_concat;
    }
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


/* Constant indices, checked at load: [outer, len, inner] -> [outer, n_idx, inner]. */
static void pc_select_gather(const pc_prep *p, size_t e, size_t *input, size_t *elem)
{
    const pc_gather *q = (const pc_gather *)p->prm;
    const size_t r = e % q->inner, j = (e / q->inner) % q->n_idx, o = e / q->inner / q->n_idx;
    int64_t idx = ((const int64_t *)p->in[1]->cdata)[j];
    if (idx < 0)
        idx += (int64_t)q->len;
    *input = 0;
    *elem = (o * q->len + (size_t)idx) * q->inner + r;
}

pc_status pc_op_Gather(pc_prep *p)
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
        /* Constant indices: range-checked once, at load. */
        size_t k;
        for (k = 0; k < idx->count; k++) {
            const int64_t v = ((const int64_t *)idx->cdata)[k];
            if (v < -(int64_t)q->len || v >= (int64_t)q->len)
                return pc_prep_fail(p, PC_ERR_SHAPE, "index %lld out of range for axis of %zu",
                                    (long long)v, q->len);
        }
        if (q->inner == 1 && q->esize == 4)
            p->fn = k_gather_cols_4;
        if (a->dtype == PC_F32) {
            p->emap = PC_EMAP_SELECT;
            p->select = pc_select_gather;
        }
    }
    return pc_set_out(p, 0, a->dtype, r, dims);
}
