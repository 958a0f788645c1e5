/* Graph validation and planning.
 *
 * Steps: check every operator against the table, sort topologically, drop nodes that do
 * not reach 'corrected', fold initializer-only subgraphs, fuse Gemm + activation, then
 * build static plans for batches of 1, 16, 256, ... and max_batch (shapes, kernel
 * choice, buffer offsets by liveness) and pack everything into one arena. pc_run then
 * does no shape work: it walks a precomputed array of kernel launches. */
#include "pc_internal.h"

#include <stdlib.h>
#include <string.h>

#define PC_INF_STEP 0x7fffffff

/* ---- helpers for operator prepare functions --------------------------------------- */

pc_status pc_prep_fail(pc_prep *p, pc_status st, const char *fmt, ...)
{
    char detail[PC_MESSAGE_SIZE];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(detail, sizeof detail, fmt, ap);
    va_end(ap);
    return pc_fail(p->b->err, st, "node '%.*s' (%.*s): %s", (int)p->node->name.size,
                   (const char *)p->node->name.data, (int)p->node->op_type.size,
                   (const char *)p->node->op_type.data, detail);
}

/* Finds attribute `name`; *msg is its AttributeProto. */
static pc_status pc_attr_msg(pc_prep *p, const char *name, pb_slice *msg, int *found)
{
    uint32_t a;
    pb_reader r;
    pb_field f;
    int more;
    pc_status st;
    *found = 0;
    for (a = 0; a < p->node->n_attr; a++) {
        pb_init(&r, p->b->file, p->node->attr[a]);
        for (;;) {
            if ((st = pb_next(&r, &f, &more, p->b->err)) != PC_OK)
                return st;
            if (!more)
                break;
            if (f.number == 1 && f.wire == PB_BYTES && pb_slice_eq(f.bytes, name)) {
                *msg = p->node->attr[a];
                *found = 1;
                return PC_OK;
            }
        }
    }
    return PC_OK;
}

/* Scalar field `number` of attribute `name`. */
static pc_status pc_attr_scalar(pc_prep *p, const char *name, uint32_t number, uint32_t wire,
                                pb_field *out, int *found)
{
    pb_slice msg;
    pb_reader r;
    pb_field f;
    int more, has;
    pc_status st;
    *found = 0;
    if ((st = pc_attr_msg(p, name, &msg, &has)) != PC_OK || !has)
        return st;
    pb_init(&r, p->b->file, msg);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, p->b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if (f.number == number) {
            if (f.wire != wire)
                return pc_prep_fail(p, PC_ERR_MALFORMED, "attribute '%s' has wire type %u",
                                    name, f.wire);
            *out = f;
            *found = 1;
        }
    }
    if (!*found)
        return pc_prep_fail(p, PC_ERR_MALFORMED, "attribute '%s' has no value of the expected type",
                            name);
    return PC_OK;
}

pc_status pc_attr_int(pc_prep *p, const char *name, int64_t def, int64_t *out)
{
    pb_field f;
    int found;
    pc_status st = pc_attr_scalar(p, name, 3, PB_VARINT, &f, &found);
    *out = found ? (int64_t)f.varint : def;
    return st;
}

pc_status pc_attr_float(pc_prep *p, const char *name, float def, float *out)
{
    pb_field f;
    int found;
    pc_status st = pc_attr_scalar(p, name, 2, PB_FIXED32, &f, &found);
    *out = found ? pb_bits_to_float((uint32_t)f.varint) : def;
    return st;
}

static pc_status pc_attr_repeated(pc_prep *p, const char *name, uint32_t number, uint32_t wire,
                                  int64_t *ints, float *floats, size_t cap, size_t *n, int *found)
{
    pb_slice msg;
    pb_reader r;
    pb_field f;
    int more;
    pc_status st;
    *n = 0;
    if ((st = pc_attr_msg(p, name, &msg, found)) != PC_OK || !*found)
        return st;
    pb_init(&r, p->b->file, msg);
    for (;;) {
        if ((st = pb_next(&r, &f, &more, p->b->err)) != PC_OK)
            return st;
        if (!more)
            break;
        if (f.number == number &&
            (st = pb_decode_repeated(p->b->file, &f, wire, ints, floats, cap, n, p->b->err)) !=
                PC_OK)
            return st;
    }
    return PC_OK;
}

