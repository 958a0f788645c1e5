/* Layer 6, planner: a plan under construction, shared by the planner (plan.c) and the
 * one-pose program pass (program.c). */
#ifndef PC_DRAFT_H
#define PC_DRAFT_H

#include "op.h"

/* One kernel launch of a plan under construction: value ids instead of pointers. */
typedef struct pc_draft {
    pc_kernel_fn fn;
    int32_t *io;        /* value ids: inputs then outputs */
    uint32_t n_io;
    void *prm;
    size_t prm_size;
    size_t n;
    int sop;            /* pc_prep.sop of the node */
} pc_draft;

typedef struct pc_plan_draft {
    size_t batch;
    pc_draft *drafts;
    size_t n_drafts;
    size_t **loc;       /* per draft, per io: location code (see PC_LOC_NONE) */
    size_t *io_loc;     /* graph inputs then outputs */
    size_t act_bytes;
} pc_plan_draft;

/* Location code: bit 0 set = constant region; SIZE_MAX = absent. */
#define PC_LOC_NONE ((size_t)-1)

/* The value whose storage v uses (itself unless it is a view). */
static inline int32_t pc_root(const pc_builder *b, int32_t v)
{
    while (b->values[v].alias >= 0)
        v = b->values[v].alias;
    return v;
}

#endif
