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
    size_t used_total;      /* bytes handed out, rounded to PC_ALIGN */
} pc_scratch;

/* A zeroed pc_scratch is in heap mode; this switches it to the caller's buffer. */
void pc_scratch_use_buffer(pc_scratch *s, void *buf, size_t size);
void *pc_scratch_alloc(pc_scratch *s, size_t size);     /* zeroed; NULL when exhausted */
void *pc_scratch_alloc_raw(pc_scratch *s, size_t size); /* not zeroed */
void pc_scratch_release(pc_scratch *s);

#endif
