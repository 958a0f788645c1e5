/* Planning: for each batch size the graph streams past once, node by node: prepare it
 * (shapes, kernel, parameters), give its outputs activation blocks (first fit, freed
 * after their last reader), and write its step, or add it to the open one-pose
 * program. Only the values alive at the current node have records. The whole walk is
 * made twice with the same code: sizing, then filling an arena of exactly the size found.
 * pc_run then does no shape work: it walks a precomputed array of kernel launches. */
#include "plan.h"
#include "graph.h"
#include "program.h"

#include <stdlib.h>
#include <string.h>

/* The record of node output `ordinal`, alive in this pass. */
static int32_t pc_record_of(const pc_builder *b, uint32_t ordinal)
{
    size_t k;
    for (k = 0; k < b->cap_values; k++)
        if (b->values[k].used && b->values[k].ordinal == (int32_t)ordinal)
            return (int32_t)k;
    return -1;
}

/* The record of a reference: a graph input, a live output, or a constant's record made
 * for the moment (*temp set: the caller releases it). */
static pc_status pc_resolve(pc_pass *pp, uint16_t ref, int32_t *id, int *temp)
{
    pc_builder *b = pp->b;
    pc_status st;
    *id = -1;
    *temp = 0;
    switch (PC_REF_KIND(ref)) {
    case PC_REF_NONE: return PC_OK;
    case PC_REF_INPUT: *id = pp->input_ids[PC_REF_INDEX(ref)]; return PC_OK;
    case PC_REF_OUTPUT:
        if (!pc_const_find(b, PC_REF_INDEX(ref))) {
            *id = pc_record_of(b, PC_REF_INDEX(ref));
            return *id >= 0 ? PC_OK : pc_fail(b->err, PC_ERR_GRAPH, "value %lu read after its "
                                              "last reader", (unsigned long)PC_REF_INDEX(ref));
        }
        break;
    default: break;
    }
    if ((st = pc_const_input(b, ref, PC_WORK, id)) != PC_OK)
        return st;
    *temp = 1;
    return PC_OK;
}

/* ---- steps of MLP layers ------------------------------------------------------------- */

/* One-pose plans: consecutive MLP layers, each reading the one before's output, are one
 * launch (k_gemm_chain), each layer run by the function of its shape. The chain is the last
 * step written, so it grows in place: its operands and parameters are the last entries of
 * their regions. */
static pc_status pc_emit_layer(pc_pass *pp, const pc_prep *p)
{
    const int avx2 = p->fn == pc_gemm_rows_kernels[1];
    const int32_t in_block = pp->b->values[p->in_ids[0]].block;
    pc_region *io_r = &pp->region[PC_REGION_IO], *prm_r = &pp->region[PC_REGION_PARAMS];
    const int32_t ids[4] = {p->in_ids[0], p->in_ids[1], p->in_ids[2], p->out_ids[0]};
    size_t k, n;
    void **io;
    pc_gemm_chain *q;
    const char *why;
    pc_status st;
    if (!(pp->last_layer == 1 + avx2 && in_block >= 0 && in_block == pp->last_out)) {
        pp->chain_io = io_r->used;
        pp->chain_prm = prm_r->used;
        pp->chain_layers = 0;
        pp->last_step = pc_region_take(pp, PC_REGION_STEPS, sizeof(pc_step));
        pp->n_steps++;
        if (pp->last_step) {
            pp->last_step->fn = k_gemm_chain;
            pp->last_step->io = (void *const *)(io_r->base + pp->chain_io);
            pp->last_step->prm = prm_r->base + pp->chain_prm;
        }
    }
    n = ++pp->chain_layers;
    io_r->used = pp->chain_io + pc_region_round(4 * n * sizeof(void *));
    prm_r->used = pp->chain_prm +
                  pc_region_round(sizeof(pc_gemm_chain) + (n - 1) * sizeof(pc_chain_layer));
    if (pp->fill) {
        io = (void **)(io_r->base + pp->chain_io) + 4 * (n - 1);
        q = (pc_gemm_chain *)(prm_r->base + pp->chain_prm);
        for (k = 0; k < 4; k++)
            if ((st = pc_locate(pp, &pp->b->values[ids[k]], &io[k])) != PC_OK)
                return st;
        q->n_layers = n;
        memcpy(&q->layer[n - 1].g, p->prm, sizeof(pc_gemm));
        q->layer[n - 1].fn = pc_chain_layer_fn(&q->layer[n - 1].g, avx2, &why);
        pp->last_step->n = p->out[0]->count;
    } else {
        void *at;
        for (k = 0; k < 4; k++) /* constants are placed in both passes alike */
            if ((st = pc_locate(pp, &pp->b->values[ids[k]], &at)) != PC_OK)
                return st;
    }
    pp->last_layer = 1 + avx2;
    pp->last_out = pp->b->values[p->out_ids[0]].block;
    return PC_OK;
}

