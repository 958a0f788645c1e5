/* ONNX decoding, one message at a time: the model's top level, the graph's inputs and
 * outputs against the pose contract (or, for the conformance tests, static shapes), a
 * node, a tensor, an attribute. Names are matched by the scan (graph.c), operators are
 * looked at by the scan and the planner. */
#include "onnx.h"

#include <math.h>
#include <string.h>


/* ---- TensorProto ------------------------------------------------------------------ */

/* The tensor's element type, count and payload, checked against its shape before anything
 * is allocated for it. */
static pc_status onnx_tensor_check(const pc_builder *b, onnx_tensor *t)
{
    size_t k, esize, have;
    t->count = 1;
    for (k = 0; k < t->rank; k++) {
        if (!pc_mul_count(&t->count, t->dims[k], PC_MAX_ELEMENTS))
            return pc_fail(b->err, PC_ERR_MALFORMED, "tensor '%.*s' has an invalid shape",
                           PC_NAME(t->name));
    }
    switch (t->data_type) {
    case ONNX_FLOAT: t->dtype = PC_F32; break;
    case ONNX_INT32: case ONNX_INT64: t->dtype = PC_I64; break;
    case ONNX_BOOL: t->dtype = PC_BOOL; break;
    default:
        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "tensor '%.*s' has unsupported data type %lld",
                       PC_NAME(t->name), (long long)t->data_type);
    }
    esize = t->data_type == ONNX_INT32 ? 4 : pc_dtype_size(t->dtype);
    if (t->has_raw) {
        if (t->raw.size != t->count * esize)
            return pc_fail(b->err, PC_ERR_MALFORMED,
                           "tensor '%.*s': raw_data has %zu bytes, shape needs %zu",
                           PC_NAME(t->name), t->raw.size, t->count * esize);
        return PC_OK;
    }
    have = t->dtype == PC_F32 ? t->n_float : t->data_type == ONNX_INT64 ? t->n_int64 : t->n_int32;
    if (have != t->count)
        return pc_fail(b->err, PC_ERR_MALFORMED, "tensor '%.*s' has %zu values, shape needs %zu",
                       PC_NAME(t->name), have, t->count);
    return PC_OK;
}

pc_status onnx_tensor_header(const pc_builder *b, pb_slice msg, onnx_tensor *t)
{
    pb_reader r;
    pb_field f;
    pc_status st;
    size_t k, n;
    int more;
    memset(t, 0, sizeof *t);
    pb_init(&r, b->file, msg);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
        switch (f.number) {
        case ONNX_TENSOR_DIMS:
            if ((st = pb_count_packed(b->file, &f, PB_VARINT, &k, b->err)) != PC_OK)
                return st;
            if (t->rank + k > PC_MAX_RANK)
                return pc_fail(b->err, PC_ERR_UNSUPPORTED, "tensor at byte %zu has rank > %d",
                               f.offset, PC_MAX_RANK);
            n = t->rank;
            if ((st = pb_decode_repeated(b->file, &f, PB_VARINT, t->dims, NULL, PC_MAX_RANK, &n,
                                         b->err)) != PC_OK)
                return st;
            t->rank = n;
            break;
        case ONNX_TENSOR_DATA_TYPE: t->data_type = (int64_t)f.varint; break;
        case ONNX_TENSOR_FLOAT_DATA:
        case ONNX_TENSOR_INT32_DATA:
        case ONNX_TENSOR_INT64_DATA:
            st = pb_count_packed(b->file, &f, f.number == ONNX_TENSOR_FLOAT_DATA ? PB_FIXED32
                                                                                  : PB_VARINT,
                                 &k, b->err);
            if (st != PC_OK)
                return st;
            *(f.number == ONNX_TENSOR_FLOAT_DATA   ? &t->n_float
              : f.number == ONNX_TENSOR_INT32_DATA ? &t->n_int32
                                                   : &t->n_int64) += k;
            break;
        case ONNX_TENSOR_NAME: t->name = f.bytes; break;
        case ONNX_TENSOR_RAW_DATA:
            t->raw = f.bytes;
            t->has_raw = 1;
            break;
        case ONNX_TENSOR_DATA_LOCATION:
            if (f.varint == ONNX_EXTERNAL)
                return pc_fail(b->err, PC_ERR_UNSUPPORTED, "tensor '%.*s' uses external data",
                               PC_NAME(t->name));
            break;
        default: break;
        }
    }
    if (more == PB_ERROR)
        return r.status;
    return onnx_tensor_check(b, t);
}