pc_status pc_attr_ints(pc_prep *p, const char *name, int64_t *buf, size_t cap, size_t *n,
                       int *found)
{
    return pc_attr_repeated(p, name, 8, PB_VARINT, buf, NULL, cap, n, found);
}

pc_status pc_attr_floats(pc_prep *p, const char *name, float *buf, size_t cap, size_t *n,
                         int *found)
{
    return pc_attr_repeated(p, name, 7, PB_FIXED32, NULL, buf, cap, n, found);
}

pc_status pc_attr_tensor(pc_prep *p, const char *name, pb_slice *tensor, int *found)
{
    pb_field f;
    pc_status st = pc_attr_scalar(p, name, 5, PB_BYTES, &f, found);
    if (*found)
        *tensor = f.bytes;
    return st;
}

int pc_has_attr(pc_prep *p, const char *name)
{
    pb_slice msg;
    int found = 0;
    if (pc_attr_msg(p, name, &msg, &found) != PC_OK)
        return 0;
    return found;
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
    for (i = 0; i < rank; i++) {
        if (dims[i] < 0 || (dims[i] > 0 && count > ((size_t)1 << 24) / (size_t)dims[i]))
            return pc_prep_fail(p, PC_ERR_SHAPE, "output dimension %d is invalid (%lld)", i,
                                (long long)dims[i]);
        count *= (size_t)dims[i];
    }
    v->dtype = dtype;
    v->rank = rank;
    for (i = 0; i < rank; i++)
        v->dims[i] = dims[i];
    v->count = count;
    return PC_OK;
}

void *pc_prep_params(pc_prep *p, size_t size)
{
    p->prm = pc_scratch_alloc(&p->b->scratch, size);
    p->prm_size = size;
    return p->prm;
}

pc_status pc_new_const(pc_prep *p, int dtype, int rank, const int64_t *dims, void **data,
                       int32_t *id)
{
    pb_slice none = {NULL, 0};
    pc_status st = pc_alloc_const(p->b, none, dtype, rank, dims, id);
    if (st != PC_OK)
        return st;
    *data = p->b->values[*id].cdata;
    return PC_OK;
}

int32_t pc_find_derived(pc_builder *b, int32_t src, int kind)
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

/* ---- passes ----------------------------------------------------------------------- */

static pc_status pc_check_ops(pc_builder *b)
{
    size_t i;
    for (i = 0; i < b->n_nodes; i++) {
        pc_node *n = &b->nodes[i];
        if (!(n->domain.size == 0 || pb_slice_eq(n->domain, "ai.onnx")))
            return pc_fail(b->err, PC_ERR_UNSUPPORTED,
                           "unsupported operator %.*s (domain '%.*s') in node '%.*s'",
                           (int)n->op_type.size, (const char *)n->op_type.data,
                           (int)n->domain.size, (const char *)n->domain.data,
                           (int)n->name.size, (const char *)n->name.data);
        n->op = pc_op_lookup(n->op_type);
        if (n->op < 0)
            return pc_fail(b->err, PC_ERR_UNSUPPORTED, "unsupported operator %.*s in node '%.*s'",
                           (int)n->op_type.size, (const char *)n->op_type.data,
                           (int)n->name.size, (const char *)n->name.data);
    }
    return PC_OK;
}

