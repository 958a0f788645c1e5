/* The graph scan: two walks over the file's nodes leave a few bytes per node and value
 * (pc_builder's scan arrays); names live only while the scan runs. */
#include "graph.h"

#include <string.h>

/* Names of the graph while the scan runs (work end): an open-addressing table from a
 * name to what it is (a node output, an initializer or a graph input). */
typedef struct pc_names {
    uint32_t *hash;
    uint16_t *ref;       /* 0: empty slot */
    size_t mask;
    pb_slice *out_name;  /* per ordinal */
    pb_slice *init_name; /* per initializer */
} pc_names;

static uint32_t pc_hash(pb_slice s)
{
    uint32_t h = 2166136261u;
    size_t i;
    for (i = 0; i < s.size; i++)
        h = (h ^ s.data[i]) * 16777619u;
    return h;
}

static pb_slice pc_ref_name(const pc_builder *b, const pc_names *t, uint16_t ref)
{
    const unsigned k = PC_REF_INDEX(ref);
    switch (PC_REF_KIND(ref)) {
    case PC_REF_OUTPUT: return t->out_name[k];
    case PC_REF_INIT: return t->init_name[k];
    default: return b->inputs[k].name;
    }
}

/* The slot of name: where it is, or the empty slot where it would go. */
static size_t pc_names_slot(const pc_builder *b, const pc_names *t, pb_slice name, uint32_t h)
{
    size_t i = h & t->mask;
    while (t->ref[i] && !(t->hash[i] == h && pb_slice_same(pc_ref_name(b, t, t->ref[i]), name)))
        i = (i + 1) & t->mask;
    return i;
}

static uint16_t pc_names_find(const pc_builder *b, const pc_names *t, pb_slice name)
{
    return t->ref[pc_names_slot(b, t, name, pc_hash(name))];
}

/* Adds name as ref; returns what already had the name (0 when new). */
static uint16_t pc_names_add(const pc_builder *b, pc_names *t, pb_slice name, uint16_t ref)
{
    const uint32_t h = pc_hash(name);
    const size_t i = pc_names_slot(b, t, name, h);
    if (t->ref[i])
        return t->ref[i];
    t->hash[i] = h;
    t->ref[i] = ref;
    return 0;
}

static const char *pc_kind_name(uint16_t ref)
{
    switch (PC_REF_KIND(ref)) {
    case PC_REF_OUTPUT: return "a node output";
    case PC_REF_INIT: return "an initializer";
    default: return "a graph input";
    }
}

/* ---- walk 1: operators, sizes, initializers ---------------------------------------- */

static pc_status pc_scan_sizes(pc_builder *b, size_t *max_in, size_t *max_out)
{
    pb_reader r;
    pb_slice msg;
    int more;
    uint32_t i = 0;
    size_t refs = 0, ordinals = 0;
    pc_status st;
    *max_in = *max_out = 0;
    pb_init(&r, b->file, b->graph);
    while ((more = onnx_next_node(b, &r, &msg)) == PB_FIELD) {
        const pc_scratch_mark mark = pc_scratch_save(&b->scratch, PC_WORK);
        pc_node n;
        int op;
        if ((st = onnx_parse_node(b, msg, i, &n)) != PC_OK)
            return st;
        if (!(n.domain.size == 0 || pb_slice_eq(n.domain, "ai.onnx")))
            return pc_fail(b->err, PC_ERR_UNSUPPORTED,
                           "unsupported operator %.*s (domain '%.*s') in node '%.*s'",
                           PC_NAME(n.op_type), PC_NAME(n.domain), PC_NAME(n.name));
        if ((op = pc_op_lookup(n.op_type)) < 0)
            return pc_fail(b->err, PC_ERR_UNSUPPORTED, "unsupported operator %.*s in node '%.*s'",
                           PC_NAME(n.op_type), PC_NAME(n.name));
        b->node_op[i++] = (uint8_t)op;
        refs += n.n_in;
        ordinals += n.n_out;
        if (n.n_in > *max_in)
            *max_in = n.n_in;
        if (n.n_out > *max_out)
            *max_out = n.n_out;
        pc_scratch_restore(&b->scratch, mark);
    }
    if (more == PB_ERROR)
        return r.status;
    if (refs > 0xfff0u || ordinals > PC_MAX_INDEX)
        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "graph too large (%zu node inputs, %zu node "
                       "outputs; the runtime takes 65520 and 16383)", refs, ordinals);
    b->n_refs = (uint32_t)refs;
    b->n_ordinals = (uint32_t)ordinals;
    return PC_OK;
}

