/* Loading: ONNX ModelProto -> builder (names resolved, constants decoded), then
 * graph.c plans it into the model's single arena. Load-time scratch memory lives in a
 * block list that is released before pc_load_* returns. */
#include "pc_internal.h"

#include <stdlib.h>
#include <string.h>

/* ---- scratch ---------------------------------------------------------------------- */

struct pc_scratch_block {
    pc_scratch_block *next;
    size_t size, used;
    /* data follows, aligned by the allocation itself */
};

#define PC_BLOCK_HEADER (((sizeof(pc_scratch_block) + PC_ALIGN - 1) / PC_ALIGN) * PC_ALIGN)

/* Untouched scratch is never faulted in: big arrays whose entries are all written before
 * use (values, drafts) take it raw, so their unused capacity costs no page faults. */
void *pc_scratch_alloc_raw(pc_scratch *s, size_t size)
{
    pc_scratch_block *b = s->head;
    size_t need = (size + PC_ALIGN - 1) / PC_ALIGN * PC_ALIGN;
    uint8_t *p;
    if (size > ((size_t)1 << 40))
        return NULL;
    if (need == 0)
        need = PC_ALIGN;
    if (!b || b->size - b->used < need) {
        const size_t block = need > 65536 ? need : 65536;
        b = (pc_scratch_block *)malloc(PC_BLOCK_HEADER + block);
        if (!b)
            return NULL;
        b->next = s->head;
        b->size = block;
        b->used = 0;
        s->head = b;
    }
    p = (uint8_t *)b + PC_BLOCK_HEADER + b->used;
    b->used += need;
    s->used_total += need;
    return p;
}

void *pc_scratch_alloc(pc_scratch *s, size_t size)
{
    void *p = pc_scratch_alloc_raw(s, size);
    if (p)
        memset(p, 0, size);
    return p;
}

void pc_scratch_release(pc_scratch *s)
{
    while (s->head) {
        pc_scratch_block *next = s->head->next;
        free(s->head);
        s->head = next;
    }
    s->used_total = 0;
}

/* ---- names ------------------------------------------------------------------------ */

static uint32_t pc_hash(pb_slice s)
{
    uint32_t h = 2166136261u;
    size_t i;
    for (i = 0; i < s.size; i++)
        h = (h ^ s.data[i]) * 16777619u;
    return h;
}

static int pc_slice_same(pb_slice a, pb_slice b)
{
    return a.size == b.size && (a.size == 0 || memcmp(a.data, b.data, a.size) == 0);
}