static pc_status pc_toposort(pc_builder *b)
{
    int32_t *indeg = pc_scratch_alloc(&b->scratch, (b->n_nodes + 1) * sizeof(int32_t));
    int32_t *first = pc_scratch_alloc(&b->scratch, (b->n_values + 1) * sizeof(int32_t));
    size_t total = 0, i, j, head = 0, tail = 0;
    int32_t *next, *who;
    for (i = 0; i < b->n_nodes; i++)
        total += b->nodes[i].n_in;
    next = pc_scratch_alloc(&b->scratch, (total + 1) * sizeof(int32_t));
    who = pc_scratch_alloc(&b->scratch, (total + 1) * sizeof(int32_t));
    b->order = pc_scratch_alloc(&b->scratch, (b->n_nodes + 1) * sizeof(int32_t));
    if (!indeg || !first || !next || !who || !b->order)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < b->n_values; i++)
        first[i] = -1;
    /* Edge list value -> consuming node, as singly linked lists per value. */
    total = 0;
    for (i = 0; i < b->n_nodes; i++) {
        const pc_node *n = &b->nodes[i];
        for (j = 0; j < n->n_in; j++) {
            const int32_t v = n->in[j];
            if (v < 0 || b->values[v].producer < 0)
                continue;
            indeg[i]++;
            who[total] = (int32_t)i;
            next[total] = first[v];
            first[v] = (int32_t)total++;
        }
    }
    for (i = 0; i < b->n_nodes; i++)
        if (indeg[i] == 0)
            b->order[tail++] = (int32_t)i;
    while (head < tail) {
        const pc_node *n = &b->nodes[b->order[head++]];
        for (j = 0; j < n->n_out; j++) {
            int32_t e;
            if (n->out[j] < 0)
                continue;
            for (e = first[n->out[j]]; e >= 0; e = next[e])
                if (--indeg[who[e]] == 0)
                    b->order[tail++] = who[e];
        }
    }
    if (tail != b->n_nodes)
        return pc_fail(b->err, PC_ERR_GRAPH, "graph has a cycle (%zu of %zu nodes sortable)", tail,
                       b->n_nodes);
    return PC_OK;
}

static pc_status pc_mark_live(pc_builder *b)
{
    uint8_t *needed = pc_scratch_alloc(&b->scratch, b->n_values + 1);
    size_t i, j;
    if (!needed)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    needed[b->output_id] = 1;
    for (i = b->n_nodes; i-- > 0;) {
        pc_node *n = &b->nodes[b->order[i]];
        for (j = 0; j < n->n_out; j++)
            if (n->out[j] >= 0 && needed[n->out[j]])
                n->live = 1;
        if (n->live)
            for (j = 0; j < n->n_in; j++)
                if (n->in[j] >= 0)
                    needed[n->in[j]] = 1;
    }
    return PC_OK;
}

static pc_status pc_prepare_node(pc_builder *b, pc_node *n, int folding, pc_prep *p)
{
    size_t j;
    pc_status st;
    memset(p, 0, sizeof *p);
    p->b = b;
    p->node = n;
    p->n_in = n->n_in;
    p->n_out = n->n_out;
    p->folding = folding;
    p->alias_of = -1;
    {
        /* One block per node and plan: pointers first, so every part stays aligned. */
        const size_t n_io = (size_t)n->n_in + n->n_out + 2;
        pc_value **ptrs = pc_scratch_alloc(&b->scratch,
                                           n_io * (sizeof(pc_value *) + sizeof(int32_t)));
        if (!ptrs)
            return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        p->in = ptrs;
        p->out = ptrs + n->n_in + 1;
        p->in_ids = (int32_t *)(ptrs + n_io);
        p->out_ids = p->in_ids + n->n_in + 1;
    }
    for (j = 0; j < n->n_in; j++) {
        p->in_ids[j] = n->in[j];
        p->in[j] = n->in[j] >= 0 ? &b->values[n->in[j]] : NULL;
        if (p->in[j] && p->in[j]->dtype == 0)
            return pc_prep_fail(p, PC_ERR_GRAPH, "input %zu has no known type", j);
    }
    for (j = 0; j < n->n_out; j++) {
        p->out_ids[j] = n->out[j];
        p->out[j] = n->out[j] >= 0 ? &b->values[n->out[j]] : NULL;
    }
    if (n->n_out < 1 || n->out[0] < 0)
        return pc_prep_fail(p, PC_ERR_GRAPH, "output 0 is missing");
    st = pc_ops[n->op].prepare(p);
    if (st != PC_OK)
        return st;
    for (j = 0; j < n->n_out; j++)
        if (p->out[j] && p->out[j]->dtype == 0)
            return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "output %zu is not supported", j);
    if (!p->fn && p->alias_of < 0)
        return pc_prep_fail(p, PC_ERR_UNSUPPORTED, "no kernel for these input types");
    return PC_OK;
}