static int onnx_host_little_endian(void)
{
    const uint16_t one = 1;
    uint8_t first;
    memcpy(&first, &one, 1);
    return first == 1;
}

/* Raw little-endian data the host reads as it lies: float32 or int64 at its alignment. */
static int onnx_in_place(const onnx_tensor *t)
{
    const size_t esize = pc_dtype_size(t->dtype);
    return onnx_host_little_endian() && t->has_raw &&
           (t->data_type == ONNX_FLOAT || t->data_type == ONNX_INT64) &&
           ((uintptr_t)t->raw.data % esize) == 0;
}

/* raw_data into the tensor's buffer: int32 widened to int64, booleans to 0 or 1, the rest
 * copied (little-endian, maybe unaligned in the file; on a big-endian host each element's
 * bytes reversed). */
static void onnx_raw_copy(const onnx_tensor *t, void *v)
{
    size_t k;
    if (t->data_type == ONNX_INT32) {
        int64_t *o = (int64_t *)v;
        for (k = 0; k < t->count; k++) {
            const uint8_t *q = t->raw.data + 4 * k;
            const uint32_t u = (uint32_t)q[0] | (uint32_t)q[1] << 8 | (uint32_t)q[2] << 16 |
                               (uint32_t)q[3] << 24;
            o[k] = (int64_t)(int32_t)u;
        }
    } else if (t->dtype == PC_BOOL) {
        uint8_t *o = (uint8_t *)v;
        for (k = 0; k < t->count; k++)
            o[k] = t->raw.data[k] != 0;
    } else if (onnx_host_little_endian()) {
        memcpy(v, t->raw.data, t->raw.size);
    } else {
        const size_t esize = pc_dtype_size(t->dtype);
        uint8_t *o = (uint8_t *)v;
        size_t i;
        for (k = 0; k < t->count; k++)
            for (i = 0; i < esize; i++)
                o[k * esize + i] = t->raw.data[k * esize + esize - 1 - i];
    }
}

/* Booleans of an int32_data field, one element at a time so that they land in a 1-byte
 * buffer; past `count` they are read and dropped. */
static pc_status onnx_bool_field(pc_builder *b, const pb_field *f, uint8_t *o, size_t count, size_t *n)
{
    pb_reader rr;
    uint64_t x;
    pc_status st = PC_OK;
    if (f->wire == PB_VARINT) {
        if (*n < count)
            o[(*n)++] = f->varint != 0;
        return PC_OK;
    }
    pb_init(&rr, b->file, f->bytes);
    while (st == PC_OK && rr.pos < rr.end) {
        st = pb_read_varint(&rr, &x, b->err);
        if (st == PC_OK && *n < count)
            o[(*n)++] = x != 0;
    }
    return st;
}

static pc_status onnx_tensor_decode(pc_builder *b, pb_slice msg, const onnx_tensor *t, int end,
                                    void **data)
{
    pb_reader r;
    pb_field f;
    pc_status st;
    size_t k, n = 0;
    int more;
    void *v;
    if (onnx_in_place(t)) {
        *data = (void *)t->raw.data;
        return PC_OK;
    }
    *data = v = pc_scratch_alloc(&b->scratch, end, t->count * pc_dtype_size(t->dtype) + 1);
    if (!v)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory for tensor '%.*s'", PC_NAME(t->name));
    if (t->has_raw) {
        onnx_raw_copy(t, v);
        return PC_OK;
    }
    pb_init(&r, b->file, msg);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
        st = PC_OK;
        if (t->dtype == PC_F32 && f.number == ONNX_TENSOR_FLOAT_DATA) {
            st = pb_decode_repeated(b->file, &f, PB_FIXED32, NULL, (float *)v, t->count, &n,
                                    b->err);
        } else if (t->dtype == PC_I64 && t->data_type == ONNX_INT64 &&
                   f.number == ONNX_TENSOR_INT64_DATA) {
            st = pb_decode_repeated(b->file, &f, PB_VARINT, (int64_t *)v, NULL, t->count, &n,
                                    b->err);
        } else if (t->dtype == PC_I64 && f.number == ONNX_TENSOR_INT32_DATA) {
            const size_t from = n;
            st = pb_decode_repeated(b->file, &f, PB_VARINT, (int64_t *)v, NULL, t->count, &n,
                                    b->err);
            for (k = from; st == PC_OK && k < n; k++) /* int32 varints are sign-extended */
                ((int64_t *)v)[k] = (int64_t)(int32_t)((int64_t *)v)[k];
        } else if (t->dtype == PC_BOOL && f.number == ONNX_TENSOR_INT32_DATA) {
            st = onnx_bool_field(b, &f, (uint8_t *)v, t->count, &n);
        }
        if (st != PC_OK)
            return st;
    }
    return more == PB_ERROR ? r.status : PC_OK;
}

