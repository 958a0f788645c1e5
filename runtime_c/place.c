/* Where a plan's values, constants and steps go. */
#include "place.h"

#include <string.h>

size_t pc_region_round(size_t bytes)
{
    return (bytes + 7) / 8 * 8;
}

void *pc_region_take(pc_pass *pp, int region, size_t bytes)
{
    pc_region *r = &pp->region[region];
    void *at = pp->fill ? r->base + r->used : NULL;
    r->used += pc_region_round(bytes);
    return at;
}

/* ---- activation blocks ------------------------------------------------------------ */

pc_status pc_block_new(pc_pass *pp, size_t bytes, int32_t *block)
{
    const size_t size = pc_round(bytes + 1);
    size_t off = 0, m, id;
    for (id = 0; id < pp->cap_blocks && pp->blocks[id].refs; id++)
        ;
    if (id == pp->cap_blocks)
        return pc_fail(pp->b->err, PC_ERR_GRAPH, "more buffers alive at once than the scan "
                       "counted (%zu)", pp->cap_blocks);
    /* The live list is sorted by offset, so the first gap is one sweep away. */
    for (m = 0; m < pp->n_live; m++) {
        const pc_block *q = &pp->blocks[pp->live[m]];
        if (off + size <= q->off)
            break;
        if (q->off + q->size > off)
            off = q->off + q->size;
    }
    memmove(pp->live + m + 1, pp->live + m, (pp->n_live - m) * sizeof *pp->live);
    pp->live[m] = (int32_t)id;
    pp->n_live++;
    pp->blocks[id].off = off;
    pp->blocks[id].size = size;
    pp->blocks[id].refs = 1;
    pp->blocks[id].deferred = 0;
    if (id >= pp->blocks_high)
        pp->blocks_high = id + 1;
    if (off + size > pp->act_peak)
        pp->act_peak = off + size;
    *block = (int32_t)id;
    return PC_OK;
}

void pc_block_ref(pc_pass *pp, int32_t block)
{
    if (block >= 0)
        pp->blocks[block].refs++;
}

static void pc_block_free(pc_pass *pp, int32_t block)
{
    size_t m;
    for (m = 0; m < pp->n_live && pp->live[m] != block; m++)
        ;
    if (m == pp->n_live)
        return;
    memmove(pp->live + m, pp->live + m + 1, (pp->n_live - m - 1) * sizeof *pp->live);
    pp->n_live--;
    pp->blocks[block].refs = 0;
}

void pc_block_unref(pc_pass *pp, int32_t block)
{
    pc_block *q;
    if (block < 0)
        return;
    q = &pp->blocks[block];
    if (q->refs > 1) {
        q->refs--;
    } else if (pp->defer_frees) {
        q->deferred = 1; /* a program still reads it: kept until the program closes */
    } else {
        pc_block_free(pp, block);
    }
}

void pc_block_flush(pc_pass *pp)
{
    size_t id;
    for (id = 0; id < pp->cap_blocks; id++)
        if (pp->blocks[id].refs && pp->blocks[id].deferred)
            pc_block_free(pp, (int32_t)id);
}

void *pc_block_at(const pc_pass *pp, int32_t block)
{
    return pp->fill ? pp->act_base + pp->blocks[block].off : NULL;
}

/* ---- records ---------------------------------------------------------------------- */

pc_status pc_give_block(pc_pass *pp, int32_t id)
{
    pc_value *v = &pp->b->values[id];
    if (v->cdata)
        return PC_OK;
    return pc_block_new(pp, v->count * pc_dtype_size(v->dtype), &v->block);
}

void pc_drop(pc_pass *pp, int32_t id)
{
    pc_value *v;
    if (id < 0)
        return;
    v = &pp->b->values[id];
    if (!v->used)
        return;
    pc_block_unref(pp, v->block);
    pc_value_release(pp->b, id);
}

/* Data that may stay where it lies: inside a file the caller keeps (pc_options flag). */
static int pc_lies_in_file(const pc_builder *b, const void *data)
{
    const uint8_t *p = (const uint8_t *)data;
    return b->in_place && p >= b->file && p < b->file + b->file_size;
}

pc_status pc_locate(pc_pass *pp, const pc_value *v, void **at)
{
    size_t k, bytes;
    void *to;
    *at = NULL;
    if (!v->cdata) {
        if (v->block >= 0)
            *at = pc_block_at(pp, v->block);
        return PC_OK;
    }
    if (pc_lies_in_file(pp->b, v->cdata)) {
        *at = v->cdata;
        return PC_OK;
    }
    for (k = 0; v->ckey >= 0 && k < pp->n_placed; k++)
        if (pp->placed[k].key == v->ckey) {
            *at = pp->fill ? pp->region[PC_REGION_CONSTS].base + pp->placed[k].off : NULL;
            return PC_OK;
        }
    bytes = v->count * pc_dtype_size(v->dtype);
    if (v->ckey >= 0) {
        if (pp->n_placed == pp->cap_placed)
            return pc_fail(pp->b->err, PC_ERR_GRAPH, "more constants than the scan counted");
        pp->placed[pp->n_placed].key = v->ckey;
        pp->placed[pp->n_placed++].off = pp->region[PC_REGION_CONSTS].used;
    }
    to = pc_region_take(pp, PC_REGION_CONSTS, bytes + 1);
    if (to && bytes)
        memcpy(to, v->cdata, bytes);
    *at = to;
    return PC_OK;
}

/* ---- steps ------------------------------------------------------------------------ */

pc_status pc_emit_step(pc_pass *pp, pc_kernel_fn fn, const int32_t *ids, size_t n_ids,
                       const void *prm, size_t prm_size, size_t n)
{
    pc_step *s = pc_region_take(pp, PC_REGION_STEPS, sizeof *s);
    void **io = pc_region_take(pp, PC_REGION_IO, (n_ids + 1) * sizeof(void *));
    void *q = prm_size ? pc_region_take(pp, PC_REGION_PARAMS, prm_size) : NULL;
    size_t j;
    pc_status st;
    for (j = 0; j < n_ids; j++) {
        void *at = NULL;
        if (ids[j] >= 0 && (st = pc_locate(pp, &pp->b->values[ids[j]], &at)) != PC_OK)
            return st;
        if (io)
            io[j] = at;
    }
    if (s) {
        s->fn = fn;
        s->io = io;
        s->prm = q;
        s->n = n;
        if (q)
            memcpy(q, prm, prm_size);
    }
    pp->n_steps++;
    pp->last_step = s;
    pp->last_layer = 0;
    return PC_OK;
}