/* ---- one node ----------------------------------------------------------------------------- */

static void pc_node_act(const pc_builder *b, uint32_t i, pc_node *n)
{
    const pc_fused *f;
    n->act = PC_ACT_NONE;
    n->act_lo = n->act_hi = 0.0f;
    for (f = b->fused; f; f = f->next)
        if (f->node == i) {
            n->act = f->act;
            n->act_lo = f->lo;
            n->act_hi = f->hi;
        }
}

/* Output record o is now a view of record src (Reshape, Squeeze, Identity, ...). */
static void pc_alias(pc_pass *pp, int32_t o, int32_t src)
{
    pc_value *v = &pp->b->values[o];
    const pc_value *s = &pp->b->values[src];
    if (s->cdata) {
        v->cdata = s->cdata;
        v->ckey = s->ckey;
    } else if (s->elems) {
        v->elems = s->elems;
    } else {
        v->block = s->block;
        pc_block_ref(pp, v->block);
    }
}

/* The node's value ids: its inputs resolved (temp[j]: a constant made for it), a new
 * record for each named output. */
static pc_status pc_node_values(pc_pass *pp, const pc_node *n, int32_t *ids, uint8_t *temp)
{
    pc_builder *b = pp->b;
    uint32_t j;
    pc_status st;
    for (j = 0; j < n->n_in; j++) {
        int t;
        if ((st = pc_resolve(pp, b->in_ref[pp->in0 + j], &ids[j], &t)) != PC_OK)
            return st;
        temp[j] = (uint8_t)t;
    }
    for (j = 0; j < n->n_out; j++) {
        int32_t *o = &ids[n->n_in + j];
        const uint32_t ord = pp->out0 + j;
        *o = -1;
        if (!n->out_names[j].size)
            continue;
        if ((st = pc_value_new(b, o)) != PC_OK)
            return st;
        b->values[*o].ordinal = (int32_t)ord;
        b->values[*o].last = b->last_use[ord];
    }
    return PC_OK;
}

/* A prepared node that neither aliases nor joins the open program: the program closed,
 * blocks for its outputs, and its step (a layer of a one-pose chain, or its kernel). */
static pc_status pc_node_step(pc_pass *pp, const pc_prep *p)
{
    pc_builder *b = pp->b;
    const size_t n_ids = p->n_in + p->n_out;
    int32_t *io;
    size_t k;
    pc_status st;
    if ((st = pc_program_close(pp)) != PC_OK)
        return st;
    for (k = 0; k < p->n_out; k++)
        if (p->out_ids[k] >= 0 && (st = pc_give_block(pp, p->out_ids[k])) != PC_OK)
            return st;
    if (pp->batch == 1 && p->layer)
        return pc_emit_layer(pp, p);
    io = pc_scratch_alloc(&b->scratch, PC_WORK, (n_ids + 1) * sizeof(int32_t));
    if (!io)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (k = 0; k < p->n_in; k++)
        io[k] = p->in_ids[k];
    for (k = 0; k < p->n_out; k++)
        io[p->n_in + k] = p->out_ids[k];
    return pc_emit_step(pp, p->fn, io, n_ids, p->prm, p->prm_size, p->out[0] ? p->out[0]->count : 0);
}