/* A pose model's float weights are finite: NaN or infinity there (an edited file, a fit
 * that diverged) would answer every pose with NaN or kilometres away. The conformance
 * graphs (any_io) may carry them as test data. */
pc_status onnx_tensor_data(pc_builder *b, pb_slice msg, const onnx_tensor *t, int end,
                           void **data)
{
    size_t k;
    const pc_status st = onnx_tensor_decode(b, msg, t, end, data);
    if (st != PC_OK || t->dtype != PC_F32 || b->any_io)
        return st;
    for (k = 0; k < t->count; k++)
        if (!isfinite(((const float *)*data)[k]))
            return pc_fail(b->err, PC_ERR_MALFORMED, "tensor '%.*s' holds a non-finite value "
                           "at element %zu (expected finite weights)", PC_NAME(t->name), k);
    return PC_OK;
}

/* ---- AttributeProto --------------------------------------------------------------- */

static pc_status onnx_attr_decode(const pc_builder *b, pb_slice msg, const char *name,
                                  onnx_attr *a)
{
    pb_reader r;
    pb_field f;
    int more;
    memset(a, 0, sizeof *a);
    a->msg = msg;
    pb_init(&r, b->file, msg);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
        const uint32_t want = f.number == ONNX_ATTR_F   ? PB_FIXED32
                              : f.number == ONNX_ATTR_I ? PB_VARINT
                              : f.number == ONNX_ATTR_T ? PB_BYTES
                                                        : f.wire;
        if (f.wire != want)
            return pc_fail(b->err, PC_ERR_MALFORMED, "attribute '%s' has wire type %lu in field %lu",
                           name, (unsigned long)f.wire, (unsigned long)f.number);
        if (f.number == ONNX_ATTR_F) {
            a->f = pb_bits_to_float((uint32_t)f.varint);
            a->has_f = 1;
        } else if (f.number == ONNX_ATTR_I) {
            a->i = (int64_t)f.varint;
            a->has_i = 1;
        } else if (f.number == ONNX_ATTR_T) {
            a->t = f.bytes;
            a->has_t = 1;
        }
    }
    return more == PB_ERROR ? r.status : PC_OK;
}

pc_status onnx_attr_find(const pc_builder *b, const pc_node *n, const char *name,
                         onnx_attr *a, int *found)
{
    uint32_t k;
    pb_reader r;
    pb_field f;
    int more;
    *found = 0;
    for (k = 0; k < n->n_attr; k++) {
        pb_init(&r, b->file, n->attr[k]);
        while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
            if (f.number == ONNX_ATTR_NAME && f.wire == PB_BYTES && pb_slice_eq(f.bytes, name)) {
                *found = 1;
                return onnx_attr_decode(b, n->attr[k], name, a);
            }
        }
        if (more == PB_ERROR)
            return r.status;
    }
    return PC_OK;
}

pc_status onnx_attr_repeated(const pc_builder *b, const onnx_attr *a, uint32_t number,
                             int64_t *ints, float *floats, size_t cap, size_t *n)
{
    pb_reader r;
    pb_field f;
    pc_status st;
    int more;
    const uint32_t wire = number == ONNX_ATTR_FLOATS ? PB_FIXED32 : PB_VARINT;
    *n = 0;
    pb_init(&r, b->file, a->msg);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD)
        if (f.number == number &&
            (st = pb_decode_repeated(b->file, &f, wire, ints, floats, cap, n, b->err)) != PC_OK)
            return st;
    return more == PB_ERROR ? r.status : PC_OK;
}