static pc_status pc_fold(pc_builder *b)
{
    size_t i, j;
    pc_status st;
    for (i = 0; i < b->n_nodes; i++) {
        pc_node *n = &b->nodes[b->order[i]];
        pc_prep p;
        pc_step step;
        void **io;
        int all_const = 1;
        if (!n->live)
            continue;
        for (j = 0; j < n->n_in; j++)
            if (n->in[j] >= 0 && !b->values[n->in[j]].cdata)
                all_const = 0;
        if (!all_const)
            continue;
        if ((st = pc_prepare_node(b, n, 1, &p)) != PC_OK)
            return st;
        n->folded = 1;
        if (p.alias_of >= 0) {
            b->values[n->out[0]].cdata = b->values[p.alias_of].cdata;
            continue;
        }
        /* Operands as the prepare function left them (it may pad or drop inputs). */
        io = pc_scratch_alloc(&b->scratch, (p.n_in + p.n_out + 1) * sizeof(void *));
        if (!io)
            return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        for (j = 0; j < p.n_in; j++)
            io[j] = p.in_ids[j] >= 0 ? b->values[p.in_ids[j]].cdata : NULL;
        for (j = 0; j < p.n_out; j++) {
            pc_value *v = p.out[j];
            if (!v)
                continue;
            v->cdata = pc_scratch_alloc(&b->scratch, v->count * pc_dtype_size(v->dtype));
            if (!v->cdata)
                return pc_fail(b->err, PC_ERR_MEMORY, "out of memory folding constants");
            io[p.n_in + j] = v->cdata;
        }
        step.fn = p.fn;
        step.io = io;
        step.prm = p.prm;
        step.n = p.out[0] ? p.out[0]->count : 0;
        if ((st = step.fn(&step)) != PC_OK)
            return pc_prep_fail(&p, st, "failed while folding constants");
    }
    return PC_OK;
}

static int pc_act_of(const pc_builder *b, const pc_node *n, float *lo, float *hi)
{
    *lo = 0.0f;
    *hi = 0.0f;
    switch (n->op) {
    case PC_OP_Tanh: return PC_ACT_TANH;
    case PC_OP_Sigmoid: return PC_ACT_SIGMOID;
    case PC_OP_Relu: return PC_ACT_RELU;
    case PC_OP_Clip: {
        const pc_value *vlo = n->n_in > 1 && n->in[1] >= 0 ? &b->values[n->in[1]] : NULL;
        const pc_value *vhi = n->n_in > 2 && n->in[2] >= 0 ? &b->values[n->in[2]] : NULL;
        *lo = -3.402823466e38f;
        *hi = 3.402823466e38f;
        if (vlo && (!vlo->cdata || vlo->dtype != PC_F32 || vlo->count != 1))
            return PC_ACT_NONE;
        if (vhi && (!vhi->cdata || vhi->dtype != PC_F32 || vhi->count != 1))
            return PC_ACT_NONE;
        if (vlo)
            *lo = *(const float *)vlo->cdata;
        if (vhi)
            *hi = *(const float *)vhi->cdata;
        return PC_ACT_CLIP;
    }
    default: return PC_ACT_NONE;
    }
}