static pc_status pc_scan_inits(pc_builder *b)
{
    pb_reader r;
    pb_field f;
    int more;
    uint32_t k = 0;
    b->inits = pc_scratch_alloc(&b->scratch, PC_KEEP, (b->n_inits + 1) * sizeof(pb_slice));
    if (!b->inits)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    pb_init(&r, b->file, b->graph);
    while ((more = pb_next(&r, &f, b->err)) == PB_FIELD)
        if (f.number == ONNX_GRAPH_INITIALIZER)
            b->inits[k++] = f.bytes;
    return more == PB_ERROR ? r.status : PC_OK;
}

static pc_status pc_names_start(pc_builder *b, pc_names *t)
{
    const size_t entries = b->n_ordinals + b->n_inits + b->n_inputs;
    size_t size = 16, k;
    pc_status st;
    /* At most 4/5 full: linear probing stays short, and the table is the scan's largest
     * part (a small target's load peaks here). */
    while (4 * size < 5 * entries)
        size *= 2;
    t->mask = size - 1;
    t->hash = pc_scratch_alloc_raw(&b->scratch, PC_WORK, size * sizeof *t->hash);
    t->ref = pc_scratch_alloc(&b->scratch, PC_WORK, size * sizeof *t->ref);
    t->out_name = pc_scratch_alloc(&b->scratch, PC_WORK, (b->n_ordinals + 1) * sizeof(pb_slice));
    t->init_name = pc_scratch_alloc(&b->scratch, PC_WORK, (b->n_inits + 1) * sizeof(pb_slice));
    if (!t->hash || !t->ref || !t->out_name || !t->init_name)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (k = 0; k < b->n_inputs; k++)
        pc_names_add(b, t, b->inputs[k].name, PC_REF(PC_REF_INPUT, k));
    for (k = 0; k < b->n_inits; k++) {
        onnx_tensor tensor;
        uint16_t had;
        if ((st = onnx_tensor_header(b, b->inits[k], &tensor)) != PC_OK)
            return st;
        t->init_name[k] = tensor.name;
        had = pc_names_add(b, t, tensor.name, PC_REF(PC_REF_INIT, k));
        if (had && PC_REF_KIND(had) == PC_REF_INIT)
            return pc_fail(b->err, PC_ERR_GRAPH, "initializer '%.*s' is defined twice",
                           PC_NAME(tensor.name));
    }
    return PC_OK;
}

/* ---- walk 2: names to references ----------------------------------------------------- */

/* After the walk: the first input read before (or without) its producer, and the graph's
 * outputs, each to the value that produces it. */
static pc_status pc_resolve_ends(pc_builder *b, pc_names *t, pb_slice missing, pb_slice missing_node)
{
    uint32_t j;
    if (missing.data) {
        if (pc_names_find(b, t, missing))
            return pc_fail(b->err, PC_ERR_GRAPH, "graph has a cycle or is not topologically "
                           "sorted: node '%.*s' reads '%.*s' before the node that produces it",
                           PC_NAME(missing_node), PC_NAME(missing));
        return pc_fail(b->err, PC_ERR_GRAPH, "input '%.*s' of node '%.*s' is not produced by any "
                       "node, initializer or graph input", PC_NAME(missing), PC_NAME(missing_node));
    }
    for (j = 0; j < b->n_outputs; j++) {
        b->outputs[j].ref = pc_names_find(b, t, b->outputs[j].name);
        if (!b->outputs[j].ref)
            return pc_fail(b->err, PC_ERR_GRAPH, "graph output '%.*s' is not produced by any node",
                           PC_NAME(b->outputs[j].name));
    }
    return PC_OK;
}

