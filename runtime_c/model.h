/* Layer 7, the loaded model: static plans of kernel launches in one arena. Written by
 * the planner, read by pc_run and the public accessors. */
#ifndef PC_MODEL_H
#define PC_MODEL_H

#include "kernels.h"

#define PC_PLAN_STRIDE 16

typedef struct pc_plan {
    size_t batch;
    pc_step *steps;
    size_t n_steps;
    float *in;
    float *t;           /* the time input's buffer; NULL when the model has none */
    const float *out;
} pc_plan;

/* A graph input or output of a model loaded with any names (conformance tests only). */
typedef struct pc_slot {
    void *data;
    size_t bytes;
} pc_slot;

struct pc_model {
    size_t arena_bytes;
    int owns_arena;     /* pc_free releases it (pc_load_memory/file) or not (pc_load_into) */
    size_t n_meta;
    const char **meta_key;
    const char **meta_value;
    size_t max_batch;
    size_t n_plans;
    pc_plan *plans;     /* batch 1, PC_PLAN_STRIDE, PC_PLAN_STRIDE^2, ..., max_batch */
    const uint8_t *act; /* the activations (the arena's last part), which tools tell from
                         * constants (tools/posecorr_plan.c) */
    size_t n_nodes;
    int takes_time;     /* the graph has the input 't' (pc_run_timed) */
    /* Checks of pc_run (see posecorr.h), the same for every model: unit quaternions in
     * and out; positions inside [lo, hi] (input_bounds; +-infinity when the caller
     * allowed a model without); a correction within the reach (correction_reach) kept as
     * the squared distance and cos^2 of half the angle (infinity and 0 without); times
     * inside [t_lo, t_hi] (time_bounds, models that take time). */
    float lo[3], hi[3]; /* run.c loads each as four floats, the fourth ignored: keep a
                         * field after hi */
    float reach_pos2, reach_cos2;
    int bounded;        /* box and reach finite (every exported model): a pose inside the
                         * box and a correction within the reach are finite, so pc_run
                         * leaves the finite tests to the models without */
    int has_span;
    float t_lo, t_hi;
    pc_slot *slots;     /* any-name models: inputs then outputs; NULL otherwise */
    size_t n_in_slots, n_out_slots;
    char message[PC_MESSAGE_SIZE];
};

/* Runs one plan on its own buffers (no copy in or out); the failing step goes into
 * the model's message. */
pc_status pc_run_steps(pc_model *m, const pc_plan *plan);

#endif
