/* Graph passes, in order: every operator known, nodes sorted topologically, nodes that
 * reach no output dropped, initializer-only subgraphs folded into constants, Gemm +
 * Tanh/Sigmoid/Relu/Clip fused. */
#include "passes.h"

#include <string.h>

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
    for (i = 0; i < b->n_outputs; i++)
        needed[b->outputs[i].id] = 1;
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
    for (i = 0; i < b->n_outputs; i++)
        b->values[b->outputs[i].id].consumers = 1;
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
        if (v < 0 || pc_is_output(b, v) || b->values[v].consumers != 1)
            continue;
        a = &b->nodes[consumer[v]];
        if (a->n_in < 1 || a->in[0] != v || a->n_out != 1 || a->out[0] < 0)
            continue;
        act = pc_act_of(b, a, &lo, &hi);
        if (act == PC_ACT_NONE)
            continue;
        /* v's only reader is the activation: Tanh/Sigmoid/Relu have no other input and
         * Clip's bounds go into the Gemm parameters. */
        g->act = act;
        g->act_lo = lo;
        g->act_hi = hi;
        g->out[0] = a->out[0];
        b->values[a->out[0]].producer = (int)i;
        a->fused_away = 1;
    }
    return PC_OK;
}

pc_status pc_run_passes(pc_builder *b)
{
    pc_status st;
    if ((st = pc_check_ops(b)) != PC_OK || (st = pc_toposort(b)) != PC_OK ||
        (st = pc_mark_live(b)) != PC_OK || (st = pc_fold(b)) != PC_OK)
        return st;
    return pc_fuse(b);
}