static pc_status pc_scan_refs(pc_builder *b, pc_names *t)
{
    pb_reader r;
    pb_slice msg;
    int more;
    uint32_t i = 0, ref = 0, ord = 0, j;
    pc_status st;
    /* The first input read before (or without) its producer, reported after the walk:
     * only then is it known whether a later node produces it. */
    pb_slice missing = {NULL, 0}, missing_node = {NULL, 0};
    pb_init(&r, b->file, b->graph);
    while ((more = onnx_next_node(b, &r, &msg)) == PB_FIELD) {
        const pc_scratch_mark mark = pc_scratch_save(&b->scratch, PC_WORK);
        pc_node n;
        if ((st = onnx_parse_node(b, msg, i, &n)) != PC_OK)
            return st;
        b->node_in0[i] = (uint16_t)ref;
        b->node_out0[i] = (uint16_t)ord;
        for (j = 0; j < n.n_in; j++, ref++) {
            uint16_t found = 0;
            if (n.in_names[j].size)
                found = pc_names_find(b, t, n.in_names[j]);
            if (n.in_names[j].size && !found && !missing.data) {
                missing = n.in_names[j];
                missing_node = n.name;
            }
            b->in_ref[ref] = found;
        }
        for (j = 0; j < n.n_out; j++, ord++) {
            uint16_t had;
            t->out_name[ord] = n.out_names[j];
            if (!n.out_names[j].size)
                continue;
            had = pc_names_add(b, t, n.out_names[j], PC_REF(PC_REF_OUTPUT, ord));
            if (had)
                return pc_fail(b->err, PC_ERR_GRAPH, "'%.*s' (output of node '%.*s') is already "
                               "%s: every value of a graph is produced once",
                               PC_NAME(n.out_names[j]), PC_NAME(n.name), pc_kind_name(had));
        }
        pc_scratch_restore(&b->scratch, mark);
        i++;
    }
    if (more == PB_ERROR)
        return r.status;
    b->node_in0[i] = (uint16_t)ref;
    b->node_out0[i] = (uint16_t)ord;
    return pc_resolve_ends(b, t, missing, missing_node);
}

/* ---- dead nodes, folding ------------------------------------------------------------- */

static int pc_node_live(const pc_builder *b, uint32_t i)
{
    return b->node_op[i] != PC_NODE_SKIP;
}

/* Nodes that reach no graph output are skipped (walking backwards, a node is needed
 * when one of its outputs is). */
static pc_status pc_scan_dead(pc_builder *b)
{
    uint8_t *needed = pc_scratch_alloc(&b->scratch, PC_WORK, b->n_ordinals + 1);
    uint32_t i, j;
    if (!needed)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (j = 0; j < b->n_outputs; j++)
        if (PC_REF_KIND(b->outputs[j].ref) == PC_REF_OUTPUT)
            needed[PC_REF_INDEX(b->outputs[j].ref)] = 1;
    for (i = b->n_nodes; i-- > 0;) {
        int live = 0;
        for (j = b->node_out0[i]; j < b->node_out0[i + 1]; j++)
            live |= needed[j];
        if (!live) {
            b->node_op[i] = PC_NODE_SKIP;
            continue;
        }
        for (j = b->node_in0[i]; j < b->node_in0[i + 1]; j++)
            if (PC_REF_KIND(b->in_ref[j]) == PC_REF_OUTPUT)
                needed[PC_REF_INDEX(b->in_ref[j])] = 1;
    }
    return PC_OK;
}

pc_status pc_const_input(pc_builder *b, uint16_t ref, int end, int32_t *id)
{
    const unsigned k = PC_REF_INDEX(ref);
    *id = -1;
    if (PC_REF_KIND(ref) == PC_REF_INIT) {
        onnx_tensor t;
        void *data;
        pc_status st;
        if ((st = onnx_tensor_header(b, b->inits[k], &t)) != PC_OK ||
            (st = onnx_tensor_data(b, b->inits[k], &t, end, &data)) != PC_OK)
            return st;
        return pc_value_const(b, t.dtype, (int)t.rank, t.dims, data, (int32_t)k, id);
    }
    if (PC_REF_KIND(ref) == PC_REF_OUTPUT) {
        const pc_const *c = pc_const_find(b, k);
        if (c) {
            int64_t dims[PC_MAX_RANK];
            int j;
            for (j = 0; j < c->rank; j++)
                dims[j] = c->dims[j];
            return pc_value_const(b, c->dtype, c->rank, dims, c->data, pc_key_ordinal(b, k), id);
        }
    }
    return PC_OK;
}