static pc_status pc_fuse(pc_builder *b)
{
    int32_t *consumer = pc_scratch_alloc(&b->scratch, (b->n_values + 1) * sizeof(int32_t));
    size_t i, j;
    if (!consumer)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < b->n_values; i++)
        b->values[i].consumers = 0;
    b->values[b->output_id].consumers = 1;
    for (i = 0; i < b->n_nodes; i++) {
        const pc_node *n = &b->nodes[i];
        if (!n->live || n->folded)
            continue;
        for (j = 0; j < n->n_in; j++)
            if (n->in[j] >= 0) {
                b->values[n->in[j]].consumers++;
                consumer[n->in[j]] = (int32_t)i;
            }
    }
    for (i = 0; i < b->n_nodes; i++) {
        pc_node *g = &b->nodes[i], *a;
        int32_t v;
        int act;
        float lo, hi;
        if (!g->live || g->folded || g->op != PC_OP_Gemm || g->n_out != 1)
            continue;
        v = g->out[0];
        if (v < 0 || v == b->output_id || b->values[v].consumers != 1)
            continue;
        a = &b->nodes[consumer[v]];
        if (a->n_in < 1 || a->in[0] != v || a->n_out != 1 || a->out[0] < 0)
            continue;
        act = pc_act_of(b, a, &lo, &hi);
        if (act == PC_ACT_NONE)
            continue;
        /* The activation's input slot is the only reader of v; reuse its other inputs? No:
         * Tanh/Sigmoid/Relu have none, Clip's bounds are folded into the Gemm parameters. */
        g->act = act;
        g->act_lo = lo;
        g->act_hi = hi;
        g->out[0] = a->out[0];
        b->values[a->out[0]].producer = (int)i;
        a->fused_away = 1;
    }
    return PC_OK;
}

/* ---- planning --------------------------------------------------------------------- */

typedef struct pc_plan_draft {
    size_t batch;
    pc_draft *drafts;
    size_t n_drafts;
    size_t **loc;       /* per draft, per io: location code (see pc_loc) */
    size_t in_loc, out_loc;
    size_t act_bytes;
} pc_plan_draft;

/* Location code: bit 0 set = constant region; SIZE_MAX = absent. */
#define PC_LOC_NONE ((size_t)-1)

static int32_t pc_root(const pc_builder *b, int32_t v)
{
    while (b->values[v].alias >= 0)
        v = b->values[v].alias;
    return v;
}

static size_t pc_round(size_t x)
{
    return (x + PC_ALIGN - 1) / PC_ALIGN * PC_ALIGN;
}

static pc_status pc_add_draft(pc_builder *b, const pc_prep *p)
{
    pc_draft *d;
    size_t j;
    if (b->n_drafts == b->n_nodes)
        return pc_fail(b->err, PC_ERR_GRAPH, "more kernel launches than nodes");
    d = &b->drafts[b->n_drafts++];
    d->fn = p->fn;
    d->n_io = (uint32_t)(p->n_in + p->n_out);
    d->io = pc_scratch_alloc(&b->scratch, (d->n_io + 1) * sizeof(int32_t));
    if (!d->io)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (j = 0; j < p->n_in; j++)
        d->io[j] = p->in_ids[j];
    for (j = 0; j < p->n_out; j++)
        d->io[p->n_in + j] = p->out_ids[j];
    d->prm = p->prm;
    d->prm_size = p->prm_size;
    d->n = p->out[0] ? p->out[0]->count : 0;
    return PC_OK;
}

static size_t pc_const_loc(pc_builder *b, int32_t r, size_t *const_bytes)
{
    pc_value *v = &b->values[r];
    if (v->const_slot < 0) {
        v->const_slot = 1;
        v->const_offset = *const_bytes;
        *const_bytes += pc_round(v->count * pc_dtype_size(v->dtype) + 1);
    }
    return (v->const_offset << 1) | 1;
}

