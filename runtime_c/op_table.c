/* The table of operators (generated from export/operators.txt) and the one call the
 * graph scan and the planner make into the operator layer: prepare a node. */
#include "op.h"

#include <string.h>

pc_status pc_prepare_node(pc_builder *b, pc_node *n, const int32_t *in_ids,
                          const int32_t *out_ids, int folding, pc_prep *p)
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
        pc_value **ptrs = pc_scratch_alloc(&b->scratch, PC_WORK,
                                           n_io * (sizeof(pc_value *) + sizeof(int32_t)));
        if (!ptrs)
            return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
        p->in = ptrs;
        p->out = ptrs + n->n_in + 1;
        p->in_ids = (int32_t *)(ptrs + n_io);
        p->out_ids = p->in_ids + n->n_in + 1;
    }
    for (j = 0; j < n->n_in; j++) {
        p->in_ids[j] = in_ids[j];
        p->in[j] = in_ids[j] >= 0 ? &b->values[in_ids[j]] : NULL;
        if (p->in[j] && p->in[j]->dtype == 0)
            return pc_prep_fail(p, PC_ERR_GRAPH, "input %zu has no known type", j);
    }
    for (j = 0; j < n->n_out; j++) {
        p->out_ids[j] = out_ids[j];
        p->out[j] = out_ids[j] >= 0 ? &b->values[out_ids[j]] : NULL;
    }
    if (n->n_out < 1 || out_ids[0] < 0)
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

/* ---- the table -------------------------------------------------------------------- */

const pc_op_info pc_ops[PC_OP_COUNT] = {
#define PC_OP(name) [PC_OP_##name] = {#name, pc_op_##name},
#include "pc_operators.def"
#undef PC_OP
};

int pc_op_lookup(pb_slice name)
{
    int i;
    for (i = 0; i < PC_OP_COUNT; i++)
        if (pb_slice_eq(name, pc_ops[i].name))
            return i;
    return -1;
}