/* Node i with its records: inputs (constants or -1 for run-time values and omitted
 * ones) and fresh output records. */
static pc_status pc_scan_node(pc_builder *b, uint32_t i, pc_node *n, int32_t *in_ids,
                              int32_t *out_ids)
{
    pb_reader r;
    pb_slice msg;
    uint32_t k = 0, j;
    int more;
    pc_status st;
    pb_init(&r, b->file, b->graph);
    while ((more = onnx_next_node(b, &r, &msg)) == PB_FIELD && k < i)
        k++;
    if (more != PB_FIELD)
        return more == PB_ERROR ? r.status : pc_fail(b->err, PC_ERR_GRAPH, "node %lu vanished", (unsigned long)i);
    if ((st = onnx_parse_node(b, msg, i, n)) != PC_OK)
        return st;
    n->op = b->node_op[i];
    for (j = 0; j < n->n_in; j++)
        if ((st = pc_const_input(b, b->in_ref[b->node_in0[i] + j], PC_WORK, &in_ids[j])) != PC_OK)
            return st;
    for (j = 0; j < n->n_out; j++) {
        out_ids[j] = -1;
        if (!n->out_names[j].size)
            continue;
        if ((st = pc_value_new(b, &out_ids[j])) != PC_OK)
            return st;
        b->values[out_ids[j]].ordinal = (int32_t)(b->node_out0[i] + j);
    }
    return PC_OK;
}

static void pc_release_all(pc_builder *b)
{
    size_t k;
    for (k = 0; k < b->cap_values; k++)
        b->values[k].used = 0;
}

/* Computes node i's outputs now; they become constants (keep end). */
static pc_status pc_fold_node(pc_builder *b, uint32_t i)
{
    pc_node n;
    pc_prep p;
    int32_t *ids = pc_scratch_alloc(&b->scratch, PC_WORK, 2 * b->cap_values * sizeof(int32_t));
    pc_step step;
    void **io;
    size_t j;
    pc_status st;
    if (!ids)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    if ((st = pc_scan_node(b, i, &n, ids, ids + b->cap_values)) != PC_OK ||
        (st = pc_prepare_node(b, &n, ids, ids + b->cap_values, 1, &p)) != PC_OK)
        return st;
    if (p.alias_of >= 0) {
        const pc_value *src = &b->values[p.alias_of], *o = p.out[0];
        pc_const *c;
        if ((st = pc_const_add(b, (uint32_t)o->ordinal, o, &c)) != PC_OK)
            return st;
        memcpy(c->data, src->cdata, o->count * pc_dtype_size(o->dtype));
        return PC_OK;
    }
    io = pc_scratch_alloc(&b->scratch, PC_WORK, (p.n_in + p.n_out + 1) * sizeof(void *));
    if (!io)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (j = 0; j < p.n_in; j++)
        io[j] = p.in_ids[j] >= 0 ? b->values[p.in_ids[j]].cdata : NULL;
    for (j = 0; j < p.n_out; j++) {
        const pc_value *o = p.out[j];
        pc_const *c;
        if (!o)
            continue;
        if ((st = pc_const_add(b, (uint32_t)o->ordinal, o, &c)) != PC_OK)
            return st;
        io[p.n_in + j] = c->data;
    }
    step.fn = p.fn;
    step.io = io;
    step.prm = p.prm;
    step.n = p.out[0] ? p.out[0]->count : 0;
    if ((st = step.fn(&step)) != PC_OK)
        return pc_prep_fail(&p, st, "failed while folding constants");
    return PC_OK;
}