/* ---- NodeProto -------------------------------------------------------------------- */

/* Which repeated field of a NodeProto (input, output, attribute) number is, or -1. */
static int onnx_node_list(uint32_t number)
{
    return number == ONNX_NODE_INPUT       ? 0
           : number == ONNX_NODE_OUTPUT    ? 1
           : number == ONNX_NODE_ATTRIBUTE ? 2
                                           : -1;
}

/* Two passes: the repeated fields are counted, then stored in one block. */
pc_status onnx_parse_node(pc_builder *b, pb_slice msg, uint32_t index, pc_node *node)
{
    pb_reader r;
    pb_field f;
    int more, pass;
    memset(node, 0, sizeof *node);
    node->index = index;
    node->op = -1;
    for (pass = 0; pass < 2; pass++) {
        uint32_t counts[3] = {0, 0, 0};
        pb_slice *const lists[3] = {node->in_names, node->out_names, node->attr};
        pb_init(&r, b->file, msg);
        while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
            const int k = onnx_node_list(f.number);
            if (f.number <= ONNX_NODE_DOMAIN && f.number != ONNX_NODE_DOC_STRING &&
                f.wire != PB_BYTES)
                return pc_fail(b->err, PC_ERR_MALFORMED, "node field %lu at byte %zu is not bytes",
                               (unsigned long)f.number, f.offset);
            if (k >= 0) {
                if (pass)
                    lists[k][counts[k]] = f.bytes;
                counts[k]++;
            } else if (f.number == ONNX_NODE_NAME) {
                node->name = f.bytes;
            } else if (f.number == ONNX_NODE_OP_TYPE) {
                node->op_type = f.bytes;
            } else if (f.number == ONNX_NODE_DOMAIN) {
                node->domain = f.bytes;
            }
        }
        if (more == PB_ERROR)
            return r.status;
        if (!pass) {
            const uint32_t ni = counts[0], no = counts[1], na = counts[2];
            pb_slice *slices;
            if (ni > 4096 || no > 16 || na > 256)
                return pc_fail(b->err, PC_ERR_UNSUPPORTED,
                               "node '%.*s' has too many inputs or outputs", PC_NAME(node->name));
            slices = pc_scratch_alloc(&b->scratch, PC_WORK, (ni + no + na + 3) * sizeof(pb_slice));
            if (!slices)
                return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
            node->n_in = ni;
            node->n_out = no;
            node->n_attr = na;
            node->in_names = slices;
            node->out_names = node->in_names + ni + 1;
            node->attr = node->out_names + no + 1;
        }
    }
    return PC_OK;
}

/* ---- ValueInfoProto --------------------------------------------------------------- */

/* Fields `number` of every message in `msg`, one level down: the nesting of
 * ValueInfoProto -> TypeProto -> Tensor -> TensorShapeProto -> Dimension. */
static int onnx_sub(pb_reader *r, pb_field *f, uint32_t number, pc_error *err)
{
    int more;
    while ((more = pb_next(r, f, err)) == PB_FIELD)
        if (f->number == number && f->wire == PB_BYTES)
            return PB_FIELD;
    return more;
}

/* Name, elem_type and shape of a ValueInfoProto into io (dims -1 where symbolic or
 * missing, rank -1 without a shape). */
