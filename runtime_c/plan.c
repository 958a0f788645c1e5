/* Planning: for each batch size, prepare every remaining node (shapes, kernel,
 * parameters), place run-time values by liveness (greedy first fit), then pack plans,
 * metadata, constants and activations into one arena. pc_run then does no shape work:
 * it walks a precomputed array of kernel launches. */
#include "plan.h"
#include "program.h"

#include <stdlib.h>
#include <string.h>

#define PC_INF_STEP 0x7fffffff

static pc_status pc_add_draft(pc_builder *b, pc_plan_draft *pd, const pc_prep *p)
{
    pc_draft *d;
    size_t j;
    if (pd->n_drafts == b->n_nodes)
        return pc_fail(b->err, PC_ERR_GRAPH, "more kernel launches than nodes");
    d = &pd->drafts[pd->n_drafts++];
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
    d->sop = p->sop;
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

/* Prepares every remaining node for this batch: output shapes, kernels, drafts. */
static pc_status pc_plan_steps(pc_builder *b, size_t batch, pc_plan_draft *pd)
{
    size_t i, j;
    pc_status st;
    /* At most one launch per node; every field is written by pc_add_draft. */
    pd->n_drafts = 0;
    pd->drafts = pc_scratch_alloc_raw(&b->scratch, (b->n_nodes + 1) * sizeof *pd->drafts);
    if (!pd->drafts)
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
    for (i = 0; i < b->n_inputs; i++) {
        const pc_io *io = &b->inputs[i];
        pc_value *in = &b->values[io->id];
        in->dtype = io->dtype;
        in->rank = io->rank;
        in->count = 1;
        for (j = 0; j < (size_t)io->rank; j++) {
            in->dims[j] = j == 0 && !b->any_io ? (int64_t)batch : io->dims[j];
            in->count *= (size_t)in->dims[j];
        }
        in->def = -1;
    }
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
        if ((st = pc_add_draft(b, pd, &p)) != PC_OK)
            return st;
    }
    if (!b->any_io) {
        const pc_value *o = &b->values[b->outputs[0].id];
        if (o->dtype != PC_F32 || o->rank != 2 || o->dims[0] != (int64_t)batch ||
            o->dims[1] != PC_POSE_WIDTH)
            return pc_fail(b->err, PC_ERR_CONTRACT,
                           "output 'corrected' is %s of rank %d (%lld x %lld) for N=%zu, the "
                           "contract needs float32 [N,7]", pc_dtype_name(o->dtype), o->rank,
                           (long long)(o->rank > 0 ? o->dims[0] : -1),
                           (long long)(o->rank > 1 ? o->dims[1] : -1), batch);
    }
    return PC_OK;
}

/* First and last step using each storage root; graph inputs and outputs live from
 * before the first step and past the last one. */
