/* What every operator family shares: failing with the node's name, attributes,
 * constant inputs, output shapes, parameter blocks, constants of their own. */
#include "op.h"

#include <string.h>

pc_status pc_prep_fail(pc_prep *p, pc_status st, const char *fmt, ...)
{
    char detail[PC_MESSAGE_SIZE];
    va_list ap;
    va_start(ap, fmt);
    pc_vformat(detail, sizeof detail, fmt, ap);
    va_end(ap);
    return pc_fail(p->b->err, st, "node '%.*s' (%.*s): %s", (int)p->node->name.size,
                   (const char *)p->node->name.data, (int)p->node->op_type.size,
                   (const char *)p->node->op_type.data, detail);
}

/* The attribute `name` of the node; a malformed one fails naming the node. */
static pc_status pc_attr(pc_prep *p, const char *name, onnx_attr *a, int *found)
{
    const pc_status st = onnx_attr_find(p->b, p->node, name, a, found);
    if (st != PC_OK)
        return pc_prep_fail(p, st, "%s", p->b->err->message);
    return PC_OK;
}

static pc_status pc_attr_missing(pc_prep *p, const char *name)
{
    return pc_prep_fail(p, PC_ERR_MALFORMED, "attribute '%s' has no value of the expected type",
                        name);
}

pc_status pc_attr_int(pc_prep *p, const char *name, int64_t def, int64_t *out)
{
    onnx_attr a;
    int found;
    pc_status st = pc_attr(p, name, &a, &found);
    *out = def;
    if (st != PC_OK || !found)
        return st;
    if (!a.has_i)
        return pc_attr_missing(p, name);
    *out = a.i;
    return PC_OK;
}

pc_status pc_attr_float(pc_prep *p, const char *name, float def, float *out)
{
    onnx_attr a;
    int found;
    pc_status st = pc_attr(p, name, &a, &found);
    *out = def;
    if (st != PC_OK || !found)
        return st;
    if (!a.has_f)
        return pc_attr_missing(p, name);
    *out = a.f;
    return PC_OK;
}

pc_status pc_attr_ints(pc_prep *p, const char *name, int64_t *buf, size_t cap, size_t *n,
                       int *found)
{
    onnx_attr a;
    pc_status st = pc_attr(p, name, &a, found);
    *n = 0;
    if (st != PC_OK || !*found)
        return st;
    return onnx_attr_repeated(p->b, &a, ONNX_ATTR_INTS, buf, NULL, cap, n);
}

pc_status pc_attr_floats(pc_prep *p, const char *name, float *buf, size_t cap, size_t *n,
                         int *found)
{
    onnx_attr a;
    pc_status st = pc_attr(p, name, &a, found);
    *n = 0;
    if (st != PC_OK || !*found)
        return st;
    return onnx_attr_repeated(p->b, &a, ONNX_ATTR_FLOATS, NULL, buf, cap, n);
}

size_t pc_attr_bytes(pc_prep *p, const char *name)
{
    onnx_attr a;
    int found = 0;
    return pc_attr(p, name, &a, &found) == PC_OK && found ? a.msg.size : 0;
}

pc_status pc_attr_tensor(pc_prep *p, const char *name, pb_slice *tensor, int *found)
{
    onnx_attr a;
    pc_status st = pc_attr(p, name, &a, found);
    if (st != PC_OK || !*found)
        return st;
    if (!a.has_t)
        return pc_attr_missing(p, name);
    *tensor = a.t;
    return PC_OK;
}

int pc_has_attr(pc_prep *p, const char *name)
{
    onnx_attr a;
    int found = 0;
    return onnx_attr_find(p->b, p->node, name, &a, &found) == PC_OK && found;
}
pc_status pc_input_ints(pc_prep *p, size_t k, int64_t *buf, size_t cap, size_t *n)
{
    const pc_value *v = k < p->n_in ? p->in[k] : NULL;
    size_t i;
    if (!v || !v->cdata || v->dtype != PC_I64 || v->rank > 1)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED,
                            "input %zu must be a constant 1-D int64 tensor", k);
    if (v->count > cap)
        return pc_prep_fail(p, PC_ERR_SHAPE, "input %zu has too many elements", k);
    for (i = 0; i < v->count; i++)
        buf[i] = ((const int64_t *)v->cdata)[i];
    *n = v->count;
    return PC_OK;
}