static pc_status onnx_parse_value_info(const pc_builder *b, pb_slice msg, pb_slice *name,
                                       int64_t *elem_type, pc_io *io)
{
    pb_reader r, rt, rtt, rs, rd;
    pb_field f, ft, ftt, fs, fd;
    int more, k;
    *elem_type = 0;
    io->rank = -1;
    name->data = NULL;
    name->size = 0;
    pb_init(&r, b->file, msg);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
        if (f.number == ONNX_VALUE_INFO_NAME && f.wire == PB_BYTES)
            *name = f.bytes;
        if (f.number != ONNX_VALUE_INFO_TYPE || f.wire != PB_BYTES)
            continue;
        pb_init(&rt, b->file, f.bytes);
        while ((k = onnx_sub(&rt, &ft, ONNX_TYPE_TENSOR, b->err)) == PB_FIELD) {
            pb_init(&rtt, b->file, ft.bytes);
            while ((k = pb_next(&rtt, &ftt, b->err)) == PB_FIELD) {
                if (ftt.number == ONNX_TENSOR_TYPE_ELEM)
                    *elem_type = (int64_t)ftt.varint;
                if (ftt.number != ONNX_TENSOR_TYPE_SHAPE || ftt.wire != PB_BYTES)
                    continue;
                io->rank = 0;
                pb_init(&rs, b->file, ftt.bytes);
                while ((k = onnx_sub(&rs, &fs, ONNX_SHAPE_DIM, b->err)) == PB_FIELD) {
                    if (io->rank >= PC_MAX_RANK)
                        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "value info of rank > %d",
                                       PC_MAX_RANK);
                    io->dims[io->rank] = -1;
                    pb_init(&rd, b->file, fs.bytes);
                    while ((k = pb_next(&rd, &fd, b->err)) == PB_FIELD)
                        if (fd.number == ONNX_DIM_VALUE && fd.wire == PB_VARINT) {
                            /* negative is no size; as -1 it would read as symbolic */
                            if ((int64_t)fd.varint < 0)
                                return pc_fail(b->err, PC_ERR_MALFORMED, "value '%.*s' has "
                                               "dimension %lld, expected a size of 0 or more",
                                               (int)name->size, name->data ? (const char *)name->data : "",
                                               (long long)(int64_t)fd.varint);
                            io->dims[io->rank] = (int64_t)fd.varint;
                        }
                    if (k == PB_ERROR)
                        return rd.status;
                    io->rank++;
                }
                if (k == PB_ERROR)
                    return rs.status;
            }
            if (k == PB_ERROR)
                return rtt.status;
        }
        if (k == PB_ERROR)
            return rt.status;
    }
    return more == PB_ERROR ? r.status : PC_OK;
}

static int onnx_dtype(int64_t elem_type)
{
    return elem_type == ONNX_FLOAT ? PC_F32 : elem_type == ONNX_INT64 ? PC_I64
                                          : elem_type == ONNX_BOOL    ? PC_BOOL : 0;
}

/* The pose contract: 'pose' float32 [N,7] with a dynamic N, and in models with a
 * time-dependent effect 't' float32 [N] (seconds since the session's start). */
static pc_status onnx_check_input(pc_builder *b, pb_slice name, int64_t elem, const pc_io *io)
{
    if (b->any_io) {
        int k;
        if (!onnx_dtype(elem))
            return pc_fail(b->err, PC_ERR_UNSUPPORTED, "input '%.*s' has data type %lld",
                           PC_NAME(name), (long long)elem);
        for (k = 0; k < io->rank; k++)
            if (io->dims[k] < 0)
                return pc_fail(b->err, PC_ERR_UNSUPPORTED, "input '%.*s' has a dynamic shape",
                               PC_NAME(name));
        if (io->rank < 0)
            return pc_fail(b->err, PC_ERR_UNSUPPORTED, "input '%.*s' has no shape", PC_NAME(name));
        return PC_OK;
    }
    if (pb_slice_eq(name, PC_TIME_INPUT)) {
        if (elem != ONNX_FLOAT)
            return pc_fail(b->err, PC_ERR_CONTRACT, "input 't' has element type %lld, "
                           "the contract needs float32", (long long)elem);
        if (io->rank != 1)
            return pc_fail(b->err, PC_ERR_CONTRACT, "input 't' must have shape [N] (rank %d)",
                           io->rank);
        if (io->dims[0] >= 0)
            return pc_fail(b->err, PC_ERR_CONTRACT,
                           "input 't' has a fixed batch size %lld; N must be dynamic",
                           (long long)io->dims[0]);
        return PC_OK;
    }
    if (!pb_slice_eq(name, "pose"))
        return pc_fail(b->err, PC_ERR_CONTRACT,
                       "model input is '%.*s', the contract needs 'pose' float32 [N,7] and "
                       "optionally 't' float32 [N]", PC_NAME(name));
    if (elem != ONNX_FLOAT)
        return pc_fail(b->err, PC_ERR_CONTRACT, "input 'pose' has element type %lld, "
                       "the contract needs float32", (long long)elem);
    if (io->rank != 2 || io->dims[1] != PC_POSE_WIDTH)
        return pc_fail(b->err, PC_ERR_CONTRACT,
                       "input 'pose' must have shape [N,7] (rank %d, width %lld)", io->rank,
                       (long long)(io->rank >= 2 ? io->dims[1] : -1));
    if (io->dims[0] >= 0)
        return pc_fail(b->err, PC_ERR_CONTRACT,
                       "input 'pose' has a fixed batch size %lld; N must be dynamic",
                       (long long)io->dims[0]);
    return PC_OK;
}