/* Node i, parsed as n; its inputs are refs pp->in0.., its outputs ordinals pp->out0.. */
static pc_status pc_plan_node(pc_pass *pp, uint32_t i, pc_node *n)
{
    pc_builder *b = pp->b;
    pc_prep p;
    int32_t *ids;
    uint8_t *temp;
    uint32_t j;
    size_t k;
    pc_status st;
    n->op = b->node_op[i];
    pc_node_act(b, i, n);
    ids = pc_scratch_alloc(&b->scratch, PC_WORK, (n->n_in + n->n_out + 1) * sizeof(int32_t));
    temp = pc_scratch_alloc(&b->scratch, PC_WORK, n->n_in + 1);
    if (!ids || !temp)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    if ((st = pc_node_values(pp, n, ids, temp)) != PC_OK ||
        (st = pc_prepare_node(b, n, ids, ids + n->n_in, 0, &p)) != PC_OK)
        return st;
    if (p.alias_of >= 0)
        pc_alias(pp, p.out_ids[0], p.alias_of);
    else if ((st = pc_program_takes(pp, &p) ? pc_program_expand(pp, &p) : pc_node_step(pp, &p)) != PC_OK)
        return st;
    /* Records whose last reader this node was, constants made for it, outputs nothing
     * reads. */
    for (j = 0; j < n->n_in; j++)
        if (temp[j])
            pc_value_release(b, ids[j]);
    for (k = 0; k < b->cap_values; k++) {
        const pc_value *v = &b->values[k];
        if (v->used && !v->input && v->ordinal >= 0 &&
            (v->last == i || (v->last == PC_USE_NONE && pp->out0 <= (uint32_t)v->ordinal &&
                              (uint32_t)v->ordinal < pp->out0 + n->n_out)))
            pc_drop(pp, (int32_t)k);
    }
    return PC_OK;
}

/* ---- one plan ------------------------------------------------------------------------------ */

static pc_status pc_plan_inputs(pc_pass *pp)
{
    pc_builder *b = pp->b;
    size_t k;
    int j;
    pc_status st;
    for (k = 0; k < b->n_inputs; k++) {
        const pc_io *io = &b->inputs[k];
        pc_value *v;
        if ((st = pc_value_new(b, &pp->input_ids[k])) != PC_OK)
            return st;
        v = &b->values[pp->input_ids[k]];
        v->input = 1;
        v->last = PC_USE_FOREVER;
        v->dtype = io->dtype;
        v->rank = io->rank;
        v->count = 1;
        for (j = 0; j < io->rank; j++) {
            v->dims[j] = j == 0 && !b->any_io ? (int64_t)pp->batch : io->dims[j];
            v->count *= (size_t)v->dims[j];
        }
        if ((st = pc_give_block(pp, pp->input_ids[k])) != PC_OK)
            return st;
    }
    return PC_OK;
}

/* The output against the contract's float32 [N,7], named with every dimension (a rank-6
 * result is not "(1 x 1)"); its own frame, off the load's deepest path. */
PC_RARE static pc_status pc_output_fault(const pc_builder *b, const pc_value *o, size_t batch)
{
    char shape[PC_MAX_RANK * 22 + 3] = "[";
    size_t used = 1;
    int j;
    for (j = 0; j < o->rank; j++) {
        pc_format(shape + used, sizeof shape - used, "%s%lld", j ? ", " : "",
                  (long long)o->dims[j]);
        used += strlen(shape + used);
    }
    pc_format(shape + used, sizeof shape - used, "]");
    return pc_fail(b->err, PC_ERR_CONTRACT,
                   "output 'corrected' is %s of shape %s for N=%zu, the contract needs float32 "
                   "[N,7]", pc_dtype_name(o->dtype), shape, batch);
}