pc_status pc_input_float_scalar(pc_prep *p, size_t k, float *out)
{
    const pc_value *v = k < p->n_in ? p->in[k] : NULL;
    if (!v || !v->cdata || v->dtype != PC_F32 || v->count != 1)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "input %zu must be a constant float scalar", k);
    *out = *(const float *)v->cdata;
    return PC_OK;
}

pc_status pc_set_out(pc_prep *p, size_t k, int dtype, int rank, const int64_t *dims)
{
    pc_value *v = k < p->n_out ? p->out[k] : NULL;
    size_t count = 1;
    int i;
    if (!v)
        return PC_OK;
    if (rank < 0 || rank > PC_MAX_RANK)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "output rank %d exceeds %d", rank, PC_MAX_RANK);
    for (i = 0; i < rank; i++)
        if (dims[i] < 0 || dims[i] > (1 << 24))
            return pc_prep_fail(p, PC_ERR_SHAPE, "output dimension %d is invalid (%lld)", i,
                                (long long)dims[i]);
    for (i = 0; i < rank; i++)
        if (!pc_mul_count(&count, dims[i], (size_t)1 << 24))
            /* The batch is the first dimension of a value that holds poses: a smaller
             * max_batch may bring it within the limit, which the caller cannot tell alone. */
            return pc_prep_fail(p, PC_ERR_SHAPE, "output holds more than 2^24 elements "
                                "(dimension %d is %lld, the first %lld: the batch, where the "
                                "value holds poses; a smaller max_batch may load it)", i,
                                (long long)dims[i], (long long)dims[0]);
    v->dtype = dtype;
    v->rank = rank;
    for (i = 0; i < rank; i++)
        v->dims[i] = (int32_t)dims[i];
    v->count = count;
    return PC_OK;
}

pc_status pc_set_out_as(pc_prep *p, size_t k, int dtype, const pc_value *like)
{
    int64_t dims[PC_MAX_RANK];
    int j;
    for (j = 0; j < like->rank; j++)
        dims[j] = like->dims[j];
    return pc_set_out(p, k, dtype, like->rank, dims);
}

void *pc_prep_params(pc_prep *p, size_t size)
{
    p->prm = pc_scratch_alloc(&p->b->scratch, PC_WORK, size);
    p->prm_size = size;
    return p->prm;
}

pc_status pc_new_const(pc_prep *p, int dtype, int rank, const int64_t *dims, void **data,
                       int32_t *id)
{
    size_t count = 1;
    int i;
    for (i = 0; i < rank; i++)
        if (!pc_mul_count(&count, dims[i], PC_MAX_ELEMENTS))
            return pc_prep_fail(p, PC_ERR_SHAPE, "constant has an invalid shape");
    *data = pc_scratch_alloc(&p->b->scratch, PC_WORK, count * pc_dtype_size(dtype) + 1);
    if (!*data)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory for a constant");
    return pc_value_const(p->b, dtype, rank, dims, *data, -1, id);
}

pc_status pc_pad_inputs(pc_prep *p, size_t n)
{
    int32_t *ids;
    pc_value **vs;
    size_t k;
    if (p->n_in >= n)
        return PC_OK;
    ids = pc_scratch_alloc(&p->b->scratch, PC_WORK, n * sizeof(int32_t));
    vs = pc_scratch_alloc(&p->b->scratch, PC_WORK, n * sizeof(pc_value *));
    if (!ids || !vs)
        return pc_fail(p->b->err, PC_ERR_MEMORY, "out of memory");
    for (k = 0; k < n; k++) {
        ids[k] = k < p->n_in ? p->in_ids[k] : -1;
        vs[k] = k < p->n_in ? p->in[k] : NULL;
    }
    p->in_ids = ids;
    p->in = vs;
    p->n_in = n;
    return PC_OK;
}

pc_status pc_axes(pc_prep *p, int64_t *axes, size_t *n, int *given)
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

pc_status pc_norm_axis(pc_prep *p, int64_t *axis, int rank)
{
    if (*axis < -rank || *axis >= rank)
        return pc_prep_fail(p, PC_ERR_SHAPE, "axis %lld out of range for rank %d",
                            (long long)*axis, rank);
    if (*axis < 0)
        *axis += rank;
    return PC_OK;
}