static pc_status onnx_check_output(pc_builder *b, pb_slice name, int64_t elem, const pc_io *io)
{
    if (b->any_io) {
        if (!onnx_dtype(elem))
            return pc_fail(b->err, PC_ERR_UNSUPPORTED, "output '%.*s' has data type %lld",
                           PC_NAME(name), (long long)elem);
        return PC_OK;
    }
    if (!pb_slice_eq(name, "corrected"))
        return pc_fail(b->err, PC_ERR_CONTRACT,
                       "model output is '%.*s', the contract needs 'corrected' float32 [N,7]",
                       PC_NAME(name));
    if (elem != ONNX_FLOAT)
        return pc_fail(b->err, PC_ERR_CONTRACT, "output 'corrected' has element type "
                       "%lld, the contract needs float32", (long long)elem);
    if (io->rank >= 0 && (io->rank != 2 || io->dims[1] != PC_POSE_WIDTH))
        return pc_fail(b->err, PC_ERR_CONTRACT, "output 'corrected' must have shape [N,7]");
    return PC_OK;
}

/* ---- GraphProto ------------------------------------------------------------------- */

/* Whether name is one of the graph's initializers (IR < 4 lists them among the inputs). */
static pc_status onnx_is_initializer(const pc_builder *b, pb_slice name, int *is)
{
    uint32_t k;
    *is = 0;
    for (k = 0; k < b->n_inits && !*is; k++) {
        pb_reader r;
        pb_field f;
        int more;
        pb_init(&r, b->file, b->inits[k]);
        while ((more = pb_next(&r, &f, b->err)) == PB_FIELD)
            if (f.number == ONNX_TENSOR_NAME && f.wire == PB_BYTES && pb_slice_same(f.bytes, name))
                *is = 1;
        if (more == PB_ERROR)
            return r.status;
    }
    return PC_OK;
}

/* A graph input, unless it is an initializer (IR < 4) or repeated; checked against the
 * contract. */
static pc_status onnx_add_input(pc_builder *b, pb_slice name, int64_t elem, const pc_io *io)
{
    pc_status st;
    int is_init;
    size_t k;
    if ((st = onnx_is_initializer(b, name, &is_init)) != PC_OK)
        return st;
    for (k = 0; k < b->n_inputs && !is_init; k++)
        is_init = pb_slice_same(b->inputs[k].name, name);
    if (is_init)
        return PC_OK;
    if ((st = onnx_check_input(b, name, elem, io)) != PC_OK)
        return st;
    if (b->n_inputs > PC_MAX_INDEX)
        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "graph has too many inputs");
    b->inputs[b->n_inputs++] = *io;
    /* the pose contract keeps 'pose' first, 't' (if any) second */
    if (!b->any_io && b->n_inputs == 2 && pb_slice_eq(name, "pose")) {
        b->inputs[1] = b->inputs[0];
        b->inputs[0] = *io;
    }
    return PC_OK;
}