/* Nodes whose inputs are all constants run once now. */
static pc_status pc_scan_fold(pc_builder *b)
{
    uint32_t i, j;
    pc_status st;
    for (i = 0; i < b->n_nodes; i++) {
        pc_scratch_mark mark;
        int all_const = 1;
        if (!pc_node_live(b, i))
            continue;
        for (j = b->node_in0[i]; j < b->node_in0[i + 1] && all_const; j++) {
            const uint16_t ref = b->in_ref[j];
            if (PC_REF_KIND(ref) == PC_REF_INPUT ||
                (PC_REF_KIND(ref) == PC_REF_OUTPUT && !pc_const_find(b, PC_REF_INDEX(ref))))
                all_const = 0;
        }
        if (!all_const)
            continue;
        mark = pc_scratch_save(&b->scratch, PC_WORK);
        st = pc_fold_node(b, i);
        pc_release_all(b);
        pc_scratch_restore(&b->scratch, mark);
        if (st != PC_OK)
            return st;
        b->node_op[i] = PC_NODE_SKIP;
    }
    return PC_OK;
}

/* ---- last readers, fusion, width ------------------------------------------------------ */

static void pc_scan_last_use(pc_builder *b, uint8_t *readers)
{
    uint32_t i, j;
    for (j = 0; j < b->n_ordinals; j++) {
        b->last_use[j] = PC_USE_NONE;
        readers[j] = 0;
    }
    for (i = 0; i < b->n_nodes; i++) {
        if (!pc_node_live(b, i))
            continue;
        for (j = b->node_in0[i]; j < b->node_in0[i + 1]; j++)
            if (PC_REF_KIND(b->in_ref[j]) == PC_REF_OUTPUT) {
                const unsigned o = PC_REF_INDEX(b->in_ref[j]);
                b->last_use[o] = (uint16_t)i;
                if (readers[o] < 2)
                    readers[o]++;
            }
    }
    for (j = 0; j < b->n_outputs; j++)
        if (PC_REF_KIND(b->outputs[j].ref) == PC_REF_OUTPUT) {
            b->last_use[PC_REF_INDEX(b->outputs[j].ref)] = PC_USE_FOREVER;
            readers[PC_REF_INDEX(b->outputs[j].ref)] = 2;
        }
}

/* The activation node a applies to its input 0, or PC_ACT_NONE (Clip: constant bounds). */
static pc_status pc_act_of(pc_builder *b, uint32_t a, int *act, float *lo, float *hi)
{
    const uint32_t n_in = (uint32_t)(b->node_in0[a + 1] - b->node_in0[a]);
    uint32_t j;
    pc_status st;
    *lo = -3.402823466e38f;
    *hi = 3.402823466e38f;
    switch (b->node_op[a]) {
    case PC_OP_Tanh: *act = PC_ACT_TANH; return PC_OK;
    case PC_OP_Sigmoid: *act = PC_ACT_SIGMOID; return PC_OK;
    case PC_OP_Relu: *act = PC_ACT_RELU; return PC_OK;
    case PC_OP_Clip: break;
    default: *act = PC_ACT_NONE; return PC_OK;
    }
    *act = PC_ACT_NONE;
    if (n_in > 3)
        return PC_OK;
    for (j = 1; j < n_in; j++) {
        const pc_scratch_mark mark = pc_scratch_save(&b->scratch, PC_WORK);
        const uint16_t ref = b->in_ref[b->node_in0[a] + j];
        int32_t id = -1;
        int ok;
        float x = 0.0f;
        if (!ref)
            continue;
        if ((st = pc_const_input(b, ref, PC_WORK, &id)) != PC_OK)
            return st;
        ok = id >= 0 && b->values[id].dtype == PC_F32 && b->values[id].count == 1;
        if (ok)
            memcpy(&x, b->values[id].cdata, sizeof x);
        pc_value_release(b, id);
        pc_scratch_restore(&b->scratch, mark);
        if (!ok)
            return PC_OK;
        if (j == 1)
            *lo = x;
        else
            *hi = x;
    }
    *act = PC_ACT_CLIP;
    return PC_OK;
}

/* The node that reads output o as its only reader, through its input 0, and has one
 * output; or -1. */
static int64_t pc_sole_reader(const pc_builder *b, const uint8_t *readers, uint32_t o)
{
    uint32_t a;
    if (readers[o] != 1 || b->last_use[o] >= PC_USE_FOREVER)
        return -1;
    a = b->last_use[o];
    if (b->node_out0[a + 1] - b->node_out0[a] != 1 ||
        b->in_ref[b->node_in0[a]] != PC_REF(PC_REF_OUTPUT, o))
        return -1;
    return a;
}