static int32_t pc_lookup(const pc_builder *b, pb_slice name)
{
    size_t i = pc_hash(name) & (b->hash_cap - 1);
    while (b->hash[i] >= 0) {
        if (pc_slice_same(b->values[b->hash[i]].name, name))
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

static pc_status pc_new_value(pc_builder *b, pb_slice name, int32_t *id)
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

/* ---- tensors ---------------------------------------------------------------------- */

size_t pc_dtype_size(int dtype)
{
    return dtype == PC_F32 ? 4 : dtype == PC_I64 ? 8 : dtype == PC_BOOL ? 1 : 0;
}

const char *pc_dtype_name(int dtype)
{
    return dtype == PC_F32 ? "float32" : dtype == PC_I64 ? "int64" : dtype == PC_BOOL ? "bool"
                                                                                      : "?";
}

pc_status pc_alloc_const(pc_builder *b, pb_slice name, int dtype, int rank,
                         const int64_t *dims, int32_t *id)
{
    pc_value *v;
    size_t count = 1;
    int i;
    pc_status st;
    for (i = 0; i < rank; i++) {
        if (dims[i] < 0 || (dims[i] > 0 && count > ((size_t)1 << 32) / (size_t)dims[i]))
            return pc_fail(b->err, PC_ERR_SHAPE, "constant '%.*s' has an invalid shape",
                           (int)name.size, (const char *)name.data);
        count *= (size_t)dims[i];
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

pc_status pc_tensor_to_const(pc_builder *b, pb_slice tensor, int32_t *id)
{
    pb_reader r;
    pb_field f;
    int more;
    pc_status st;
    int64_t dims[PC_MAX_RANK];
    size_t rank = 0, n_float = 0, n_int32 = 0, n_int64 = 0, k, count = 1, n;
    int64_t data_type = 0;
    pb_slice name = {NULL, 0}, raw = {NULL, 0};
    int has_raw = 0, dtype, i;
    pc_value *v;
    pc_error *err = b->err;

    pb_init(&r, b->file, tensor);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, err)) != PC_OK)
            return st;
        if (!more)
            break;
        switch (f.number) {
        case 1:
            if ((st = pb_count_packed(b->file, &f, PB_VARINT, &k, err)) != PC_OK)
                return st;
            if (rank + k > PC_MAX_RANK)
                return pc_fail(err, PC_ERR_UNSUPPORTED, "tensor at byte %zu has rank > %d",
                               f.offset, PC_MAX_RANK);
            n = rank;
            if ((st = pb_decode_repeated(b->file, &f, PB_VARINT, dims, NULL, PC_MAX_RANK, &n,
                                         err)) != PC_OK)
                return st;
            rank = n;
            break;
        case 2:
            data_type = (int64_t)f.varint;
            break;
        case 4:
            if ((st = pb_count_packed(b->file, &f, PB_FIXED32, &k, err)) != PC_OK)
                return st;
            n_float += k;
            break;
        case 5:
            if ((st = pb_count_packed(b->file, &f, PB_VARINT, &k, err)) != PC_OK)
                return st;
            n_int32 += k;
            break;
        case 7:
            if ((st = pb_count_packed(b->file, &f, PB_VARINT, &k, err)) != PC_OK)
                return st;
            n_int64 += k;
            break;
        case 8:
            name = f.bytes;
            break;
        case 9:
            raw = f.bytes;
            has_raw = 1;
            break;
        case 14:
            if (f.varint == 1)
                return pc_fail(err, PC_ERR_UNSUPPORTED,
                               "tensor '%.*s' uses external data", (int)name.size,
                               (const char *)name.data);
            break;
        default:
            break;
        }
    }
    for (k = 0; k < rank; k++) {
        if (dims[k] < 0 || (dims[k] > 0 && count > ((size_t)1 << 31) / (size_t)dims[k]))
            return pc_fail(err, PC_ERR_MALFORMED, "tensor '%.*s' has an invalid shape",
                           (int)name.size, (const char *)name.data);
        count *= (size_t)dims[k];
    }
    switch (data_type) {
    case 1: dtype = PC_F32; break;
    case 6: case 7: dtype = PC_I64; break;
    case 9: dtype = PC_BOOL; break;
    default:
        return pc_fail(err, PC_ERR_UNSUPPORTED, "tensor '%.*s' has unsupported data type %lld",
                       (int)name.size, (const char *)name.data, (long long)data_type);
    }
    /* Check the payload size against the shape before allocating anything. */
    if (has_raw) {
        const size_t esize = data_type == 6 ? 4 : pc_dtype_size(dtype);
        if (raw.size != count * esize)
            return pc_fail(err, PC_ERR_MALFORMED,
                           "tensor '%.*s': raw_data has %zu bytes, shape needs %zu",
                           (int)name.size, (const char *)name.data, raw.size, count * esize);
    } else {
        const size_t have = dtype == PC_F32 ? n_float : data_type == 7 ? n_int64 : n_int32;
        if (have != count)
            return pc_fail(err, PC_ERR_MALFORMED,
                           "tensor '%.*s' has %zu values, shape needs %zu", (int)name.size,
                           (const char *)name.data, have, count);
    }
    if ((st = pc_alloc_const(b, name, dtype, (int)rank, dims, id)) != PC_OK)
        return st;
    v = &b->values[*id];
    if (has_raw) {
        if (data_type == 6) {
            int64_t *o = (int64_t *)v->cdata;
            for (k = 0; k < count; k++) {
                uint32_t u = (uint32_t)raw.data[4 * k] | (uint32_t)raw.data[4 * k + 1] << 8 |
                             (uint32_t)raw.data[4 * k + 2] << 16 |
                             (uint32_t)raw.data[4 * k + 3] << 24;
                o[k] = (int64_t)(int32_t)u;
            }
        } else if (dtype == PC_BOOL) {
            uint8_t *o = (uint8_t *)v->cdata;
            for (k = 0; k < count; k++)
                o[k] = raw.data[k] != 0;
        } else {
            /* raw_data is little-endian and may be unaligned in the file. */
            memcpy(v->cdata, raw.data, raw.size);
        }
        return PC_OK;
    }
    pb_init(&r, b->file, tensor);
    n = 0;
    for (;;) {
        if ((st = pb_next(&r, &f, &more, err)) != PC_OK)
            return st;
        if (!more)
            break;
        if (dtype == PC_F32 && f.number == 4)
            st = pb_decode_repeated(b->file, &f, PB_FIXED32, NULL, (float *)v->cdata, count, &n,
                                    err);
        else if (dtype == PC_I64 && data_type == 7 && f.number == 7)
            st = pb_decode_repeated(b->file, &f, PB_VARINT, (int64_t *)v->cdata, NULL, count,
                                    &n, err);
        else if (f.number == 5 && (data_type == 6 || dtype == PC_BOOL)) {
            int64_t tmp[64];
            size_t m = 0, j;
            /* Decode in chunks so booleans land in a 1-byte buffer. */
            if (dtype == PC_I64) {
                st = pb_decode_repeated(b->file, &f, PB_VARINT, (int64_t *)v->cdata, NULL,
                                        count, &n, err);
                for (j = 0; st == PC_OK && j < n; j++)
                    ((int64_t *)v->cdata)[j] = (int64_t)(int32_t)((int64_t *)v->cdata)[j];
            } else {
                if (f.wire == PB_VARINT) {
                    if (n < count)
                        ((uint8_t *)v->cdata)[n++] = f.varint != 0;
                } else {
                    pb_reader rr;
                    uint64_t x;
                    pb_init(&rr, b->file, f.bytes);
                    while (rr.pos < rr.end && st == PC_OK) {
                        st = pb_read_varint(&rr, &x, err);
                        if (st == PC_OK && n < count)
                            ((uint8_t *)v->cdata)[n++] = x != 0;
                    }
                }
                (void)tmp;
                (void)m;
            }
        }
        if (st != PC_OK)
            return st;
    }
    (void)i;
    return PC_OK;
}

