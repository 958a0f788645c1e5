/* Layer 0, base: load-time scratch memory. Either a list of malloc'd blocks, or a bump
 * allocator over a caller's buffer (pc_load_into: no malloc at all). */
#ifndef PC_SCRATCH_H
#define PC_SCRATCH_H

#include "base.h"

typedef struct pc_scratch_block pc_scratch_block;
typedef struct pc_scratch {
    pc_scratch_block *head; /* heap mode */
    uint8_t *fixed;         /* fixed mode: next free byte of the caller's buffer */
    size_t fixed_left;
    size_t used_total;      /* bytes in use, rounded to PC_ALIGN */
    size_t peak;            /* most bytes in use at once: what a caller's buffer needs */
} pc_scratch;

/* A point to come back to: everything allocated after it is released at once. */
typedef struct pc_scratch_mark {
    pc_scratch_block *head;
    size_t head_used;
    uint8_t *fixed;
    size_t fixed_left, used_total;
} pc_scratch_mark;

/* A zeroed pc_scratch is in heap mode; this switches it to the caller's buffer. */
void pc_scratch_use_buffer(pc_scratch *s, void *buf, size_t size);
void *pc_scratch_alloc(pc_scratch *s, size_t size);     /* zeroed; NULL when exhausted */
void *pc_scratch_alloc_raw(pc_scratch *s, size_t size); /* not zeroed */
void pc_scratch_release(pc_scratch *s);
pc_scratch_mark pc_scratch_save(const pc_scratch *s);
void pc_scratch_restore(pc_scratch *s, pc_scratch_mark m);

#endif