/* Radbas as an exporter writes it, exp(-(x * x)), after output o: Mul(o, o), the only
 * reader of o, then Neg and Exp, each the only reader of the one before. The Exp node
 * (the Mul and the Neg in *mul_node and *neg_node), or -1. */
static int64_t pc_radbas_after(const pc_builder *b, const uint8_t *readers, uint32_t o,
                               uint32_t *mul_node, uint32_t *neg_node)
{
    const uint16_t ref = PC_REF(PC_REF_OUTPUT, o);
    uint32_t mul, j, refs = 0;
    int64_t neg, exp_node;
    if (b->last_use[o] >= PC_USE_FOREVER)
        return -1;
    mul = b->last_use[o];
    if (b->node_op[mul] != PC_OP_Mul || b->node_in0[mul + 1] - b->node_in0[mul] != 2 ||
        b->in_ref[b->node_in0[mul]] != ref || b->in_ref[b->node_in0[mul] + 1] != ref ||
        b->node_out0[mul + 1] - b->node_out0[mul] != 1)
        return -1;
    for (j = 0; j < b->n_refs; j++) /* readers[] stops counting at two */
        refs += b->in_ref[j] == ref;
    if (refs != 2)
        return -1;
    neg = pc_sole_reader(b, readers, b->node_out0[mul]);
    if (neg < 0 || b->node_op[neg] != PC_OP_Neg)
        return -1;
    exp_node = pc_sole_reader(b, readers, b->node_out0[neg]);
    if (exp_node < 0 || b->node_op[exp_node] != PC_OP_Exp)
        return -1;
    *mul_node = mul;
    *neg_node = (uint32_t)neg;
    return exp_node;
}

/* A Gemm whose only reader is an activation (or radbas's three nodes) takes it over: the
 * activation's readers read the Gemm's output instead. */
static pc_status pc_scan_fuse(pc_builder *b, const uint8_t *readers)
{
    uint32_t g, j;
    pc_fused *f;
    pc_status st;
    for (g = 0; g < b->n_nodes; g++) {
        uint32_t og, oa, mul, neg;
        int64_t a;
        int act = PC_ACT_NONE;
        float lo = 0.0f, hi = 0.0f;
        if (b->node_op[g] != PC_OP_Gemm || b->node_out0[g + 1] - b->node_out0[g] != 1)
            continue;
        og = b->node_out0[g];
        if ((a = pc_sole_reader(b, readers, og)) >= 0 &&
            (st = pc_act_of(b, (uint32_t)a, &act, &lo, &hi)) != PC_OK)
            return st;
        if (act == PC_ACT_NONE && (a = pc_radbas_after(b, readers, og, &mul, &neg)) >= 0) {
            /* only the Exp's output is read on */
            b->node_op[mul] = PC_NODE_SKIP;
            b->node_op[neg] = PC_NODE_SKIP;
            act = PC_ACT_RADBAS;
        }
        if (act == PC_ACT_NONE)
            continue;
        oa = b->node_out0[a];
        for (j = 0; j < b->n_refs; j++)
            if (b->in_ref[j] == PC_REF(PC_REF_OUTPUT, oa))
                b->in_ref[j] = PC_REF(PC_REF_OUTPUT, og);
        for (j = 0; j < b->n_outputs; j++)
            if (b->outputs[j].ref == PC_REF(PC_REF_OUTPUT, oa))
                b->outputs[j].ref = PC_REF(PC_REF_OUTPUT, og);
        b->last_use[og] = b->last_use[oa];
        b->node_op[a] = PC_NODE_SKIP;
        if (!(f = pc_scratch_alloc(&b->scratch, PC_KEEP, sizeof *f)))
            return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        f->node = g;
        f->act = act;
        f->lo = lo;
        f->hi = hi;
        f->next = b->fused;
        b->fused = f;
    }
    return PC_OK;
}

/* Records a plan pass holds at once: the run-time values alive at a node, with the
 * node's operands (constants get a record for the moment), the graph inputs, and the
 * records of the graph outputs at the end. */