/* ---- ONNX messages ---------------------------------------------------------------- */

static pc_status pc_parse_node(pc_builder *b, pb_slice msg, pc_node *node)
{
    pb_reader r;
    pb_field f;
    int more, pass;
    pc_status st;
    for (pass = 0; pass < 2; pass++) {
        uint32_t ni = 0, no = 0, na = 0;
        pb_init(&r, b->file, msg);
        for (;;) {
            if ((st = pb_next(&r, &f, &more, b->err)) != PC_OK)
                return st;
            if (!more)
                break;
            if (f.number <= 7 && f.number != 6 && f.wire != PB_BYTES)
                return pc_fail(b->err, PC_ERR_MALFORMED, "node field %u at byte %zu is not bytes",
                               f.number, f.offset);
            switch (f.number) {
            case 1:
                if (pass)
                    node->in_names[ni] = f.bytes;
                ni++;
                break;
            case 2:
                if (pass)
                    node->out_names[no] = f.bytes;
                no++;
                break;
            case 3: node->name = f.bytes; break;
            case 4: node->op_type = f.bytes; break;
            case 5:
                if (pass)
                    node->attr[na] = f.bytes;
                na++;
                break;
            case 7: node->domain = f.bytes; break;
            default: break;
            }
        }
        if (!pass) {
            if (ni > 4096 || no > 16 || na > 256)
                return pc_fail(b->err, PC_ERR_UNSUPPORTED, "node '%.*s' has too many inputs or outputs",
                               (int)node->name.size, (const char *)node->name.data);
            node->n_in = ni;
            node->n_out = no;
            node->n_attr = na;
            node->in_names = pc_scratch_alloc(&b->scratch, (ni + 1) * sizeof(pb_slice));
            node->out_names = pc_scratch_alloc(&b->scratch, (no + 1) * sizeof(pb_slice));
            node->attr = pc_scratch_alloc(&b->scratch, (na + 1) * sizeof(pb_slice));
            node->in = pc_scratch_alloc(&b->scratch, (ni + 1) * sizeof(int32_t));
            node->out = pc_scratch_alloc(&b->scratch, (no + 1) * sizeof(int32_t));
            if (!node->in_names || !node->out_names || !node->attr || !node->in || !node->out)
                return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        }
    }
    return PC_OK;
}

