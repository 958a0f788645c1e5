/* Graph IR: value table with a name index, constants, derived constants. */
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

static uint32_t pc_hash(pb_slice s)
{
    uint32_t h = 2166136261u;
    size_t i;
    for (i = 0; i < s.size; i++)
        h = (h ^ s.data[i]) * 16777619u;
    return h;
}

pc_status pc_ir_reserve(pc_builder *b, size_t cap)
{
    size_t i;
    b->cap_values = cap;
    b->values = pc_scratch_alloc_raw(&b->scratch, cap * sizeof(pc_value));
    for (b->hash_cap = 16; b->hash_cap < 2 * cap; b->hash_cap *= 2)
        ;
    b->hash = pc_scratch_alloc_raw(&b->scratch, b->hash_cap * sizeof(int32_t));
    if (!b->values || !b->hash)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < b->hash_cap; i++)
        b->hash[i] = -1;
    return PC_OK;
}

int32_t pc_lookup(const pc_builder *b, pb_slice name)
{
    size_t i = pc_hash(name) & (b->hash_cap - 1);
    while (b->hash[i] >= 0) {
        if (pb_slice_same(b->values[b->hash[i]].name, name))
            return b->hash[i];
        i = (i + 1) & (b->hash_cap - 1);
    }
    return -1;
}

static void pc_insert(pc_builder *b, int32_t id)
{
    size_t i = pc_hash(b->values[id].name) & (b->hash_cap - 1);
    while (b->hash[i] >= 0)
        i = (i + 1) & (b->hash_cap - 1);
    b->hash[i] = id;
}

pc_status pc_new_value(pc_builder *b, pb_slice name, int32_t *id)
{
    pc_value *v;
    if (b->n_values >= b->cap_values)
        return pc_fail(b->err, PC_ERR_GRAPH, "too many tensors in graph");
    v = &b->values[b->n_values];
    memset(v, 0, sizeof *v);
    v->name = name;
    v->producer = -1;
    v->alias = -1;
    v->const_slot = -1;
    *id = (int32_t)b->n_values++;
    if (name.size)
        pc_insert(b, *id);
    return PC_OK;
}

pc_status pc_alloc_const(pc_builder *b, pb_slice name, int dtype, int rank,
                         const int64_t *dims, int32_t *id)
{
    pc_value *v;
    size_t count = 1;
    int i;
    pc_status st;
    for (i = 0; i < rank; i++) {
        if (!pc_mul_count(&count, dims[i], PC_MAX_ELEMENTS))
            return pc_fail(b->err, PC_ERR_SHAPE, "constant '%.*s' has an invalid shape",
                           (int)name.size, (const char *)name.data);
    }
    if ((st = pc_new_value(b, name, id)) != PC_OK)
        return st;
    v = &b->values[*id];
    v->dtype = dtype;
    v->rank = rank;
    for (i = 0; i < rank; i++)
        v->dims[i] = dims[i];
    v->count = count;
    v->cdata = pc_scratch_alloc(&b->scratch, count * pc_dtype_size(dtype));
    if (!v->cdata)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory for constant '%.*s'",
                       (int)name.size, (const char *)name.data);
    return PC_OK;
}

int32_t pc_find_derived(const pc_builder *b, int32_t src, int kind)
{
    size_t i;
    for (i = 0; i < b->n_derived; i++)
        if (b->derived[i].src == src && b->derived[i].kind == kind)
            return b->derived[i].id;
    return -1;
}

pc_status pc_add_derived(pc_builder *b, int32_t src, int kind, int32_t id)
{
    if (b->n_derived == b->cap_derived) {
        size_t cap = b->cap_derived ? 2 * b->cap_derived : 16;
        pc_derived *d = pc_scratch_alloc(&b->scratch, cap * sizeof *d);
        if (!d)
            return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        if (b->n_derived)
            memcpy(d, b->derived, b->n_derived * sizeof *d);
        b->derived = d;
        b->cap_derived = cap;
    }
    b->derived[b->n_derived].src = src;
    b->derived[b->n_derived].kind = kind;
    b->derived[b->n_derived].id = id;
    b->n_derived++;
    return PC_OK;
}

int pc_is_output(const pc_builder *b, int32_t id)
{
    size_t i;
    for (i = 0; i < b->n_outputs; i++)
        if (b->outputs[i].id == id)
            return 1;
    return 0;
}