static void pc_plan_lifetimes(pc_builder *b, const pc_plan_draft *pd)
{
    size_t i, j;
    for (i = 0; i < pd->n_drafts; i++) {
        const pc_draft *d = &pd->drafts[i];
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
    for (i = 0; i < b->n_inputs; i++) {
        const int32_t r = pc_root(b, b->inputs[i].id);
        b->values[r].def = -1;
        if (b->values[r].last < 0)
            b->values[r].last = 0;
    }
    for (i = 0; i < b->n_outputs; i++) {
        const int32_t r = pc_root(b, b->outputs[i].id);
        if (!b->values[r].cdata) {
            b->values[r].last = PC_INF_STEP;
            if (b->values[r].def == PC_INF_STEP)
                b->values[r].def = -1;
        }
    }
}

/* Greedy first-fit of the roots over their lifetimes, in order of definition. */
static pc_status pc_plan_place(pc_builder *b, pc_plan_draft *pd)
{
    size_t i, k, n_roots = 0;
    int32_t *roots;
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
    return PC_OK;
}

/* Every operand as a location code: activation offset or constant slot. */
static pc_status pc_plan_locate(pc_builder *b, pc_plan_draft *pd, size_t batch,
                                size_t *const_bytes)
{
    size_t i, j;
    const size_t n_io = b->n_inputs + b->n_outputs;
    pd->batch = batch;
    pd->loc = pc_scratch_alloc(&b->scratch, (pd->n_drafts + 1) * sizeof(size_t *));
    pd->io_loc = pc_scratch_alloc(&b->scratch, (n_io + 1) * sizeof(size_t));
    if (!pd->loc || !pd->io_loc)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (i = 0; i < pd->n_drafts; i++) {
        const pc_draft *d = &pd->drafts[i];
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
    for (i = 0; i < n_io; i++) {
        const int32_t r = pc_root(b, i < b->n_inputs ? b->inputs[i].id
                                                     : b->outputs[i - b->n_inputs].id);
        pd->io_loc[i] = b->values[r].cdata ? pc_const_loc(b, r, const_bytes)
                                           : b->values[r].offset << 1;
    }
    return PC_OK;
}


/* One-pose plans: consecutive MLP layers, each reading the one before's output, become
 * one launch (pc_gemm_chain_kernels) that runs them in turn as before. */
static pc_status pc_chain_dense(pc_builder *b, pc_plan_draft *pd)
{
    size_t i = 0, w = 0, j, k;
    while (i < pd->n_drafts) {
        const pc_kernel_fn fn = pd->drafts[i].fn;
        const int rows = fn == pc_gemm_rows_kernels[0] || fn == pc_gemm_rows_kernels[1];
        for (j = i + 1; rows && j < pd->n_drafts && pd->drafts[j].fn == fn &&
                        pc_root(b, pd->drafts[j].io[0]) == pc_root(b, pd->drafts[j - 1].io[3]);
             j++)
            ;
        if (rows && j - i >= 2) {
            pc_draft *d = &pd->drafts[w];
            const size_t n = j - i;
            const size_t prm_size = sizeof(pc_gemm_chain) + (n - 1) * sizeof(pc_gemm);
            pc_gemm_chain *q = pc_scratch_alloc(&b->scratch, prm_size);
            int32_t *io = pc_scratch_alloc(&b->scratch, (4 * n + 1) * sizeof(int32_t));
            const size_t n_out = pd->drafts[j - 1].n;
            const int avx2 = fn == pc_gemm_rows_kernels[1];
            if (!q || !io)
                return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
            q->n_layers = n;
            for (k = 0; k < n; k++) {
                memcpy(&q->layer[k], pd->drafts[i + k].prm, sizeof(pc_gemm));
                memcpy(io + 4 * k, pd->drafts[i + k].io, 4 * sizeof(int32_t));
            }
            d->fn = pc_gemm_chain_kernels[avx2];
            d->io = io;
            d->n_io = (uint32_t)(4 * n);
            d->prm = q;
            d->prm_size = prm_size;
            d->n = n_out;
            d->sop = 0;
            w++;
            i = j;
        } else {
            pd->drafts[w++] = pd->drafts[i++];
        }
    }
    pd->n_drafts = w;
    return PC_OK;
}

static pc_status pc_plan_batch(pc_builder *b, size_t batch, pc_plan_draft *pd,
                               size_t *const_bytes)
{
    pc_status st;
    if ((st = pc_plan_steps(b, batch, pd)) != PC_OK)
        return st;
    if (batch == 1 && ((st = pc_fuse_small_steps(b, pd)) != PC_OK ||
                       (st = pc_chain_dense(b, pd)) != PC_OK))
        return st;
    pc_plan_lifetimes(b, pd);
    if ((st = pc_plan_place(b, pd)) != PC_OK)
        return st;
    return pc_plan_locate(b, pd, batch, const_bytes);
}

/* Sizes of the arena's parts, known once every plan is drafted. */
typedef struct pc_layout {
    size_t max_batch, n_plans;
    pc_plan_draft *pds;
    size_t meta_bytes, slot_bytes, step_bytes, const_bytes, act_bytes, size;
} pc_layout;

/* Plans for N = 1, 16, 256, ... and max_batch: planning is most of the load time, and a
 * remainder below 16 poses runs pose by pose at little cost per pose. */
static pc_status pc_plan_all(pc_builder *b, const pc_options *opts, pc_layout *L)
{
    size_t k, i, batch;
    pc_status st;
    memset(L, 0, sizeof *L);
    L->max_batch = opts && opts->max_batch ? opts->max_batch : PC_DEFAULT_MAX_BATCH;
    if (L->max_batch > PC_MAX_MAX_BATCH)
        L->max_batch = PC_MAX_MAX_BATCH;
    for (k = 1; 2 * k <= L->max_batch; k *= 2)
        ;
    L->max_batch = k;
    for (k = 1; k < L->max_batch; k *= PC_PLAN_STRIDE)
        L->n_plans++;
    L->n_plans++;
    if (b->any_io) /* static shapes: one plan */
        L->n_plans = L->max_batch = 1;
    L->pds = pc_scratch_alloc(&b->scratch, L->n_plans * sizeof *L->pds);
    if (!L->pds)
        return pc_fail(b->err, PC_ERR_MEMORY, "out of memory");
    for (k = 0, batch = 1; k < L->n_plans; k++, batch *= PC_PLAN_STRIDE) {
        const pc_plan_draft *pd = &L->pds[k];
        if ((st = pc_plan_batch(b, batch < L->max_batch ? batch : L->max_batch, &L->pds[k],
                                &L->const_bytes)) != PC_OK)
            return st;
        if (pd->act_bytes > L->act_bytes)
            L->act_bytes = pd->act_bytes;
        L->step_bytes += pc_round(pd->n_drafts * sizeof(pc_step) + 1);
        for (i = 0; i < pd->n_drafts; i++)
            L->step_bytes += pc_round(pd->drafts[i].n_io * sizeof(void *) + 1) +
                             pc_round(pd->drafts[i].prm_size + 1);
    }
    for (i = 0; i < b->n_meta; i++)
        L->meta_bytes += b->meta[i].key.size + b->meta[i].value.size + 2;
    L->slot_bytes = b->any_io ? pc_round((b->n_inputs + b->n_outputs) * sizeof(pc_slot) + 1) : 0;
    L->size = pc_round(sizeof(pc_model)) + pc_round(L->n_plans * sizeof(pc_plan)) +
              L->slot_bytes + pc_round(2 * (b->n_meta + 1) * sizeof(char *)) +
              pc_round(L->meta_bytes + 1) + L->step_bytes + L->const_bytes + L->act_bytes +
              PC_ALIGN;
    if (L->size > ((size_t)1 << 29))
        return pc_fail(b->err, PC_ERR_UNSUPPORTED, "model needs a %zu-byte arena (limit 512 MiB)",
                       L->size);
    return PC_OK;
}

/* The arena: malloc'd, or the end of the caller's buffer (its start holds the scratch
 * still in use). */
static pc_status pc_arena(pc_builder *b, size_t size, void *buf, size_t buf_size,
                          uint8_t **arena)
{
    if (buf) {
        *arena = (uint8_t *)(((uintptr_t)buf + buf_size - size) / PC_ALIGN * PC_ALIGN);
        if ((uintptr_t)buf + buf_size < size || (uintptr_t)*arena < (uintptr_t)buf ||
            *arena < b->scratch.fixed)
            return pc_fail(b->err, PC_ERR_MEMORY, "the %zu-byte buffer is too small for the "
                           "model (pc_required_bytes)", buf_size);
    } else if (!(*arena = (uint8_t *)malloc(size))) {
        return pc_fail(b->err, PC_ERR_MEMORY, "cannot allocate the %zu-byte model arena", size);
    }
    memset(*arena, 0, size);
    return PC_OK;
}

static char *pc_copy_string(char *dst, pb_slice s, const char **out)
{
    if (s.size)
        memcpy(dst, s.data, s.size);
    dst[s.size] = '\0';
    *out = dst;
    return dst + s.size + 1;
}

/* Layout: model | plans | slots | metadata | steps (per plan: steps, io, params) |
 * constants | activations. Steps of one plan are contiguous so a single-pose run stays
 * in a few cache lines. */
static pc_model *pc_pack(const pc_builder *b, const pc_layout *L, uint8_t *arena)
{
    pc_model *m = (pc_model *)arena;
    uint8_t *cursor = arena + pc_round(sizeof(pc_model)), *const_base, *act_base;
    const size_t n_io = b->n_inputs + b->n_outputs;
    size_t i, j, k;
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
    m->n_meta = b->n_meta;
    m->meta_key = (const char **)cursor;
    m->meta_value = m->meta_key + b->n_meta + 1;
    cursor += pc_round(2 * (b->n_meta + 1) * sizeof(char *));
    for (s = (char *)cursor, i = 0; i < b->n_meta; i++) {
        s = pc_copy_string(s, b->meta[i].key, &m->meta_key[i]);
        s = pc_copy_string(s, b->meta[i].value, &m->meta_value[i]);
    }
    cursor += pc_round(L->meta_bytes + 1);
    const_base = cursor + L->step_bytes;
    act_base = const_base + L->const_bytes;
    act_base = (uint8_t *)(((uintptr_t)act_base + PC_ALIGN - 1) / PC_ALIGN * PC_ALIGN);
    for (i = 0; i < b->n_values; i++) {
        const pc_value *v = &b->values[i];
        if (v->cdata && v->const_slot >= 0)
            memcpy(const_base + v->const_offset, v->cdata, v->count * pc_dtype_size(v->dtype));
    }
#define PC_RESOLVE(loc) \
    ((loc) == PC_LOC_NONE ? NULL : ((loc)&1) ? (void *)(const_base + ((loc) >> 1)) \
                                             : (void *)(act_base + ((loc) >> 1)))
    for (k = 0; k < L->n_plans; k++) {
        pc_plan *plan = &m->plans[k];
        const pc_plan_draft *pd = &L->pds[k];
        pc_step *steps = (pc_step *)cursor;
        cursor += pc_round(pd->n_drafts * sizeof(pc_step) + 1);
        plan->batch = pd->batch;
        plan->steps = steps;
        plan->n_steps = pd->n_drafts;
        plan->in = (float *)PC_RESOLVE(pd->io_loc[0]);
        plan->t = m->takes_time ? (float *)PC_RESOLVE(pd->io_loc[1]) : NULL;
        plan->out = (const float *)PC_RESOLVE(pd->io_loc[b->n_inputs]);
        for (i = 0; m->slots && i < n_io; i++) {
            const pc_value *v = &b->values[i < b->n_inputs ? b->inputs[i].id
                                                           : b->outputs[i - b->n_inputs].id];
            m->slots[i].data = PC_RESOLVE(pd->io_loc[i]);
            m->slots[i].bytes = v->count * pc_dtype_size(v->dtype);
        }
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
            if (d->fn == k_scalar_program)
                pc_scalar_program_bind((pc_scalar_program *)cursor, io);
            cursor += pc_round(d->prm_size + 1);
        }
    }
#undef PC_RESOLVE
    return m;
}

pc_status pc_plan_build(pc_builder *b, const pc_options *opts, void *buf, size_t buf_size,
                        pc_model **model_out)
{
    pc_layout L;
    uint8_t *arena;
    pc_status st;
    if ((st = pc_plan_all(b, opts, &L)) != PC_OK ||
        (st = pc_arena(b, L.size, buf, buf_size, &arena)) != PC_OK)
        return st;
    *model_out = pc_pack(b, &L, arena);
    (*model_out)->owns_arena = buf == NULL;
    return PC_OK;
}