/* Reads name, elem_type and shape of a ValueInfoProto. dims[k] = -1 for a symbolic or
 * missing dimension; *rank = -1 when there is no shape. */
static pc_status pc_parse_value_info(pc_builder *b, pb_slice msg, pb_slice *name,
                                     int64_t *elem_type, int *rank, int64_t *dims)
{
    pb_reader r, rt, rtt, rs, rd;
    pb_field f, ft, ftt, fs, fd;
    int more;
    pc_status st;
    *elem_type = 0;
    *rank = -1;
    name->data = NULL;
    name->size = 0;
    pb_init(&r, b->file, msg);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if (f.number == 1 && f.wire == PB_BYTES)
            *name = f.bytes;
        if (f.number != 2 || f.wire != PB_BYTES)
            continue;
        pb_init(&rt, b->file, f.bytes);
        for (;;) {
            if ((st = pb_next(&rt, &ft, &more, b->err)) != PC_OK)
                return st;
            if (!more)
                break;
            if (ft.number != 1 || ft.wire != PB_BYTES)
                continue;
            pb_init(&rtt, b->file, ft.bytes);
            for (;;) {
                if ((st = pb_next(&rtt, &ftt, &more, b->err)) != PC_OK)
                    return st;
                if (!more)
                    break;
                if (ftt.number == 1)
                    *elem_type = (int64_t)ftt.varint;
                if (ftt.number != 2 || ftt.wire != PB_BYTES)
                    continue;
                *rank = 0;
                pb_init(&rs, b->file, ftt.bytes);
                for (;;) {
                    if ((st = pb_next(&rs, &fs, &more, b->err)) != PC_OK)
                        return st;
                    if (!more)
                        break;
                    if (fs.number != 1 || fs.wire != PB_BYTES)
                        continue;
                    if (*rank >= PC_MAX_RANK)
                        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "value info of rank > %d",
                                       PC_MAX_RANK);
                    dims[*rank] = -1;
                    pb_init(&rd, b->file, fs.bytes);
                    for (;;) {
                        if ((st = pb_next(&rd, &fd, &more, b->err)) != PC_OK)
                            return st;
                        if (!more)
                            break;
                        if (fd.number == 1 && fd.wire == PB_VARINT)
                            dims[*rank] = (int64_t)fd.varint;
                    }
                    (*rank)++;
                }
            }
        }
    }
    return PC_OK;
}