static pc_status pc_scan_width(pc_builder *b)
{
    uint16_t *dies = pc_scratch_alloc(&b->scratch, PC_WORK, (b->n_nodes + 1) * sizeof(uint16_t));
    size_t alive = 0, peak = 0;
    uint32_t i, j;
    if (!dies)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < b->n_nodes; i++)
        for (j = b->node_out0[i]; j < b->node_out0[i + 1]; j++) {
            const uint16_t last = b->last_use[j];
            if (!pc_node_live(b, i) || last == PC_USE_FOREVER)
                continue;
            dies[last == PC_USE_NONE ? i : last]++;
        }
    for (i = 0; i < b->n_nodes; i++) {
        const size_t n_out = b->node_out0[i + 1] - b->node_out0[i];
        const size_t n_in = b->node_in0[i + 1] - b->node_in0[i];
        if (!pc_node_live(b, i))
            continue;
        if (alive + n_in + n_out > peak)
            peak = alive + n_in + n_out;
        alive += n_out;
        alive -= dies[i];
    }
    if (alive > peak)
        peak = alive;
    b->max_live = peak;
    b->cap_values = peak + b->n_inputs + b->n_outputs + 1;
    return PC_OK;
}

/* What the scan leaves for the passes (keep end): the operator of each node, every input
 * resolved, each value's last reader, the fused activations and folded constants. What
 * only the scan reads (each node's first input and output, the names, the readers) is on
 * the work end and gone when it returns: the passes count inputs and outputs as they
 * stream the nodes. */
pc_status pc_scan_graph(pc_builder *b)
{
    size_t n_io, max_in, max_out;
    pc_scratch_mark mark, scan_mark;
    pc_names names;
    uint8_t *readers;
    pc_status st;
    if ((st = onnx_scan_model(b)) != PC_OK ||
        (st = onnx_graph_counts(b, &b->n_nodes, &b->n_inits, &n_io)) != PC_OK ||
        (st = pc_scan_inits(b)) != PC_OK || (st = onnx_parse_io(b, n_io)) != PC_OK)
        return st;
    scan_mark = pc_scratch_save(&b->scratch, PC_WORK);
    b->node_op = pc_scratch_alloc(&b->scratch, PC_KEEP, b->n_nodes + 1);
    b->node_in0 = pc_scratch_alloc(&b->scratch, PC_WORK, (b->n_nodes + 1) * sizeof(uint16_t));
    b->node_out0 = pc_scratch_alloc(&b->scratch, PC_WORK, (b->n_nodes + 1) * sizeof(uint16_t));
    if (!b->node_op || !b->node_in0 || !b->node_out0)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    if ((st = pc_scan_sizes(b, &max_in, &max_out)) != PC_OK)
        return st;
    b->in_ref = pc_scratch_alloc(&b->scratch, PC_KEEP, (b->n_refs + 1) * sizeof(uint16_t));
    b->last_use = pc_scratch_alloc(&b->scratch, PC_KEEP, (b->n_ordinals + 1) * sizeof(uint16_t));
    if (!b->in_ref || !b->last_use)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    mark = pc_scratch_save(&b->scratch, PC_WORK);
    if ((st = pc_names_start(b, &names)) != PC_OK || (st = pc_scan_refs(b, &names)) != PC_OK)
        return st;
    pc_scratch_restore(&b->scratch, mark);
    if ((st = pc_scan_dead(b)) != PC_OK)
        return st;
    pc_scratch_restore(&b->scratch, mark);
    /* Records for folding: one node's operands at a time. */
    b->cap_values = max_in + max_out + 4;
    b->values = pc_scratch_alloc(&b->scratch, PC_WORK, b->cap_values * sizeof(pc_value));
    if (!b->values)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    if ((st = pc_scan_fold(b)) != PC_OK)
        return st;
    readers = pc_scratch_alloc(&b->scratch, PC_WORK, b->n_ordinals + 1);
    if (!readers)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    pc_scan_last_use(b, readers);
    if ((st = pc_scan_fuse(b, readers)) != PC_OK || (st = pc_scan_width(b)) != PC_OK)
        return st;
    pc_scratch_restore(&b->scratch, scan_mark);
    b->values = NULL;
    b->node_in0 = b->node_out0 = NULL;
    return PC_OK;
}