static pc_status pc_check_output(const pc_builder *b, const pc_value *o, size_t batch)
{
    if (b->any_io || (o->dtype == PC_F32 && o->rank == 2 && o->dims[0] == (int64_t)batch &&
                      o->dims[1] == PC_POSE_WIDTH))
        return PC_OK;
    return pc_output_fault(b, o, batch);
}

/* Where the plan's inputs and outputs lie (plan->in, t, out; slots: every graph input and
 * output, for the conformance runs), each output checked against the contract. */
static pc_status pc_plan_ends(pc_pass *pp, size_t batch, pc_plan *plan, pc_slot *slots)
{
    pc_builder *b = pp->b;
    size_t k;
    pc_status st;
    for (k = 0; k < b->n_outputs; k++) {
        const pc_scratch_mark mark = pc_scratch_save(&b->scratch, PC_WORK);
        int32_t id;
        int temp;
        void *at;
        if ((st = pc_resolve(pp, b->outputs[k].ref, &id, &temp)) != PC_OK ||
            (st = pc_check_output(b, &b->values[id], batch)) != PC_OK ||
            (st = pc_locate(pp, &b->values[id], &at)) != PC_OK)
            return st;
        if (plan && k == 0)
            plan->out = (const float *)at;
        if (slots) {
            slots[b->n_inputs + k].data = at;
            slots[b->n_inputs + k].bytes = b->values[id].count * pc_dtype_size(b->values[id].dtype);
        }
        if (temp)
            pc_value_release(b, id);
        pc_scratch_restore(&b->scratch, mark);
    }
    for (k = 0; k < b->n_inputs; k++) {
        const pc_value *v = &b->values[pp->input_ids[k]];
        void *at = pc_block_at(pp, v->block);
        if (plan && k == 0)
            plan->in = (float *)at;
        if (plan && k == 1 && !b->any_io)
            plan->t = (float *)at;
        if (slots) {
            slots[k].data = at;
            slots[k].bytes = v->count * pc_dtype_size(v->dtype);
        }
    }
    return PC_OK;
}

/* The plan for `batch` poses; plan and slots are written in the filling pass. */
static pc_status pc_plan_one(pc_pass *pp, size_t batch, pc_plan *plan, pc_slot *slots)
{
    pc_builder *b = pp->b;
    pb_reader r;
    pb_slice msg;
    int more;
    uint32_t i = 0;
    pc_status st;
    memset(b->values, 0, b->cap_values * sizeof *b->values);
    memset(pp->blocks, 0, pp->cap_blocks * sizeof *pp->blocks);
    pp->n_live = 0;
    pp->batch = batch;
    pp->n_steps = 0;
    pp->last_step = NULL;
    pp->last_layer = 0;
    pp->defer_frees = 0;
    pp->in0 = pp->out0 = 0;
    if (plan)
        plan->steps = (pc_step *)(pp->region[PC_REGION_STEPS].base +
                                  pp->region[PC_REGION_STEPS].used);
    if ((st = pc_plan_inputs(pp)) != PC_OK)
        return st;
    pb_init(&r, b->file, b->graph);
    while ((more = onnx_next_node(b, &r, &msg)) == PB_FIELD) {
        const pc_scratch_mark mark = pc_scratch_save(&b->scratch, PC_WORK);
        pc_node n;
        st = onnx_parse_node(b, msg, i, &n);
        if (st == PC_OK && b->node_op[i] != PC_NODE_SKIP)
            st = pc_plan_node(pp, i, &n);
        pc_scratch_restore(&b->scratch, mark);
        if (st != PC_OK)
            return st;
        pp->in0 += n.n_in;
        pp->out0 += n.n_out;
        i++;
    }
    if (more == PB_ERROR)
        return r.status;
    if ((st = pc_program_close(pp)) != PC_OK || (st = pc_plan_ends(pp, batch, plan, slots)) != PC_OK)
        return st;
    if (plan) {
        plan->batch = batch;
        plan->n_steps = pp->n_steps;
    }
    return PC_OK;
}