static pc_status pc_parse_graph(pc_builder *b, pb_slice graph)
{
    pb_reader r;
    pb_field f;
    int more;
    pc_status st;
    size_t n_nodes = 0, n_init = 0, n_outputs = 0, n_in = 0, n_out = 0, i, j, total_out = 0;
    int32_t id;
    pb_slice in_msg = {NULL, 0}, out_msg = {NULL, 0};
    pb_slice name;
    int64_t elem, dims[PC_MAX_RANK];
    int rank;

    pb_init(&r, b->file, graph);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if ((f.number == 1 || f.number == 5 || f.number == 11 || f.number == 12) &&
            f.wire != PB_BYTES)
            return pc_fail(b->err, PC_ERR_MALFORMED, "graph field %u at byte %zu is not bytes",
                           f.number, f.offset);
        if (f.number == 1)
            n_nodes++;
        else if (f.number == 5)
            n_init++;
        else if (f.number == 15)
            return pc_fail(b->err, PC_ERR_UNSUPPORTED, "sparse initializers are not supported");
    }
    if (n_nodes > 100000 || n_init > 100000)
        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "graph too large");
    b->nodes = pc_scratch_alloc(&b->scratch, (n_nodes + 1) * sizeof(pc_node));
    if (!b->nodes)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    pb_init(&r, b->file, graph);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if (f.number == 1) {
            pc_node *node = &b->nodes[b->n_nodes++];
            if ((st = pc_parse_node(b, f.bytes, node)) != PC_OK)
                return st;
            total_out += node->n_out;
        }
    }
    /* Values: initializers, the input, node outputs, and derived constants. */
    b->cap_values = n_init + 4 + total_out + 3 * n_nodes + 16;
    b->values = pc_scratch_alloc_raw(&b->scratch, b->cap_values * sizeof(pc_value));
    for (b->hash_cap = 16; b->hash_cap < 2 * b->cap_values; b->hash_cap *= 2)
        ;
    b->hash = pc_scratch_alloc(&b->scratch, b->hash_cap * sizeof(int32_t));
    if (!b->values || !b->hash)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < b->hash_cap; i++)
        b->hash[i] = -1;

    pb_init(&r, b->file, graph);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if (f.number == 5) {
            if ((st = pc_tensor_to_const(b, f.bytes, &id)) != PC_OK)
                return st;
            if (b->values[id].name.size == 0)
                return pc_fail(b->err, PC_ERR_MALFORMED, "initializer at byte %zu has no name",
                               f.offset);
            if (pc_lookup(b, b->values[id].name) != id)
                return pc_fail(b->err, PC_ERR_GRAPH, "duplicate initializer '%.*s'",
                               (int)b->values[id].name.size,
                               (const char *)b->values[id].name.data);
        }
    }
    (void)n_outputs;
    /* Graph inputs; IR < 4 lists initializers among them, which are not model inputs. */
    pb_init(&r, b->file, graph);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if (f.number != 11 && f.number != 12)
            continue;
        if ((st = pc_parse_value_info(b, f.bytes, &name, &elem, &rank, dims)) != PC_OK)
            return st;
        if (f.number == 11) {
            if (pc_lookup(b, name) >= 0)
                continue;
            n_in++;
            in_msg = f.bytes;
            if (!pb_slice_eq(name, "pose"))
                return pc_fail(b->err, PC_ERR_CONTRACT,
                               "model input is '%.*s', the contract needs 'pose' float32 [N,7]",
                               (int)name.size, (const char *)name.data);
            if (elem != 1)
                return pc_fail(b->err, PC_ERR_CONTRACT, "input 'pose' has element type %lld, "
                               "the contract needs float32", (long long)elem);
            if (rank != 2 || dims[1] != PC_POSE_WIDTH)
                return pc_fail(b->err, PC_ERR_CONTRACT,
                               "input 'pose' must have shape [N,7] (rank %d, width %lld)", rank,
                               (long long)(rank >= 2 ? dims[1] : -1));
            if (dims[0] >= 0)
                return pc_fail(b->err, PC_ERR_CONTRACT,
                               "input 'pose' has a fixed batch size %lld; N must be dynamic",
                               (long long)dims[0]);
            if ((st = pc_new_value(b, name, &b->input_id)) != PC_OK)
                return st;
            b->values[b->input_id].dtype = PC_F32;
        } else {
            n_out++;
            out_msg = f.bytes;
            if (!pb_slice_eq(name, "corrected"))
                return pc_fail(b->err, PC_ERR_CONTRACT,
                               "model output is '%.*s', the contract needs 'corrected' float32 [N,7]",
                               (int)name.size, (const char *)name.data);
            if (elem != 1)
                return pc_fail(b->err, PC_ERR_CONTRACT, "output 'corrected' has element type "
                               "%lld, the contract needs float32", (long long)elem);
            if (rank >= 0 && (rank != 2 || dims[1] != PC_POSE_WIDTH))
                return pc_fail(b->err, PC_ERR_CONTRACT,
                               "output 'corrected' must have shape [N,7]");
        }
    }
    (void)in_msg;
    (void)out_msg;
    if (n_in != 1)
        return pc_fail(b->err, PC_ERR_CONTRACT,
                       "model has %zu inputs, the contract needs exactly one ('pose')", n_in);
    if (n_out != 1)
        return pc_fail(b->err, PC_ERR_CONTRACT,
                       "model has %zu outputs, the contract needs exactly one ('corrected')", n_out);

    /* Node outputs, then node inputs (nodes need not be sorted in the file). */
    for (i = 0; i < b->n_nodes; i++) {
        pc_node *node = &b->nodes[i];
        for (j = 0; j < node->n_out; j++) {
            node->out[j] = -1;
            if (node->out_names[j].size == 0)
                continue;
            if (pc_lookup(b, node->out_names[j]) >= 0)
                return pc_fail(b->err, PC_ERR_GRAPH,
                               "tensor '%.*s' is produced twice (node '%.*s')",
                               (int)node->out_names[j].size,
                               (const char *)node->out_names[j].data, (int)node->name.size,
                               (const char *)node->name.data);
            if ((st = pc_new_value(b, node->out_names[j], &node->out[j])) != PC_OK)
                return st;
            b->values[node->out[j]].producer = (int)i;
        }
    }
    for (i = 0; i < b->n_nodes; i++) {
        pc_node *node = &b->nodes[i];
        for (j = 0; j < node->n_in; j++) {
            if (node->in_names[j].size == 0) {
                node->in[j] = -1;
                continue;
            }
            node->in[j] = pc_lookup(b, node->in_names[j]);
            if (node->in[j] < 0)
                return pc_fail(b->err, PC_ERR_GRAPH,
                               "input '%.*s' of node '%.*s' is not produced by any node",
                               (int)node->in_names[j].size,
                               (const char *)node->in_names[j].data, (int)node->name.size,
                               (const char *)node->name.data);
        }
    }
    {
        pb_slice out_name = {(const uint8_t *)"corrected", 9};
        b->output_id = pc_lookup(b, out_name);
        if (b->output_id < 0)
            return pc_fail(b->err, PC_ERR_GRAPH, "output 'corrected' is not produced by any node");
    }
    return PC_OK;
}

