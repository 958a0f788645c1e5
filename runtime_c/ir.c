/* The records of a pass and the scan's constants. */
#include "ir.h"

#include <string.h>

size_t pc_dtype_size(int dtype)
{
    return dtype == PC_F32 ? 4 : dtype == PC_I64 ? 8 : dtype == PC_BOOL ? 1 : 0;
}

const char *pc_dtype_name(int dtype)
{
    return dtype == PC_F32 ? "float32" : dtype == PC_I64 ? "int64" : dtype == PC_BOOL ? "bool"
                                                                                      : "?";
}

int32_t pc_key_ordinal(const pc_builder *b, uint32_t ordinal)
{
    return (int32_t)(b->n_inits + ordinal);
}

pc_status pc_value_new(pc_builder *b, int32_t *id)
{
    size_t i;
    for (i = 0; i < b->cap_values; i++) {
        pc_value *v = &b->values[i];
        if (v->used)
            continue;
        memset(v, 0, sizeof *v);
        v->used = 1;
        v->ckey = -1;
        v->ordinal = -1;
        v->last = PC_USE_NONE;
        v->block = -1;
        *id = (int32_t)i;
        if (i >= b->values_high)
            b->values_high = i + 1;
        return PC_OK;
    }
    return pc_fail(b->err, PC_ERR_GRAPH, "more values alive at once than the scan counted (%zu)",
                   b->cap_values);
}

void pc_value_release(pc_builder *b, int32_t id)
{
    if (id >= 0 && (size_t)id < b->cap_values)
        b->values[id].used = 0;
}

pc_status pc_value_const(pc_builder *b, int dtype, int rank, const int64_t *dims, void *data,
                         int32_t key, int32_t *id)
{
    pc_value *v;
    size_t count = 1;
    int i;
    pc_status st;
    for (i = 0; i < rank; i++)
        if (!pc_mul_count(&count, dims[i], PC_MAX_ELEMENTS) || dims[i] > INT32_MAX)
            return pc_fail(b->err, PC_ERR_SHAPE, "constant has an invalid shape");
    if ((st = pc_value_new(b, id)) != PC_OK)
        return st;
    v = &b->values[*id];
    v->dtype = dtype;
    v->rank = rank;
    for (i = 0; i < rank; i++)
        v->dims[i] = (int32_t)dims[i];
    v->count = count;
    v->cdata = data;
    v->ckey = key;
    return PC_OK;
}

const pc_const *pc_const_find(const pc_builder *b, uint32_t ordinal)
{
    const pc_const *c;
    for (c = b->consts; c; c = c->next)
        if (c->ordinal == ordinal)
            return c;
    return NULL;
}

pc_status pc_const_add(pc_builder *b, uint32_t ordinal, const pc_value *like, pc_const **out)
{
    pc_const *c = pc_scratch_alloc(&b->scratch, PC_KEEP, sizeof *c);
    int i;
    if (!c || !(c->data = pc_scratch_alloc(&b->scratch, PC_KEEP,
                                           like->count * pc_dtype_size(like->dtype) + 1)))
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory for a folded constant");
    c->ordinal = ordinal;
    c->dtype = like->dtype;
    c->rank = like->rank;
    for (i = 0; i < like->rank; i++)
        c->dims[i] = like->dims[i];
    c->count = like->count;
    c->next = b->consts;
    b->consts = c;
    *out = c;
    return PC_OK;
}