/* ---- the arena -------------------------------------------------------------------------------- */

/* Sizes of the arena's parts. */
typedef struct pc_layout {
    size_t max_batch, n_plans;
    size_t n_meta, meta_bytes, slot_bytes, act_bytes, size;
    size_t region[PC_REGIONS];
} pc_layout;

static void pc_batches(const pc_builder *b, const pc_options *opts, pc_layout *L)
{
    size_t k;
    L->max_batch = opts && opts->max_batch ? opts->max_batch : PC_DEFAULT_MAX_BATCH;
    if (L->max_batch > PC_MAX_MAX_BATCH)
        L->max_batch = PC_MAX_MAX_BATCH;
    for (k = 1; 2 * k <= L->max_batch; k *= 2)
        ;
    L->max_batch = k;
    L->n_plans = 1;
    for (k = 1; k < L->max_batch; k *= PC_PLAN_STRIDE)
        L->n_plans++;
    if (b->any_io) /* static shapes: one plan */
        L->n_plans = L->max_batch = 1;
}

static size_t pc_plan_batch(const pc_layout *L, size_t k)
{
    size_t batch = 1;
    while (k--)
        batch *= PC_PLAN_STRIDE;
    return batch < L->max_batch ? batch : L->max_batch;
}

/* Every plan, once; fill: into the arena (model set), else only sizes into L. */
static pc_status pc_plan_pass(pc_pass *pp, pc_layout *L, pc_model *m)
{
    size_t k;
    pc_status st;
    for (k = 0; k < PC_REGIONS; k++)
        pp->region[k].used = 0;
    pp->n_placed = 0;
    pp->act_peak = 0;
    for (k = 0; k < L->n_plans; k++) {
        if ((st = pc_plan_one(pp, pc_plan_batch(L, k), m ? &m->plans[k] : NULL,
                              m && k == 0 ? m->slots : NULL)) != PC_OK)
            return st;
    }
    if (!m) {
        for (k = 0; k < PC_REGIONS; k++)
            L->region[k] = pp->region[k].used;
        L->act_bytes = pp->act_peak;
    }
    return PC_OK;
}

static pc_status pc_count_meta(pc_builder *b, pc_layout *L)
{
    pb_reader r;
    pb_slice whole, key, value;
    int more;
    whole.data = b->file;
    whole.size = b->file_size;
    pb_init(&r, b->file, whole);
    while ((more = onnx_next_meta(b, &r, &key, &value)) == PB_FIELD) {
        L->n_meta++;
        L->meta_bytes += key.size + value.size + 2;
    }
    return more == PB_ERROR ? r.status : PC_OK;
}

static char *pc_copy_string(char *dst, pb_slice s, const char **out)
{
    if (s.size)
        memcpy(dst, s.data, s.size);
    dst[s.size] = '\0';
    *out = dst;
    return dst + s.size + 1;
}

/* model | plans | slots | metadata | steps | operands | parameters | constants |
 * program constants | activations. */