pc_status pc_parse_model(pc_builder *b)
{
    pb_reader r, ro;
    pb_field f, fo;
    int more, has_graph = 0;
    pc_status st;
    pb_slice graph = {NULL, 0}, whole;
    size_t n_meta = 0;
    whole.data = b->file;
    whole.size = b->file_size;
    b->opset = -1;
    pb_init(&r, b->file, whole);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if ((f.number == 7 || f.number == 8 || f.number == 14) && f.wire != PB_BYTES)
            return pc_fail(b->err, PC_ERR_MALFORMED, "model field %u at byte %zu is not bytes",
                           f.number, f.offset);
        if (f.number == 7) {
            graph = f.bytes;
            has_graph = 1;
        } else if (f.number == 8) {
            pb_slice domain = {NULL, 0};
            int64_t version = -1;
            pb_init(&ro, b->file, f.bytes);
            for (;;) {
                if ((st = pb_next(&ro, &fo, &more, b->err)) != PC_OK)
                    return st;
                if (!more)
                    break;
                if (fo.number == 1 && fo.wire == PB_BYTES)
                    domain = fo.bytes;
                if (fo.number == 2 && fo.wire == PB_VARINT)
                    version = (int64_t)fo.varint;
            }
            if (domain.size == 0 || pb_slice_eq(domain, "ai.onnx"))
                b->opset = version;
        } else if (f.number == 14) {
            n_meta++;
        }
    }
    if (!has_graph)
        return pc_fail(b->err, PC_ERR_MALFORMED, "model has no graph (not an ONNX file?)");
    if (b->opset < 13 || b->opset > 21)
        return pc_fail(b->err, PC_ERR_UNSUPPORTED,
                       "default-domain opset %lld is not supported (13..21)", (long long)b->opset);
    b->meta = pc_scratch_alloc(&b->scratch, (n_meta + 1) * sizeof(pc_meta));
    if (!b->meta)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    pb_init(&r, b->file, whole);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if (f.number == 14) {
            pc_meta *m = &b->meta[b->n_meta++];
            pb_init(&ro, b->file, f.bytes);
            for (;;) {
                if ((st = pb_next(&ro, &fo, &more, b->err)) != PC_OK)
                    return st;
                if (!more)
                    break;
                if (fo.number == 1 && fo.wire == PB_BYTES)
                    m->key = fo.bytes;
                if (fo.number == 2 && fo.wire == PB_BYTES)
                    m->value = fo.bytes;
            }
        }
    }
    return pc_parse_graph(b, graph);
}