pc_status onnx_parse_io(pc_builder *b, size_t n_io)
{
    pb_reader r;
    pb_field f;
    pc_status st;
    pb_slice name;
    int64_t elem;
    pc_io io;
    int more;
    size_t k;
    b->inputs = pc_scratch_alloc(&b->scratch, PC_KEEP, (n_io + 1) * sizeof(pc_io));
    b->outputs = pc_scratch_alloc(&b->scratch, PC_KEEP, (n_io + 1) * sizeof(pc_io));
    if (!b->inputs || !b->outputs)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    pb_init(&r, b->file, b->graph);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
        if (f.number != ONNX_GRAPH_INPUT && f.number != ONNX_GRAPH_OUTPUT)
            continue;
        memset(&io, 0, sizeof io);
        if ((st = onnx_parse_value_info(b, f.bytes, &name, &elem, &io)) != PC_OK)
            return st;
        io.dtype = onnx_dtype(elem);
        io.name = name;
        if (f.number == ONNX_GRAPH_INPUT)
            st = onnx_add_input(b, name, elem, &io);
        else if ((st = onnx_check_output(b, name, elem, &io)) == PC_OK)
            b->outputs[b->n_outputs++] = io;
        if (st != PC_OK)
            return st;
    }
    if (more == PB_ERROR)
        return r.status;
    for (k = 0; k < b->n_inputs; k++)
        b->inputs[k].ref = PC_REF(PC_REF_INPUT, k);
    if (b->any_io)
        return b->n_outputs ? PC_OK : pc_fail(b->err, PC_ERR_GRAPH, "graph has no output");
    /* names are checked above and repeated ones skipped: at most 'pose' and 't' */
    if (b->n_inputs == 0 || !pb_slice_eq(b->inputs[0].name, "pose"))
        return pc_fail(b->err, PC_ERR_CONTRACT,
                       "model has no input 'pose', the contract needs 'pose' float32 [N,7] "
                       "and optionally 't' float32 [N]");
    if (b->n_outputs != 1)
        return pc_fail(b->err, PC_ERR_CONTRACT,
                       "model has %zu outputs, the contract needs exactly one ('corrected')",
                       b->n_outputs);
    return PC_OK;
}

pc_status onnx_graph_counts(pc_builder *b, uint32_t *nodes, uint32_t *inits, size_t *io)
{
    pb_reader r;
    pb_field f;
    int more;
    *nodes = *inits = 0;
    *io = 0;
    pb_init(&r, b->file, b->graph);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
        if ((f.number == ONNX_GRAPH_NODE || f.number == ONNX_GRAPH_INITIALIZER ||
             f.number == ONNX_GRAPH_INPUT || f.number == ONNX_GRAPH_OUTPUT) &&
            f.wire != PB_BYTES)
            return pc_fail(b->err, PC_ERR_MALFORMED, "graph field %lu at byte %zu is not bytes",
                           (unsigned long)f.number, f.offset);
        if (f.number == ONNX_GRAPH_NODE)
            ++*nodes;
        else if (f.number == ONNX_GRAPH_INITIALIZER)
            ++*inits;
        else if (f.number == ONNX_GRAPH_INPUT || f.number == ONNX_GRAPH_OUTPUT)
            ++*io;
        else if (f.number == ONNX_GRAPH_SPARSE_INITIALIZER)
            return pc_fail(b->err, PC_ERR_UNSUPPORTED, "sparse initializers are not supported");
        if (*nodes > PC_MAX_NODES || *inits > PC_MAX_INDEX)
            return pc_fail(b->err, PC_ERR_UNSUPPORTED, "graph too large (more than %u %s, the "
                           "runtime's limit)", *nodes > PC_MAX_NODES ? PC_MAX_NODES : PC_MAX_INDEX,
                           *nodes > PC_MAX_NODES ? "nodes" : "initializers");
    }
    return more == PB_ERROR ? r.status : PC_OK;
}

static int onnx_next_field(const pc_builder *b, pb_reader *r, uint32_t number, pb_field *f)
{
    int more;
    while ((more = pb_next(r, f, b->err)) == PB_FIELD)
        if (f->number == number && f->wire == PB_BYTES)
            return PB_FIELD;
    return more;
}

int onnx_next_node(const pc_builder *b, pb_reader *r, pb_slice *msg)
{
    pb_field f;
    const int more = onnx_next_field(b, r, ONNX_GRAPH_NODE, &f);
    if (more == PB_FIELD)
        *msg = f.bytes;
    return more;
}

/* ---- ModelProto ------------------------------------------------------------------- */

/* Field `first` (bytes) and field `second` (bytes or varint) of a small message:
 * StringStringEntryProto key/value, OperatorSetIdProto domain/version. */