static pc_status pc_plan_batch(pc_builder *b, size_t batch, pc_plan_draft *pd,
                               size_t *const_bytes)
{
    size_t i, j, k, n_roots = 0;
    pc_status st;
    int32_t *roots;
    pc_value *in;
    /* At most one launch per node; every field is written by pc_add_draft. */
    b->n_drafts = 0;
    b->drafts = pc_scratch_alloc_raw(&b->scratch, (b->n_nodes + 1) * sizeof *b->drafts);
    if (!b->drafts)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < b->n_values; i++) {
        pc_value *v = &b->values[i];
        v->alias = -1;
        v->def = PC_INF_STEP;
        v->last = -1;
        if (!v->cdata) {
            v->dtype = 0;
            v->rank = 0;
            v->count = 0;
        }
    }
    in = &b->values[b->input_id];
    in->dtype = PC_F32;
    in->rank = 2;
    in->dims[0] = (int64_t)batch;
    in->dims[1] = PC_POSE_WIDTH;
    in->count = batch * PC_POSE_WIDTH;
    in->def = -1;
    for (i = 0; i < b->n_nodes; i++) {
        pc_node *n = &b->nodes[b->order[i]];
        pc_prep p;
        if (!n->live || n->folded || n->fused_away)
            continue;
        if ((st = pc_prepare_node(b, n, 0, &p)) != PC_OK)
            return st;
        if (p.alias_of >= 0) {
            pc_value *o = p.out[0];
            int32_t r = pc_root(b, p.alias_of);
            if (b->values[r].cdata)
                o->cdata = b->values[r].cdata;
            else
                o->alias = r;
            continue;
        }
        if ((st = pc_add_draft(b, &p)) != PC_OK)
            return st;
    }
    {
        const pc_value *o = &b->values[b->output_id];
        if (o->dtype != PC_F32 || o->rank != 2 || o->dims[0] != (int64_t)batch ||
            o->dims[1] != PC_POSE_WIDTH)
            return pc_fail(b->err, PC_ERR_CONTRACT,
                           "output 'corrected' is %s of rank %d (%lld x %lld) for N=%zu, the "
                           "contract needs float32 [N,7]", pc_dtype_name(o->dtype), o->rank,
                           (long long)(o->rank > 0 ? o->dims[0] : -1),
                           (long long)(o->rank > 1 ? o->dims[1] : -1), batch);
    }
    /* Liveness per storage root. */
    for (i = 0; i < b->n_drafts; i++) {
        const pc_draft *d = &b->drafts[i];
        const size_t n_in = d->n_io - (size_t)0;
        (void)n_in;
        for (j = 0; j < d->n_io; j++) {
            int32_t r;
            if (d->io[j] < 0)
                continue;
            r = pc_root(b, d->io[j]);
            if (b->values[r].cdata)
                continue;
            if (b->values[r].def > (int32_t)i)
                b->values[r].def = (int32_t)i;
            if (b->values[r].last < (int32_t)i)
                b->values[r].last = (int32_t)i;
        }
    }
    {
        int32_t r = pc_root(b, b->input_id);
        b->values[r].def = -1;
        if (b->values[r].last < 0)
            b->values[r].last = 0;
        r = pc_root(b, b->output_id);
        if (!b->values[r].cdata) {
            b->values[r].last = PC_INF_STEP;
            if (b->values[r].def == PC_INF_STEP)
                b->values[r].def = -1;
        }
    }
    /* Greedy first-fit over lifetimes, in order of definition. */
    roots = pc_scratch_alloc(&b->scratch, (b->n_values + 1) * sizeof(int32_t));
    if (!roots)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < b->n_values; i++) {
        pc_value *v = &b->values[i];
        if (v->alias < 0 && !v->cdata && v->def != PC_INF_STEP)
            roots[n_roots++] = (int32_t)i;
    }
    for (i = 1; i < n_roots; i++) { /* insertion sort by def; n is small */
        int32_t x = roots[i];
        for (k = i; k > 0 && b->values[roots[k - 1]].def > b->values[x].def; k--)
            roots[k] = roots[k - 1];
        roots[k] = x;
    }
    pd->act_bytes = 0;
    {
        size_t *sizes = pc_scratch_alloc(&b->scratch, (n_roots + 1) * sizeof(size_t));
        if (!sizes)
            return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        for (i = 0; i < n_roots; i++) {
            const pc_value *v = &b->values[roots[i]];
            sizes[i] = pc_round(v->count * pc_dtype_size(v->dtype) + 1);
        }
        size_t n_active = 0;
        int32_t *active = pc_scratch_alloc(&b->scratch, (n_roots + 1) * sizeof(int32_t));
        if (!active)
            return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        for (i = 0; i < n_roots; i++) {
            pc_value *v = &b->values[roots[i]];
            size_t off = 0, m, kept = 0;
            /* Roots come in order of definition, so a placed buffer that died before
             * this one is defined can never overlap a later one: drop it for good. The
             * active list stays sorted by offset, so the first gap is one sweep away. */
            for (k = 0; k < n_active; k++)
                if (b->values[roots[active[k]]].last >= v->def)
                    active[kept++] = active[k];
            n_active = kept;
            for (m = 0; m < n_active; m++) {
                const pc_value *q = &b->values[roots[active[m]]];
                if (off + sizes[i] <= q->offset)
                    break;
                if (q->offset + sizes[active[m]] > off)
                    off = q->offset + sizes[active[m]];
            }
            v->offset = off;
            for (m = n_active; m > 0 && b->values[roots[active[m - 1]]].offset > off; m--)
                active[m] = active[m - 1];
            active[m] = (int32_t)i;
            n_active++;
            if (off + sizes[i] > pd->act_bytes)
                pd->act_bytes = off + sizes[i];
        }
    }
    /* Resolve every operand to a location. */
    pd->batch = batch;
    pd->drafts = b->drafts;
    pd->n_drafts = b->n_drafts;
    pd->loc = pc_scratch_alloc(&b->scratch, (b->n_drafts + 1) * sizeof(size_t *));
    if (!pd->loc)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < b->n_drafts; i++) {
        const pc_draft *d = &b->drafts[i];
        pd->loc[i] = pc_scratch_alloc(&b->scratch, (d->n_io + 1) * sizeof(size_t));
        if (!pd->loc[i])
            return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        for (j = 0; j < d->n_io; j++) {
            int32_t r;
            if (d->io[j] < 0) {
                pd->loc[i][j] = PC_LOC_NONE;
                continue;
            }
            r = pc_root(b, d->io[j]);
            pd->loc[i][j] = b->values[r].cdata ? pc_const_loc(b, r, const_bytes)
                                               : b->values[r].offset << 1;
        }
    }
    {
        int32_t r = pc_root(b, b->input_id);
        pd->in_loc = b->values[r].offset << 1;
        r = pc_root(b, b->output_id);
        pd->out_loc = b->values[r].cdata ? pc_const_loc(b, r, const_bytes)
                                         : b->values[r].offset << 1;
    }
    return PC_OK;
}

