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

void pc_scratch_use_buffer(pc_scratch *s, void *buf, size_t size)
{
    const uintptr_t start = (uintptr_t)buf, aligned = (start + PC_ALIGN - 1) / PC_ALIGN * PC_ALIGN;
    s->fixed = (uint8_t *)aligned;
    s->fixed_left = size > aligned - start ? size - (aligned - start) : 0;
}

/* Untouched scratch is never faulted in: big arrays whose entries are all written before
 * use (values, drafts) take it raw, so their unused capacity costs no page faults. */
void *pc_scratch_alloc_raw(pc_scratch *s, size_t size)
{
    pc_scratch_block *b = s->head;
    size_t need = pc_round(size);
    uint8_t *p;
    /* room for the rounding and a block header on either width of size_t */
    if (size > SIZE_MAX / 2)
        return NULL;
    if (need == 0)
        need = PC_ALIGN;
    if (s->fixed) {
        if (need > s->fixed_left)
            return NULL;
        p = s->fixed;
        s->fixed += need;
        s->fixed_left -= need;
        s->used_total += need;
        s->peak = s->used_total > s->peak ? s->used_total : s->peak;
        return p;
    }
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
    s->peak = s->used_total > s->peak ? s->used_total : s->peak;
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

pc_scratch_mark pc_scratch_save(const pc_scratch *s)
{
    pc_scratch_mark m;
    m.head = s->head;
    m.head_used = s->head ? s->head->used : 0;
    m.fixed = s->fixed;
    m.fixed_left = s->fixed_left;
    m.used_total = s->used_total;
    return m;
}

void pc_scratch_restore(pc_scratch *s, pc_scratch_mark m)
{
    while (s->head != m.head) {
        pc_scratch_block *next = s->head->next;
        free(s->head);
        s->head = next;
    }
    if (s->head)
        s->head->used = m.head_used;
    s->fixed = m.fixed;
    s->fixed_left = m.fixed_left;
    s->used_total = m.used_total;
}