static pc_status onnx_pair(const pc_builder *b, pb_slice msg, uint32_t first_number,
                           uint32_t second_number, pb_slice *first, pb_slice *second,
                           int64_t *number)
{
    pb_reader r;
    pb_field f;
    int more;
    pb_init(&r, b->file, msg);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
        if (f.number == first_number && f.wire == PB_BYTES)
            *first = f.bytes;
        if (f.number == second_number && f.wire == PB_BYTES && second)
            *second = f.bytes;
        if (f.number == second_number && f.wire == PB_VARINT && number)
            *number = (int64_t)f.varint;
    }
    return more == PB_ERROR ? r.status : PC_OK;
}

int onnx_next_meta(const pc_builder *b, pb_reader *r, pb_slice *key, pb_slice *value)
{
    pb_field f;
    int more = onnx_next_field(b, r, ONNX_MODEL_METADATA_PROPS, &f);
    key->data = value->data = NULL;
    key->size = value->size = 0;
    if (more == PB_FIELD && (r->status = onnx_pair(b, f.bytes, ONNX_STRING_KEY, ONNX_STRING_VALUE,
                                                   key, value, NULL)) != PC_OK)
        more = PB_ERROR;
    return more;
}

/* The model's top level: its graph, opsets and metadata entries read as fields. */
static pc_status onnx_read_model(pc_builder *b)
{
    pb_reader r;
    pb_field f;
    int more, has_graph = 0;
    pc_status st;
    pb_slice whole;
    whole.data = b->file;
    whole.size = b->file_size;
    b->opset = -1;
    pb_init(&r, b->file, whole);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD) {
        if ((f.number == ONNX_MODEL_GRAPH || f.number == ONNX_MODEL_OPSET_IMPORT ||
             f.number == ONNX_MODEL_METADATA_PROPS) && f.wire != PB_BYTES)
            return pc_fail(b->err, PC_ERR_MALFORMED, "model field %lu at byte %zu is not bytes",
                           (unsigned long)f.number, f.offset);
        if (f.number == ONNX_MODEL_GRAPH) {
            b->graph = f.bytes;
            has_graph = 1;
        } else if (f.number == ONNX_MODEL_OPSET_IMPORT) {
            pb_slice domain = {NULL, 0};
            int64_t version = -1;
            if ((st = onnx_pair(b, f.bytes, ONNX_OPSET_DOMAIN, ONNX_OPSET_VERSION, &domain, NULL,
                                &version)) != PC_OK)
                return st;
            if (domain.size == 0 || pb_slice_eq(domain, "ai.onnx"))
                b->opset = version;
        } else if (f.number == ONNX_MODEL_METADATA_PROPS) {
            pb_slice key = {NULL, 0}, value = {NULL, 0};
            if ((st = onnx_pair(b, f.bytes, ONNX_STRING_KEY, ONNX_STRING_VALUE, &key, &value,
                                NULL)) != PC_OK)
                return st;
        }
    }
    if (more == PB_ERROR)
        return r.status;
    return has_graph ? PC_OK : pc_fail(b->err, PC_ERR_MALFORMED, "no graph");
}

/* A file whose top level does not read as a model (bytes that are not protobuf, a field of
 * the wrong type, no graph) is no ONNX model at all, and the message says so before where
 * the reader stopped, as the Python back end and `posecorr info` do: a text file given as
 * the model is "not a valid ONNX model (unsupported wire type 4 at byte 2)". A truncated
 * file keeps its own words: it is a model cut short. */
pc_status onnx_scan_model(pc_builder *b)
{
    char where[96];
    const pc_status st = onnx_read_model(b);
    if (st == PC_ERR_MALFORMED) {
        memcpy(where, b->err->message, sizeof where - 1);
        where[sizeof where - 1] = '\0';
        return pc_fail(b->err, PC_ERR_MALFORMED, "not a valid ONNX model (%s)", where);
    }
    if (st != PC_OK)
        return st;
    if (b->opset < PC_OPSET_MIN || b->opset > PC_OPSET_MAX)
        return pc_fail(b->err, PC_ERR_UNSUPPORTED,
                       "default-domain opset %lld is not supported (%d..%d)", (long long)b->opset,
                       PC_OPSET_MIN, PC_OPSET_MAX);
    return PC_OK;
}