static pc_model *pc_layout_model(pc_builder *b, const pc_layout *L, uint8_t *arena, pc_pass *pp)
{
    pc_model *m = (pc_model *)arena;
    uint8_t *cursor = arena + pc_round(sizeof(pc_model));
    pb_reader r;
    pb_slice whole, key, value;
    size_t i;
    char *s;
    m->arena_bytes = L->size;
    m->max_batch = L->max_batch;
    m->n_plans = L->n_plans;
    m->n_nodes = b->n_nodes;
    m->takes_time = !b->any_io && b->n_inputs == 2;
    m->plans = (pc_plan *)cursor;
    cursor += pc_round(L->n_plans * sizeof(pc_plan));
    if (b->any_io) {
        m->slots = (pc_slot *)cursor;
        m->n_in_slots = b->n_inputs;
        m->n_out_slots = b->n_outputs;
        cursor += L->slot_bytes;
    }
    m->n_meta = L->n_meta;
    m->meta_key = (const char **)cursor;
    m->meta_value = m->meta_key + L->n_meta + 1;
    cursor += pc_round(2 * (L->n_meta + 1) * sizeof(char *));
    whole.data = b->file;
    whole.size = b->file_size;
    pb_init(&r, b->file, whole);
    for (s = (char *)cursor, i = 0; i < L->n_meta &&
                                    onnx_next_meta(b, &r, &key, &value) == PB_FIELD; i++) {
        s = pc_copy_string(s, key, &m->meta_key[i]);
        s = pc_copy_string(s, value, &m->meta_value[i]);
    }
    cursor += pc_round(L->meta_bytes + 1);
    for (i = 0; i < PC_REGIONS; i++) {
        if (i == PC_REGION_KPOOL) {
            /* the pool ends where the activations start */
            pp->act_base = (uint8_t *)(((uintptr_t)cursor + L->region[i] + PC_ALIGN - 1) /
                                       PC_ALIGN * PC_ALIGN);
            cursor = pp->act_base - L->region[i];
        }
        pp->region[i].base = cursor;
        cursor += L->region[i];
    }
    pp->kpool_total = L->region[PC_REGION_KPOOL];
    m->act = pp->act_base;
    return m;
}

/* The arena: malloc'd, or the end of the caller's buffer (its start holds the scratch
 * still in use). */
static pc_status pc_arena(pc_builder *b, size_t size, void *buf, size_t buf_size,
                          uint8_t **arena)
{
    if (buf) {
        uint8_t *end = (uint8_t *)buf + buf_size;
        *arena = (uint8_t *)(((uintptr_t)end - size) / PC_ALIGN * PC_ALIGN);
        if (buf_size < size + PC_ALIGN || !pc_scratch_set_top(&b->scratch, *arena))
            return pc_fail(b->err, PC_ERR_MEMORY, "the %zu-byte buffer is too small for the "
                           "model (pc_required_bytes)", buf_size);
    } else if (!(*arena = (uint8_t *)malloc(size))) {
        return pc_fail(b->err, PC_ERR_MEMORY, "cannot allocate the %zu-byte model arena", size);
    }
    memset(*arena, 0, size);
    return PC_OK;
}

/* The sizing pass's records, as many as the scan says a pass may hold at once. */
static void pc_pass_bounds(pc_builder *b, pc_pass *pp)
{
    const pc_const *c;
    size_t n_consts = 0;
    for (c = b->consts; c; c = c->next)
        n_consts++;
    /* Blocks held at once: those of the records alive when a program opened (kept while
     * it is open), those it gives the records it leaves, and its temporaries. */
    pp->cap_blocks = 2 * b->cap_values + 2;
    pp->cap_placed = b->n_inits + n_consts + 1;
    b->values_high = pp->blocks_high = 0;
}

/* The filling pass's: as many as the sizing pass took (it makes the same choices, so it
 * takes the same ones), which leaves more of a small target's buffer to the arena. */
static void pc_pass_exact(pc_builder *b, pc_pass *pp)
{
    b->cap_values = b->values_high;
    pp->cap_blocks = pp->blocks_high;
    pp->cap_placed = pp->n_placed + 1;
}

/* The pass's records (keep end), of the sizes set above. */
static pc_status pc_pass_alloc(pc_builder *b, pc_pass *pp)
{
    b->values = pc_scratch_alloc(&b->scratch, PC_KEEP, b->cap_values * sizeof(pc_value));
    pp->blocks = pc_scratch_alloc(&b->scratch, PC_KEEP, pp->cap_blocks * sizeof(pc_block));
    pp->live = pc_scratch_alloc(&b->scratch, PC_KEEP, pp->cap_blocks * sizeof(int32_t));
    pp->placed = pc_scratch_alloc(&b->scratch, PC_KEEP, pp->cap_placed * sizeof(pc_placed));
    pp->input_ids = pc_scratch_alloc(&b->scratch, PC_KEEP, (b->n_inputs + 1) * sizeof(int32_t));
    if (!b->values || !pp->blocks || !pp->live || !pp->placed || !pp->input_ids)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    return PC_OK;
}

