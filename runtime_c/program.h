/* Layer 6, planner: one-pose programs. */
#ifndef PC_PROGRAM_H
#define PC_PROGRAM_H

#include "draft.h"

/* Turns each run of consecutive small steps of a one-pose plan (elementwise arithmetic,
 * comparisons, Where, slices, gathers, concatenations, sums over the last axis) into one
 * k_scalar_program launch. */
pc_status pc_fuse_small_steps(pc_builder *b, pc_plan_draft *pd);

#endif