pc_status pc_build(pc_builder *b, const pc_options *opts, pc_model **model_out)
{
    size_t max_batch = opts && opts->max_batch ? opts->max_batch : PC_DEFAULT_MAX_BATCH;
    size_t n_plans = 0, k, i, j, const_bytes = 0, size, act_bytes = 0, meta_bytes = 0;
    size_t step_bytes = 0, batch;
    pc_plan_draft *pds;
    pc_status st;
    uint8_t *arena, *cursor, *const_base, *act_base;
    pc_model *m;

    if (max_batch > PC_MAX_MAX_BATCH)
        max_batch = PC_MAX_MAX_BATCH;
    for (k = 1; 2 * k <= max_batch; k *= 2)
        ;
    max_batch = k;
    /* Plans for N = 1, 16, 256, ... and max_batch: planning is most of the load time, and
     * a remainder below 16 poses runs pose by pose at little cost per pose. */
    for (k = 1; k < max_batch; k *= PC_PLAN_STRIDE)
        n_plans++;
    n_plans++;

    if ((st = pc_check_ops(b)) != PC_OK || (st = pc_toposort(b)) != PC_OK ||
        (st = pc_mark_live(b)) != PC_OK || (st = pc_fold(b)) != PC_OK ||
        (st = pc_fuse(b)) != PC_OK)
        return st;
    pds = pc_scratch_alloc(&b->scratch, n_plans * sizeof *pds);
    if (!pds)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (k = 0, batch = 1; k < n_plans; k++, batch *= PC_PLAN_STRIDE) {
        if ((st = pc_plan_batch(b, batch < max_batch ? batch : max_batch, &pds[k],
                                &const_bytes)) != PC_OK)
            return st;
        if (pds[k].act_bytes > act_bytes)
            act_bytes = pds[k].act_bytes;
        step_bytes += pc_round(pds[k].n_drafts * sizeof(pc_step) + 1);
        for (i = 0; i < pds[k].n_drafts; i++)
            step_bytes += pc_round(pds[k].drafts[i].n_io * sizeof(void *) + 1) +
                          pc_round(pds[k].drafts[i].prm_size + 1);
    }
    for (i = 0; i < b->n_meta; i++)
        meta_bytes += b->meta[i].key.size + b->meta[i].value.size + 2;
    size = pc_round(sizeof(pc_model)) + pc_round(n_plans * sizeof(pc_plan)) +
           pc_round(2 * (b->n_meta + 1) * sizeof(char *)) + pc_round(meta_bytes + 1) +
           step_bytes + const_bytes + act_bytes + PC_ALIGN;
    if (size > ((size_t)1 << 29))
        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "model needs a %zu-byte arena (limit 512 MiB)",
                       size);
    arena = (uint8_t *)malloc(size);
    if (!arena)
        return pc_fail(b->err, PC_ERR_MEMORY, "cannot allocate the %zu-byte model arena", size);
    memset(arena, 0, size);
    /* Layout: model | plans | metadata | steps (per plan: steps, io, params) | constants |
     * activations. Steps of one plan are contiguous so a single-pose run stays in a few
     * cache lines. */
    m = (pc_model *)arena;
    cursor = arena + pc_round(sizeof(pc_model));
    m->arena_bytes = size;
    m->max_batch = max_batch;
    m->n_plans = n_plans;
    m->n_nodes = b->n_nodes;
    m->plans = (pc_plan *)cursor;
    cursor += pc_round(n_plans * sizeof(pc_plan));
    m->n_meta = b->n_meta;
    m->meta_key = (const char **)cursor;
    m->meta_value = m->meta_key + b->n_meta + 1;
    cursor += pc_round(2 * (b->n_meta + 1) * sizeof(char *));
    {
        char *s = (char *)cursor;
        for (i = 0; i < b->n_meta; i++) {
            memcpy(s, b->meta[i].key.data ? (const void *)b->meta[i].key.data : "", b->meta[i].key.size);
            s[b->meta[i].key.size] = '\0';
            m->meta_key[i] = s;
            s += b->meta[i].key.size + 1;
            memcpy(s, b->meta[i].value.data ? (const void *)b->meta[i].value.data : "",
                   b->meta[i].value.size);
            s[b->meta[i].value.size] = '\0';
            m->meta_value[i] = s;
            s += b->meta[i].value.size + 1;
        }
        cursor += pc_round(meta_bytes + 1);
    }
    const_base = cursor + step_bytes;
    act_base = const_base + const_bytes;
    act_base = (uint8_t *)(((uintptr_t)act_base + PC_ALIGN - 1) / PC_ALIGN * PC_ALIGN);
    for (i = 0; i < b->n_values; i++) {
        const pc_value *v = &b->values[i];
        if (v->cdata && v->const_slot >= 0)
            memcpy(const_base + v->const_offset, v->cdata, v->count * pc_dtype_size(v->dtype));
    }
