/* Load-time scratch memory, released (heap mode) or abandoned (fixed mode) before
 * pc_load_* returns. */
#include "scratch.h"

#include <stdlib.h>
#include <string.h>

struct pc_scratch_block {
    pc_scratch_block *next;
    size_t size, used;
    /* data follows, aligned by the allocation itself */
};

#define PC_BLOCK_HEADER (((sizeof(pc_scratch_block) + PC_ALIGN - 1) / PC_ALIGN) * PC_ALIGN)
#define PC_BLOCK_BYTES 16384

void pc_scratch_use_buffer(pc_scratch *s, void *buf, size_t size)
{
    const uintptr_t start = (uintptr_t)buf, aligned = (start + PC_ALIGN - 1) / PC_ALIGN * PC_ALIGN;
    const uintptr_t end = start + size;
    s->fixed = 1;
    s->lo = (uint8_t *)aligned;
    s->hi = (uint8_t *)(end > aligned ? end / PC_ALIGN * PC_ALIGN : aligned);
    if (s->hi < s->lo)
        s->hi = s->lo;
}

int pc_scratch_set_top(pc_scratch *s, void *top)
{
    uint8_t *t = (uint8_t *)((uintptr_t)top / PC_ALIGN * PC_ALIGN);
    if (!s->fixed)
        return 1;
    if (t < s->lo)
        return 0;
    s->hi = t;
    return 1;
}

static void pc_account(pc_scratch *s, int end, size_t need)
{
    s->used[end] += need;
    if (s->used[0] + s->used[1] > s->peak)
        s->peak = s->used[0] + s->used[1];
}

/* Untouched scratch is never faulted in: arrays whose entries are all written before use
 * take it raw, so their unused capacity costs no page faults. */
void *pc_scratch_alloc_raw(pc_scratch *s, int end, size_t size)
{
    pc_scratch_block *b = s->head[end];
    size_t need = pc_round(size);
    uint8_t *p;
    if (size > SIZE_MAX / 2)
        return NULL;
    if (need == 0)
        need = PC_ALIGN;
    if (s->fixed) {
        if (need > (size_t)(s->hi - s->lo))
            return NULL;
        if (end == PC_KEEP) {
            p = s->lo;
            s->lo += need;
        } else {
            s->hi -= need;
            p = s->hi;
        }
        pc_account(s, end, need);
        return p;
    }
    if (!b || b->size - b->used < need) {
        const size_t block = need > PC_BLOCK_BYTES ? need : PC_BLOCK_BYTES;
        b = (pc_scratch_block *)malloc(PC_BLOCK_HEADER + block);
        if (!b)
            return NULL;
        b->next = s->head[end];
        b->size = block;
        b->used = 0;
        s->head[end] = b;
    }
    p = (uint8_t *)b + PC_BLOCK_HEADER + b->used;
    b->used += need;
    pc_account(s, end, need);
    return p;
}

void *pc_scratch_alloc(pc_scratch *s, int end, size_t size)
{
    void *p = pc_scratch_alloc_raw(s, end, size);
    if (p)
        memset(p, 0, size);
    return p;
}

void pc_scratch_release(pc_scratch *s)
{
    int end;
    for (end = 0; end < 2; end++) {
        while (s->head[end]) {
            pc_scratch_block *next = s->head[end]->next;
            free(s->head[end]);
            s->head[end] = next;
        }
        s->used[end] = 0;
    }
}

pc_scratch_mark pc_scratch_save(const pc_scratch *s, int end)
{
    pc_scratch_mark m;
    m.end = end;
    m.head = s->head[end];
    m.head_used = s->head[end] ? s->head[end]->used : 0;
    m.at = end == PC_KEEP ? s->lo : s->hi;
    m.used = s->used[end];
    return m;
}

void pc_scratch_restore(pc_scratch *s, pc_scratch_mark m)
{
    const int end = m.end;
    while (s->head[end] != m.head) {
        pc_scratch_block *next = s->head[end]->next;
        free(s->head[end]);
        s->head[end] = next;
    }
    if (s->head[end])
        s->head[end]->used = m.head_used;
    if (s->fixed) {
        if (end == PC_KEEP)
            s->lo = m.at;
        else
            s->hi = m.at;
    }
    s->used[end] = m.used;
}