/* ---- public entry points ---------------------------------------------------------- */

pc_status pc_load_memory(const void *data, size_t size, const pc_options *opts,
                         pc_model **model, pc_error *err)
{
    pc_builder b;
    pc_error local;
    pc_status st;
    if (!err)
        err = &local;
    err->status = PC_OK;
    err->message[0] = '\0';
    if (!model)
        return pc_fail(err, PC_ERR_ARGUMENT, "model pointer is NULL");
    *model = NULL;
    if (!data && size)
        return pc_fail(err, PC_ERR_ARGUMENT, "data is NULL");
    if (size == 0)
        return pc_fail(err, PC_ERR_TRUNCATED, "truncated file at byte 0 (empty)");
    memset(&b, 0, sizeof b);
    b.err = err;
    b.file = (const uint8_t *)data;
    b.file_size = size;
    b.input_id = -1;
    b.output_id = -1;
    b.cpu_avx2 = -1;
    st = pc_parse_model(&b);
    if (st == PC_OK)
        st = pc_build(&b, opts, model);
    pc_scratch_release(&b.scratch);
    if (st != PC_OK && err->status == PC_OK)
        pc_fail(err, st, "%s", pc_status_name(st));
    return st;
}

pc_status pc_load_file(const char *path, const pc_options *opts, pc_model **model,
                       pc_error *err)
{
    FILE *fp;
    long len;
    uint8_t *buf;
    pc_status st;
    pc_error local;
    if (!err)
        err = &local;
    if (model)
        *model = NULL;
    if (!path || !model)
        return pc_fail(err, PC_ERR_ARGUMENT, "path or model pointer is NULL");
    fp = fopen(path, "rb");
    if (!fp)
        return pc_fail(err, PC_ERR_IO, "cannot open '%s'", path);
    if (fseek(fp, 0, SEEK_END) != 0 || (len = ftell(fp)) < 0 || fseek(fp, 0, SEEK_SET) != 0) {
        fclose(fp);
        return pc_fail(err, PC_ERR_IO, "cannot determine the size of '%s'", path);
    }
    buf = (uint8_t *)malloc(len > 0 ? (size_t)len : 1);
    if (!buf) {
        fclose(fp);
        return pc_fail(err, PC_ERR_MEMORY, "out of memory reading '%s'", path);
    }
    if (len > 0 && fread(buf, 1, (size_t)len, fp) != (size_t)len) {
        fclose(fp);
        free(buf);
        return pc_fail(err, PC_ERR_IO, "cannot read '%s'", path);
    }
    fclose(fp);
    st = pc_load_memory(buf, (size_t)len, opts, model, err);
    free(buf);
    return st;
}

void pc_free(pc_model *model)
{
    free(model);
}

size_t pc_metadata_count(const pc_model *model)
{
    return model ? model->n_meta : 0;
}

const char *pc_metadata_key(const pc_model *model, size_t index)
{
    return model && index < model->n_meta ? model->meta_key[index] : NULL;
}

const char *pc_metadata_value(const pc_model *model, size_t index)
{
    return model && index < model->n_meta ? model->meta_value[index] : NULL;
}

const char *pc_metadata_lookup(const pc_model *model, const char *key)
{
    size_t i;
    if (!model || !key)
        return NULL;
    for (i = 0; i < model->n_meta; i++)
        if (strcmp(model->meta_key[i], key) == 0)
            return model->meta_value[i];
    return NULL;
}

size_t pc_max_batch(const pc_model *model) { return model ? model->max_batch : 0; }
size_t pc_arena_bytes(const pc_model *model) { return model ? model->arena_bytes : 0; }
size_t pc_step_count(const pc_model *model)
{
    return model && model->n_plans ? model->plans[0].n_steps : 0;
}
size_t pc_node_count(const pc_model *model) { return model ? model->n_nodes : 0; }
const char *pc_model_message(const pc_model *model) { return model ? model->message : ""; }