/* The arena's size from the sizing pass's parts (L->size), at most 512 MiB. */
static pc_status pc_arena_size(const pc_builder *b, pc_layout *L)
{
    size_t k;
    L->slot_bytes = b->any_io ? pc_round((b->n_inputs + b->n_outputs) * sizeof(pc_slot) + 1) : 0;
    L->size = pc_round(sizeof(pc_model)) + pc_round(L->n_plans * sizeof(pc_plan)) + L->slot_bytes +
              pc_round(2 * (L->n_meta + 1) * sizeof(char *)) + pc_round(L->meta_bytes + 1) +
              L->act_bytes + 2 * PC_ALIGN;
    for (k = 0; k < PC_REGIONS; k++)
        L->size += L->region[k];
    if (L->size > ((size_t)1 << 29))
        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "model needs a %zu-byte arena (limit 512 MiB)",
                       L->size);
    return PC_OK;
}

/* The pass's records and the one-pose compiler's state (keep end). */
static pc_status pc_pass_start(pc_pass *pp, const pc_options *opts)
{
    pc_program_limits limits;
    pc_status st;
    if ((st = pc_pass_alloc(pp->b, pp)) != PC_OK || (opts && (opts->flags & PC_LOAD_NO_PROGRAMS)))
        return st;
    limits.ops = !opts ? 0 : opts->program_ops > PC_MAX_PROGRAM_OPS ? PC_MAX_PROGRAM_OPS : opts->program_ops;
    limits.interpret = opts && (opts->flags & PC_LOAD_INTERPRET);
    return pc_program_start(pp, &limits);
}

pc_status pc_plan_build(pc_builder *b, const pc_options *opts, void *buf, size_t buf_size,
                        pc_model **model_out)
{
    pc_layout L;
    pc_pass pp;
    pc_scratch_mark pass_mark;
    uint8_t *arena;
    pc_model *m;
    pc_status st;
    memset(&L, 0, sizeof L);
    memset(&pp, 0, sizeof pp);
    pp.b = b;
    pc_batches(b, opts, &L);
    pass_mark = pc_scratch_save(&b->scratch, PC_KEEP);
    pc_pass_bounds(b, &pp);
    if ((st = pc_pass_start(&pp, opts)) != PC_OK)
        return st;
    if ((st = pc_plan_pass(&pp, &L, NULL)) != PC_OK)
        return st;
    if (!(opts && (opts->flags & PC_LOAD_NO_METADATA)) && (st = pc_count_meta(b, &L)) != PC_OK)
        return st;
    if ((st = pc_arena_size(b, &L)) != PC_OK)
        return st;
    pc_scratch_restore(&b->scratch, pass_mark);
    pc_pass_exact(b, &pp);
    if ((st = pc_pass_start(&pp, opts)) != PC_OK)
        return st;
    /* From here on the arena is in use too: the load's peak is the larger of the two. */
    b->peak_unplaced = b->scratch.peak;
    b->scratch.peak = b->scratch.used[PC_KEEP] + b->scratch.used[PC_WORK];
    if ((st = pc_arena(b, L.size, buf, buf_size, &arena)) != PC_OK)
        return st;
    m = pc_layout_model(b, &L, arena, &pp);
    m->owns_arena = buf == NULL;
    pp.fill = 1;
    if ((st = pc_plan_pass(&pp, &L, m)) != PC_OK) {
        if (!buf)
            free(arena);
        return st;
    }
    *model_out = m;
    return PC_OK;
}