#define PC_RESOLVE(loc) \
    ((loc) == PC_LOC_NONE ? NULL : ((loc)&1) ? (void *)(const_base + ((loc) >> 1)) \
                                             : (void *)(act_base + ((loc) >> 1)))
    for (k = 0; k < n_plans; k++) {
        pc_plan *plan = &m->plans[k];
        const pc_plan_draft *pd = &pds[k];
        pc_step *steps = (pc_step *)cursor;
        cursor += pc_round(pd->n_drafts * sizeof(pc_step) + 1);
        plan->batch = pd->batch;
        plan->steps = steps;
        plan->n_steps = pd->n_drafts;
        plan->in = (float *)PC_RESOLVE(pd->in_loc);
        plan->out = (const float *)PC_RESOLVE(pd->out_loc);
        for (i = 0; i < pd->n_drafts; i++) {
            const pc_draft *d = &pd->drafts[i];
            void **io = (void **)cursor;
            cursor += pc_round(d->n_io * sizeof(void *) + 1);
            for (j = 0; j < d->n_io; j++)
                io[j] = PC_RESOLVE(pd->loc[i][j]);
            steps[i].fn = d->fn;
            steps[i].io = io;
            steps[i].n = d->n;
            if (d->prm_size) {
                memcpy(cursor, d->prm, d->prm_size);
                steps[i].prm = cursor;
            }
            cursor += pc_round(d->prm_size + 1);
        }
    }
#undef PC_RESOLVE
    *model_out = m;
    return PC_OK;
}
