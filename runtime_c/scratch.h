/* Layer 0, base: load-time scratch memory with two ends. The keep end holds what lives
 * for the whole load or a plan pass (the graph scan's arrays, folded constants, a pass's
 * value records, a one-pose program under construction); the work end holds what one
 * node or one step of the planner needs for a moment. Each end is a stack: a mark taken
 * on it releases everything allocated on that end after it.
 *
 * Either malloc'd blocks (one list per end), or one caller's buffer (pc_load_into: no
 * malloc at all): the keep end grows up from its start, the work end down from its top,
 * and the top moves below the model's arena once the arena is placed. */
#ifndef PC_SCRATCH_H
#define PC_SCRATCH_H

#include "base.h"

typedef struct pc_scratch_block pc_scratch_block;

enum { PC_KEEP = 0, PC_WORK = 1 };

typedef struct pc_scratch {
    pc_scratch_block *head[2]; /* heap mode */
    uint8_t *lo, *hi;          /* fixed mode: [lo, hi) is free */
    int fixed;
    size_t used[2];            /* bytes in use per end, rounded to PC_ALIGN */
    size_t peak;               /* most bytes in use at once, both ends together */
} pc_scratch;

typedef struct pc_scratch_mark {
    int end;
    pc_scratch_block *head;
    size_t head_used;
    uint8_t *at;
    size_t used;
} pc_scratch_mark;

/* A zeroed pc_scratch is in heap mode; this switches it to the caller's buffer. */
void pc_scratch_use_buffer(pc_scratch *s, void *buf, size_t size);
/* Fixed mode: the work end's top (where the model's arena begins); the work end must be
 * empty. Returns 0 when top lies below what the keep end holds. */
int pc_scratch_set_top(pc_scratch *s, void *top);
void *pc_scratch_alloc(pc_scratch *s, int end, size_t size);     /* zeroed; NULL if full */
void *pc_scratch_alloc_raw(pc_scratch *s, int end, size_t size); /* not zeroed */
void pc_scratch_release(pc_scratch *s);
pc_scratch_mark pc_scratch_save(const pc_scratch *s, int end);
void pc_scratch_restore(pc_scratch *s, pc_scratch_mark m);

#endif
